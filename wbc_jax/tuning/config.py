"""The configuration of a tuning run (``wbc-jax tune``): its fields are the command's flags."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import pathlib

from wbc_jax.core import constants
from wbc_jax.core.types import option
from wbc_jax.sim import physics

CHECKPOINTS = ("tick", "none")
PUSH_SCALES = ("envelope", "lip")
ENVELOPE_FILE = pathlib.Path(__file__).resolve().parents[2] / "docs" / "tuning" / "default_envelope.json"


@dataclasses.dataclass(frozen=True)
class TuneConfig:
    """A tuning run (the defaults are small, for a CPU; the GPU sizes come as flags, e.g.
    ``--batch 1024``). The CLI flags of ``wbc-jax tune`` are generated from these fields."""

    out: str = option("runs/tune", "output folder (resumes a run there)")
    steps: int = option(8, "gradient steps")
    batch: int = option(4, "pushes per gradient step (sampled afresh each step)")
    horizon: float = option(2.0, "seconds per training rollout")
    seed: int = option(0, "seed of the sampled pushes, the searches and the held-out pushes")
    lr: float = option(0.05, "adam learning rate (on the unconstrained parameters)")
    clip_norm: float = option(1.0, "global-norm gradient clipping")
    bound_factor: float = option(10.0, "gains (and regularisation) stay within [default / f, default * f]")
    zeta_range: tuple[float, float] = option((0.02, 2.0), "damping ratios of the CoM, angular-momentum and "
                                             "postural error dynamics stay in this range", nargs=2)  # fmt: skip
    tune_regularisation: bool = option(False, "also tune Reg.pinvDamp and Reg.KP_postural (not storable in a "
                                       "gains file; the evaluation then compiles per gain set)")  # fmt: skip
    init_gains: str | None = option(None, "start from this gains file (inside the bounds; default: WBC's)",
                                    metavar="FILE")  # fmt: skip
    magnitude_range: tuple[float, float] = option((0.6, 1.4), "push impulses as multiples of --push-scale in the "
                                                  "push's direction", nargs=2)  # fmt: skip
    push_scale: str = option("envelope", "what push impulses are multiples of, per direction: 'envelope' (the default "
                             "gains' strict envelope, --envelope) or 'lip' (the feet-in-place LIP bound m omega d)",
                             choices=PUSH_SCALES)  # fmt: skip
    train_bodies: tuple[str, ...] = option(("chest", "root_link"), "pushed bodies", nargs="+")
    tasks: str | None = option(None, "contact file of the two feet (JSON/YAML), as push-sweep --tasks: e.g. "
                               "experiments/tasks/feet_sole95.yaml (the CoP rectangles of the model's soles)",
                               metavar="FILE")  # fmt: skip
    angular_weight_soft: float = option(1.0, "the controller's angular_weight_soft, as push-sweep's (1: WBC)")
    duration_range: tuple[float, float] = option((0.05, 0.3), "push durations [s]", nargs=2)
    push_onset: float = option(0.2, "push start [s]")
    friction_range: tuple[float, float] = option((0.6, 1.2), "floor friction", nargs=2)
    mass_range: tuple[float, float] = option((0.9, 1.1), "plant mass scale", nargs=2)
    joint_noise: float = option(0.01, "initial joint noise std [rad]")
    envelope: str | None = option(None, "the default gains' envelope per direction, JSON (default: "
                                  "docs/tuning/default_envelope.json of this checkout if there, else "
                                  "--envelope-fraction x the LIP bound)", metavar="FILE")  # fmt: skip
    envelope_fraction: float = option(0.5, "without --envelope: the default envelope as this fraction of the LIP bound")
    solver_iterations: int | None = option(None, "contact-solver Newton iterations in training (default: the model's)")
    ls_iterations: int | None = option(None, "contact-solver line-search iterations in training (default: the model's)")
    checkpoint: str = option("tick", "rematerialisation in the backward pass", choices=CHECKPOINTS)
    env_clip: float = option(3.0, "each rollout's gradient is clipped to this multiple of the batch's median "
                             "per-rollout gradient norm before the batch mean (0: no per-rollout clipping); "
                             "rollouts with a non-finite gradient are left out of the mean")  # fmt: skip
    keep_tracking: bool = option(False, "bounds that keep the seed's CoM sinusoid tracked: K_P,CoM x, y >= "
                                 f"{constants.TRACKING_KP_COM_FLOOR:g}, the yaw entries of K_I,w and of the "
                                 f"angular damping ratio >= {constants.TRACKING_YAW_FRACTION:g} x the WBC "
                                 "defaults (docs/tuning/README.md)")  # fmt: skip
    population: int = option(8, "CMA-ES / random-search candidates per generation")
    es_batch: int = option(0, "pushes per candidate (0: batch // (population + 1), at least 1)")
    es_sigma: float = option(0.5, "CMA-ES initial step / random-search spread (unconstrained units)")
    baselines: tuple[str, ...] = option(("cmaes", "random"), "gradient-free baselines at equal simulated steps",
                                        nargs="*")  # fmt: skip
    wall_budget: bool = option(True, "the baselines also run until the gradient run's wall time is spent")
    eval_pushes: int = option(16, "held-out pushes (the training distribution, another seed)")
    eval_horizon: float = option(3.0, "seconds per held-out rollout")

    def __post_init__(self):
        self.check()

    def check(self) -> None:
        """Every check that needs no model or compilation."""
        for name in ("steps", "batch", "population", "eval_pushes"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"--{name.replace('_', '-')} must be a whole number >= 1, got {v!r}")
        if isinstance(self.es_batch, bool) or not isinstance(self.es_batch, int) or self.es_batch < 0:
            raise ValueError(f"--es-batch must be a whole number >= 0, got {self.es_batch!r}")
        for name in ("horizon", "lr", "clip_norm", "eval_horizon", "es_sigma", "envelope_fraction",
                     "angular_weight_soft"):  # fmt: skip
            v = getattr(self, name)
            if isinstance(v, bool) or not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"--{name.replace('_', '-')} must be positive and finite, got {v!r}")
        if isinstance(self.env_clip, bool) or not (math.isfinite(self.env_clip) and self.env_clip >= 0):
            raise ValueError(f"--env-clip must be finite and >= 0, got {self.env_clip!r}")
        if not (math.isfinite(self.bound_factor) and self.bound_factor > 1.0):
            raise ValueError(f"--bound-factor must be > 1, got {self.bound_factor}")
        for name in ("zeta_range", "magnitude_range", "duration_range", "friction_range", "mass_range"):
            lo, hi = getattr(self, name)
            if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo <= hi):
                raise ValueError(f"--{name.replace('_', '-')} must be positive and ordered, got {(lo, hi)}")
        if not (math.isfinite(self.push_onset) and self.push_onset >= 0):
            raise ValueError(f"--push-onset must be >= 0, got {self.push_onset}")
        if not (math.isfinite(self.joint_noise) and self.joint_noise >= 0):
            raise ValueError(f"--joint-noise must be >= 0, got {self.joint_noise}")
        push_end = self.push_onset + self.duration_range[1]
        for name in ("horizon", "eval_horizon"):
            if getattr(self, name) <= push_end:
                raise ValueError(f"--{name.replace('_', '-')} {getattr(self, name)} s must end after the push "
                                 f"(onset {self.push_onset} + up to {self.duration_range[1]} s)")  # fmt: skip
        if not self.train_bodies:
            raise ValueError("--train-bodies: give at least one body")
        if self.push_scale not in PUSH_SCALES:
            raise ValueError(f"--push-scale must be one of {list(PUSH_SCALES)}, got {self.push_scale!r}")
        if self.checkpoint not in CHECKPOINTS:
            raise ValueError(f"--checkpoint must be one of {list(CHECKPOINTS)}, got {self.checkpoint!r}")
        unknown = sorted(set(self.baselines) - {"cmaes", "random"})
        if unknown:
            raise ValueError(f"--baselines: unknown {unknown}; valid: cmaes, random")
        physics.PhysicsConfig(backend="jax", solver_iterations=self.solver_iterations, ls_iterations=self.ls_iterations)
        for name, path in (("init-gains", self.init_gains), ("envelope", self.envelope), ("tasks", self.tasks)):
            if path is not None:
                p = pathlib.Path(path)
                if not p.is_file():
                    raise ValueError(f"--{name} {path} is not a file")

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
