"""The configuration of gain tuning, ``wbc-jax tune`` (:class:`TuneConfig`: its fields are the command's flags),
and the limits and hashes shared with the held-out evaluation's
(:class:`~wbc_jax.tuning.heldout_config.HeldoutConfig`), which ``wbc-jax tune`` also takes."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import pathlib
from typing import ClassVar

from wbc_jax.control.flags import ControllerFlags
from wbc_jax.core import constants
from wbc_jax.core.options import check_options, flat_dict, nested, option
from wbc_jax.jobs import grids
from wbc_jax.robot import model
from wbc_jax.robot.robots import robot_option
from wbc_jax.sim import physics, watchdog

CHECKPOINTS = ("tick", "none", "dots")
PUSH_SCALES = ("envelope", "lip")
MAX_BATCH = 10_000_000  # pushes of one step, candidates, held-out pushes: beyond it a typo
# The phases of a tuning run, in the order they run (each resumable).
PHASES = ("predict", "train", "quality", "profile", "cmaes", "random", "hybrid", "heldout", "report")
SEARCHES = ("cmaes", "random")
SEARCH_BACKENDS = ("auto", "jax", "warp")
ESTIMATORS = ("first-order", "smoothed", "interpolated")
PARAMETERISATIONS = ("gains", "scheduled")
# The default envelope (docs/tuning/README.md's bisection) and the hand-set row of every comparison (the
# default gains with a critically damped CoM loop) are the robot's (its description's package data files).


@dataclasses.dataclass(frozen=True)
class TuneConfig:
    """A tuning run (the defaults are small, for a CPU; the GPU sizes come as flags, e.g.
    ``--batch 1024``). The CLI flags of ``wbc-jax tune`` are generated from these fields, and
    their declared ranges are checked by :meth:`check`."""

    robot: str = robot_option()
    out: str = option("runs/tune", "output folder (resumes a run there)")
    phases: tuple[str, ...] = option(
        ("train", "cmaes", "random", "heldout", "report"),
        "what to run, in this "
        "order: predict (does the loss rank held-out survival), train (gradient "
        "tuning), quality (the gradient against zeroth-order estimates), profile "
        "(where a gradient step's time goes), cmaes and random (gradient-free "
        "searches), hybrid (with --budget-s: the gradient refining CMA-ES's set at "
        "half of each budget for the other half), heldout (every gain set on the "
        "held-out grid, variations, one-foot task and sinusoid), report "
        "(heldout.json, race.json, figures)",
        nargs="+",
        choices=PHASES,
        nonempty=True,
    )
    steps: int = option(8, "gradient steps (an upper bound with --budget-s)", ge=1, le=1_000_000)
    batch: int = option(4, "rollouts per gradient step (sampled afresh each step)", ge=1, le=MAX_BATCH)
    horizon: float = option(2.0, "seconds per training rollout", gt=0.0, le=constants.MAX_HORIZON_S, unit="s")
    seed: int = option(
        0, "seed of the sampled pushes, the searches and the held-out pushes", ge=0, le=constants.MAX_SEED
    )
    lr: float = option(0.05, "adam learning rate (on the unconstrained parameters)", gt=0.0, le=10.0)
    clip_norm: float = option(1.0, "global-norm gradient clipping", gt=0.0, le=1e6)
    budget_s: float = option(
        0.0,
        "wall-time budget of every method in seconds, compilation included (the race); "
        "0: the gradient runs --steps and the searches its simulated steps (and, with "
        "--wall-budget, its wall time)",
        ge=0.0,
        le=1e7,
        unit="s",
    )
    snapshots_s: tuple[float, ...] = option(
        (120.0, 300.0),
        "with --budget-s: wall times [s] at which each method's current gain set is also kept and held out",
        nargs="*",
        gt=0.0,
        le=1e7,
        unit="s",
    )
    parameterisation: str = option(
        "gains",
        "what is tuned: 'gains' (58 gains, 60 with --tune-regularisation) or "
        "'scheduled' (the same gains scheduled on the push state: 348 entries, "
        "wbc_jax/tuning/algorithms/schedule.py)",
        choices=PARAMETERISATIONS,
    )
    estimator: str = option(
        "first-order",
        "gradient estimator: 'first-order' (per-rollout reverse mode, robust "
        "mean), 'smoothed' (the same at antithetic Gaussian perturbations of the parameters: "
        "the gradient of the smoothed loss), 'interpolated' (first- and zeroth-order "
        "estimates of the smoothed loss mixed by their variances, Suh et al. 2022)",
        choices=ESTIMATORS,
    )
    smoothing_sigma: float = option(
        0.1,
        "std of the parameter perturbations (unconstrained units) of the smoothed "
        "and interpolated estimators and of the zeroth-order estimates",
        gt=0.0,
        le=100.0,
    )
    bias_factor: float = option(
        2.0,
        "interpolated: the first-order share is cut where the first- and zeroth-order "
        "means differ by more than this many standard errors of the zeroth-order one",
        gt=0.0,
        le=1e6,
    )
    window_s: float = option(
        0.0,
        "> 0: differentiate short windows of this length started from states along "
        "forward rollouts, with a terminal capturability cost (short-horizon gradients); "
        "0: the whole horizon",
        ge=0.0,
        le=constants.MAX_HORIZON_S,
        unit="s",
    )
    windows: int = option(
        4, "windows per forward rollout (with --window-s): --batch = rollouts x windows", ge=1, le=MAX_BATCH
    )
    terminal_weight: float = option(
        4.0,
        "weight of a window's terminal capturability cost (capture point and CoM speed at its last tick)",
        ge=0.0,
        le=1e6,
    )
    bound_factor: float = option(
        10.0, "gains (and regularisation) stay within [default / f, default * f]", gt=1.0, le=1e3
    )
    zeta_range: tuple[float, float] = option(
        (0.02, 2.0),
        "damping ratios of the CoM, angular-momentum and postural error dynamics stay in this range",
        nargs=2,
        gt=0.0,
        le=100.0,
        ordered=True,
    )
    tune_regularisation: bool = option(
        False,
        "also tune Reg.pinvDamp and Reg.KP_postural (not storable in a "
        "gains file; the evaluation then compiles per gain set)",
    )
    init_gains: str | None = option(
        None, "start from this gains file (inside the bounds; default: WBC's)", metavar="FILE", input_file=True
    )
    magnitude_range: tuple[float, float] = option(
        (0.6, 1.4),
        "push impulses as multiples of --push-scale in the push's direction",
        nargs=2,
        gt=0.0,
        le=100.0,
        ordered=True,
    )
    push_scale: str = option(
        "envelope",
        "what push impulses are multiples of, per direction: 'envelope' (the default "
        "gains' strict envelope, --envelope) or 'lip' (the feet-in-place LIP bound m omega d)",
        choices=PUSH_SCALES,
    )
    train_bodies: tuple[str, ...] = option(
        ("trunk", "pelvis"),
        "pushed bodies (bodies of the robot or roles)",
        nargs="+",
        nonempty=True,
        names=model.pushable_bodies,
    )
    controller: ControllerFlags = nested(ControllerFlags())
    duration_range: tuple[float, float] = option(
        (0.05, 0.3),
        "push durations [s]",
        nargs=2,
        ge=constants.MIN_PUSH_DURATION_S,
        le=constants.MAX_PUSH_DURATION_S,
        unit="s",
        ordered=True,
    )
    push_onset: float = grids.push_onset_option(0.2)
    friction_range: tuple[float, float] = option(
        (0.6, 1.2),
        "floor friction",
        nargs=2,
        ge=constants.FRICTION_RANGE[0],
        le=constants.FRICTION_RANGE[1],
        ordered=True,
    )
    mass_range: tuple[float, float] = option(
        (0.9, 1.1),
        "plant mass scale",
        nargs=2,
        ge=constants.MASS_SCALE_RANGE[0],
        le=constants.MASS_SCALE_RANGE[1],
        ordered=True,
    )
    joint_noise: float = option(
        0.01, "initial joint noise std [rad]", ge=0.0, le=constants.MAX_JOINT_NOISE_RAD, unit="rad"
    )
    envelope: str | None = option(
        None,
        "the default gains' envelope per direction, JSON (default: "
        "the robot description's default_envelope, package data; where it "
        "has none, --envelope-fraction x the LIP bound)",
        metavar="FILE",
        input_file=True,
    )
    envelope_fraction: float = option(
        0.5, "without --envelope: the default envelope as this fraction of the LIP bound", gt=0.0, le=10.0
    )
    solver_iterations: int | None = option(
        None,
        "contact-solver Newton iterations in training (default: the model's)",
        ge=1,
        le=constants.MAX_SOLVER_ITERATIONS,
    )
    ls_iterations: int | None = option(
        None,
        "contact-solver line-search iterations in training (default: the model's)",
        ge=1,
        le=constants.MAX_SOLVER_ITERATIONS,
    )
    solver_gradient: str = option(
        "implicit",
        "how reverse mode passes MJX's contact solver: 'implicit' (the "
        "implicit-function derivative at the converged solution: one Cholesky solve per "
        "physics step) or 'unrolled' (through every Newton and line-search iteration, "
        "run as a fixed-length scan); the same gradient, measured in docs/tuning/README.md",
        choices=physics.SOLVER_GRADIENTS,
    )
    checkpoint: str = option(
        "tick",
        "rematerialisation in the backward pass: 'tick' (each 10 ms tick recomputed), "
        "'dots' (the same, keeping its matrix products), 'none' (everything stored)",
        choices=CHECKPOINTS,
    )
    env_clip: float = option(
        3.0,
        "each rollout's gradient is clipped to this multiple of the batch's median "
        "per-rollout gradient norm before the batch mean (0: no per-rollout clipping); "
        "rollouts with a non-finite gradient are left out of the mean",
        ge=0.0,
        le=1e6,
    )
    keep_tracking: bool = option(
        False,
        "bounds that keep the seed's CoM sinusoid tracked: K_P,CoM x, y >= "
        f"{constants.TRACKING_KP_COM_FLOOR:g}, the yaw entries of K_I,w and of the "
        f"angular damping ratio >= {constants.TRACKING_YAW_FRACTION:g} x the WBC "
        "defaults (docs/tuning/README.md)",
    )
    search_backend: str = option(
        "auto",
        "physics engine of the gradient-free searches (auto: warp where available, "
        "else jax; the gradient always runs on jax)",
        choices=SEARCH_BACKENDS,
    )
    population: int = option(
        8,
        "CMA-ES / random-search candidates per generation (CMA-ES recombines the better half: at least 2)",
        ge=2,
        le=MAX_BATCH,
    )
    es_batch: int = option(0, "pushes per candidate (0: batch // (population + 1), at least 1)", ge=0, le=MAX_BATCH)
    es_sigma: float = option(0.5, "CMA-ES initial step / random-search spread (unconstrained units)", gt=0.0, le=100.0)
    wall_budget: bool = option(
        True, "without --budget-s: the searches also run until the gradient run's wall time is spent"
    )
    eval_pushes: int = option(16, "held-out pushes of the training distribution (phase predict)", ge=1, le=MAX_BATCH)
    eval_horizon: float = option(
        3.0, "seconds per held-out rollout of phase predict", gt=0.0, le=constants.MAX_HORIZON_S, unit="s"
    )
    quality_pushes: int = option(
        32,
        "phase quality: fixed held-out pushes of the training distribution whose mean "
        "loss the gradients are checked on (a multiple of --batch)",
        ge=1,
        le=MAX_BATCH,
    )
    quality_directions: int = option(
        16,
        "phase quality: antithetic random directions of the zeroth-order estimate "
        "on the quality pushes (0: from the antithetic pairs of the gradient program "
        "instead, one push each; no population program, no descent check)",
        ge=0,
        le=MAX_BATCH,
    )
    stall_timeout_s: float | None = option(
        None,
        "seconds a call of a tuning program may run on a device (one program per local GPU) before the run "
        "stops with an error naming the device and the call (default: max("
        f"{watchdog.MIN_STALL_S:g} s, {watchdog.STALL_FACTOR:g}x that program's slowest finished call), "
        f"{watchdog.FIRST_CHUNK_STALL_S:g} s for its first; compiling gets at least {watchdog.COMPILE_STALL_S:g} s)",
        gt=0.0,
        le=watchdog.MAX_STALL_S,
        unit="s",
    )

    # Fields that bound how a run proceeds, not what it computes: no part of its fingerprint or checkpoint keys.
    PROCEDURE: ClassVar[tuple[str, ...]] = ("stall_timeout_s",)

    def __post_init__(self):
        self.check()

    def check(self) -> None:
        """Every check that compiles nothing: the declared ranges, then what ties the flags together."""
        check_options(self)
        push_end = self.push_onset + self.duration_range[1]
        for name in ("horizon", "eval_horizon"):
            if getattr(self, name) <= push_end:
                raise ValueError(
                    f"--{name.replace('_', '-')} {getattr(self, name)} s must end after the push "
                    f"(onset {self.push_onset} + up to {self.duration_range[1]} s)"
                )
        if self.window_s and not (0.01 <= self.window_s < self.horizon):
            raise ValueError(
                f"--window-s {self.window_s} must be at least one tick (0.01 s) and shorter than "
                f"--horizon {self.horizon} s"
            )
        if self.estimator != "first-order" and self.batch % 2:
            raise ValueError(
                f"--estimator {self.estimator} pairs antithetic rollouts: --batch must be even, got {self.batch}"
            )
        if self.window_s and self.distinct_rollouts % self.windows:
            raise ValueError(
                f"--batch {self.batch} must be a multiple of --windows {self.windows}"
                + (" x 2 (antithetic pairs)" if self.pairs else "")
            )
        if self.quality_pushes % self.pushes_per_call:
            raise ValueError(
                f"--quality-pushes {self.quality_pushes} must be a multiple of the {self.pushes_per_call} "
                "pushes of one gradient program call (--batch, halved for antithetic pairs, divided by "
                "--windows with --window-s)"
            )
        if "hybrid" in self.phases and not self.budget_s:
            raise ValueError(
                "--phases hybrid is a method of the race: give --budget-s (it refines CMA-ES's set at "
                "half of each budget with the gradient for the other half)"
            )
        if self.parameterisation == "scheduled" and self.tune_regularisation:
            raise ValueError("--parameterisation scheduled schedules the gains only: drop --tune-regularisation")
        if self.out is not None and pathlib.Path(self.out).exists() and not pathlib.Path(self.out).is_dir():
            raise ValueError(f"--out {self.out} is a file; give a folder for the tune run")
        physics.PhysicsConfig(backend="jax", solver_iterations=self.solver_iterations, ls_iterations=self.ls_iterations)

    @property
    def input_files(self) -> dict:
        """{name: path or None} of the files a tuning result reads, for its provenance (sha256 each)."""
        return {"init_gains": self.init_gains, "envelope": self.envelope, "tasks": self.controller.tasks}

    @property
    def candidate_batch(self) -> int:
        """Pushes per candidate of the gradient-free searches."""
        return self.es_batch or max(1, self.batch // (self.population + 1))

    @property
    def pairs(self) -> bool:
        """The gradient batch comes in antithetic pairs (rows 2j, 2j + 1 share their push)."""
        return self.estimator != "first-order"

    @property
    def distinct_rollouts(self) -> int:
        """Distinct pushes (or window starts) of a gradient batch."""
        return self.batch // 2 if self.pairs else self.batch

    @property
    def pushes_per_call(self) -> int:
        """Pushes (whole-horizon rollouts, or forward rollouts of the windows) of one gradient program call."""
        return self.distinct_rollouts // (self.windows if self.window_s else 1)

    @property
    def searches(self) -> tuple[str, ...]:
        """The gradient-free searches among the phases."""
        return tuple(k for k in SEARCHES if k in self.phases)


def default_config() -> TuneConfig:
    return TuneConfig()


# Fields that do not change what the gradient training computes.
NOT_TRAINING = (
    "out",
    "phases",
    "population",
    "es_batch",
    "es_sigma",
    "wall_budget",
    "eval_pushes",
    "eval_horizon",
    "search_backend",
    "snapshots_s",
    "quality_pushes",
    "quality_directions",
    *TuneConfig.PROCEDURE,
)


def config_key(*configs, exclude=()) -> str:
    """A short hash of dataclass configs, less the ``exclude`` fields (checkpoints belong to one)."""
    blob = json.dumps([{k: v for k, v in flat_dict(c).items() if k not in exclude} for c in configs], sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]
