"""The configuration of a tuning run (``wbc-jax tune``): its fields are the command's flags."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import pathlib

from wbc_jax.core import constants
from wbc_jax.core.options import check_options, option
from wbc_jax.robot import model
from wbc_jax.sim import physics

CHECKPOINTS = ("tick", "none")
PUSH_SCALES = ("envelope", "lip")
BASELINES = ("cmaes", "random")
MAX_BATCH = 10_000_000  # pushes of one step, candidates, held-out pushes: beyond it a typo
ENVELOPE_FILE = pathlib.Path(__file__).resolve().parents[2] / "docs" / "tuning" / "default_envelope.json"


@dataclasses.dataclass(frozen=True)
class TuneConfig:
    """A tuning run (the defaults are small, for a CPU; the GPU sizes come as flags, e.g.
    ``--batch 1024``). The CLI flags of ``wbc-jax tune`` are generated from these fields, and
    their declared ranges are checked by :meth:`check`."""

    out: str = option("runs/tune", "output folder (resumes a run there)")
    steps: int = option(8, "gradient steps", ge=1, le=1_000_000)
    batch: int = option(4, "pushes per gradient step (sampled afresh each step)", ge=1, le=MAX_BATCH)
    horizon: float = option(2.0, "seconds per training rollout", gt=0.0, le=constants.MAX_HORIZON_S, unit="s")
    seed: int = option(
        0, "seed of the sampled pushes, the searches and the held-out pushes", ge=0, le=constants.MAX_SEED
    )
    lr: float = option(0.05, "adam learning rate (on the unconstrained parameters)", gt=0.0, le=10.0)
    clip_norm: float = option(1.0, "global-norm gradient clipping", gt=0.0, le=1e6)
    bound_factor: float = option(10.0, "gains (and regularisation) stay within [default / f, default * f]",
                                 gt=1.0, le=1e3)  # fmt: skip
    zeta_range: tuple[float, float] = option((0.02, 2.0), "damping ratios of the CoM, angular-momentum and "
                                             "postural error dynamics stay in this range", nargs=2, gt=0.0, le=100.0,
                                             ordered=True)  # fmt: skip
    tune_regularisation: bool = option(False, "also tune Reg.pinvDamp and Reg.KP_postural (not storable in a "
                                       "gains file; the evaluation then compiles per gain set)")  # fmt: skip
    init_gains: str | None = option(None, "start from this gains file (inside the bounds; default: WBC's)",
                                    metavar="FILE", input_file=True)  # fmt: skip
    magnitude_range: tuple[float, float] = option((0.6, 1.4), "push impulses as multiples of --push-scale in the "
                                                  "push's direction", nargs=2, gt=0.0, le=100.0,
                                                  ordered=True)  # fmt: skip
    push_scale: str = option("envelope", "what push impulses are multiples of, per direction: 'envelope' (the default "
                             "gains' strict envelope, --envelope) or 'lip' (the feet-in-place LIP bound m omega d)",
                             choices=PUSH_SCALES)  # fmt: skip
    train_bodies: tuple[str, ...] = option(("chest", "root_link"), "pushed bodies", nargs="+", nonempty=True,
                                           names=model.pushable_bodies)  # fmt: skip
    tasks: str | None = option(None, "contact file of the two feet (JSON/YAML), as push-sweep --tasks: e.g. "
                               "experiments/tasks/feet_sole95.yaml (the CoP rectangles of the model's soles)",
                               metavar="FILE", input_file=True)  # fmt: skip
    angular_weight_soft: float = option(
        1.0, "the controller's angular_weight_soft, as push-sweep's (1: WBC)", gt=constants.ANGULAR_WEIGHT_RANGE[0],
        le=constants.ANGULAR_WEIGHT_RANGE[1],
    )  # fmt: skip
    duration_range: tuple[float, float] = option((0.05, 0.3), "push durations [s]", nargs=2, gt=0.0,
                                                 le=constants.MAX_PUSH_DURATION_S, unit="s", ordered=True)  # fmt: skip
    push_onset: float = option(0.2, "push start [s]", ge=0.0, lt=constants.MAX_HORIZON_S, unit="s")
    friction_range: tuple[float, float] = option((0.6, 1.2), "floor friction", nargs=2, ge=constants.FRICTION_RANGE[0],
                                                 le=constants.FRICTION_RANGE[1], ordered=True)  # fmt: skip
    mass_range: tuple[float, float] = option((0.9, 1.1), "plant mass scale", nargs=2, ge=constants.MASS_SCALE_RANGE[0],
                                             le=constants.MASS_SCALE_RANGE[1], ordered=True)  # fmt: skip
    joint_noise: float = option(0.01, "initial joint noise std [rad]", ge=0.0, le=constants.MAX_JOINT_NOISE_RAD,
                                unit="rad")  # fmt: skip
    envelope: str | None = option(None, "the default gains' envelope per direction, JSON (default: "
                                  "docs/tuning/default_envelope.json of this checkout if there, else "
                                  "--envelope-fraction x the LIP bound)", metavar="FILE", input_file=True)  # fmt: skip
    envelope_fraction: float = option(0.5, "without --envelope: the default envelope as this fraction of the LIP bound",
                                      gt=0.0, le=10.0)  # fmt: skip
    solver_iterations: int | None = option(None, "contact-solver Newton iterations in training (default: the model's)",
                                           ge=1, le=constants.MAX_SOLVER_ITERATIONS)  # fmt: skip
    ls_iterations: int | None = option(None, "contact-solver line-search iterations in training (default: the "
                                       "model's)", ge=1, le=constants.MAX_SOLVER_ITERATIONS)  # fmt: skip
    checkpoint: str = option("tick", "rematerialisation in the backward pass", choices=CHECKPOINTS)
    env_clip: float = option(3.0, "each rollout's gradient is clipped to this multiple of the batch's median "
                             "per-rollout gradient norm before the batch mean (0: no per-rollout clipping); "
                             "rollouts with a non-finite gradient are left out of the mean", ge=0.0,
                             le=1e6)  # fmt: skip
    keep_tracking: bool = option(False, "bounds that keep the seed's CoM sinusoid tracked: K_P,CoM x, y >= "
                                 f"{constants.TRACKING_KP_COM_FLOOR:g}, the yaw entries of K_I,w and of the "
                                 f"angular damping ratio >= {constants.TRACKING_YAW_FRACTION:g} x the WBC "
                                 "defaults (docs/tuning/README.md)")  # fmt: skip
    population: int = option(8, "CMA-ES / random-search candidates per generation (CMA-ES recombines the better "
                             "half: at least 2)", ge=2, le=MAX_BATCH)  # fmt: skip
    es_batch: int = option(0, "pushes per candidate (0: batch // (population + 1), at least 1)", ge=0, le=MAX_BATCH)
    es_sigma: float = option(0.5, "CMA-ES initial step / random-search spread (unconstrained units)", gt=0.0, le=100.0)
    baselines: tuple[str, ...] = option(("cmaes", "random"), "gradient-free baselines at equal simulated steps",
                                        nargs="*", choices=BASELINES)  # fmt: skip
    wall_budget: bool = option(True, "the baselines also run until the gradient run's wall time is spent")
    eval_pushes: int = option(16, "held-out pushes (the training distribution, another seed)", ge=1, le=MAX_BATCH)
    eval_horizon: float = option(3.0, "seconds per held-out rollout", gt=0.0, le=constants.MAX_HORIZON_S, unit="s")

    def __post_init__(self):
        self.check()

    def check(self) -> None:
        """Every check that compiles nothing: the declared ranges, then what ties the flags together."""
        check_options(self)
        push_end = self.push_onset + self.duration_range[1]
        for name in ("horizon", "eval_horizon"):
            if getattr(self, name) <= push_end:
                raise ValueError(f"--{name.replace('_', '-')} {getattr(self, name)} s must end after the push "
                                 f"(onset {self.push_onset} + up to {self.duration_range[1]} s)")  # fmt: skip
        if self.out is not None and pathlib.Path(self.out).exists() and not pathlib.Path(self.out).is_dir():
            raise ValueError(f"--out {self.out} is a file; give a folder for the tune run")
        physics.PhysicsConfig(backend="jax", solver_iterations=self.solver_iterations, ls_iterations=self.ls_iterations)

    @property
    def candidate_batch(self) -> int:
        """Pushes per candidate of the gradient-free searches."""
        return self.es_batch or max(1, self.batch // (self.population + 1))


def default_config() -> TuneConfig:
    return TuneConfig()


# Fields that do not change what the gradient training computes.
NOT_TRAINING = ("out", "population", "es_batch", "es_sigma", "baselines", "wall_budget", "eval_pushes", "eval_horizon")


def config_key(*configs, exclude=()) -> str:
    """A short hash of dataclass configs, less the ``exclude`` fields (checkpoints belong to one)."""
    blob = json.dumps([{k: v for k, v in dataclasses.asdict(c).items() if k not in exclude} for c in configs],
                      sort_keys=True)  # fmt: skip
    return hashlib.sha256(blob.encode()).hexdigest()[:16]
