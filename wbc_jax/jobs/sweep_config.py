"""The configuration of a push-recovery sweep (``wbc-jax push-sweep``; ``wbc-jax envelope`` uses
the same fields): the grid of pushes, the gain sets, the plant's variations, the engine and the
output folder. Its fields are the command's flags; :meth:`SweepConfig.check` validates them
before anything loads or compiles."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from wbc_jax.control.controller import FORCE_MODES, ControllerConfig, with_job_settings
from wbc_jax.control.torques import POSTURAL_VARIANTS
from wbc_jax.core.types import option
from wbc_jax.jobs import runs
from wbc_jax.sim import physics

SWEEP_TASKS = ("stand", "one-foot")
# The one-foot task (references.make_schedule) balances on the left foot from 7 to 9 s.
ONE_FOOT_WINDOW = (7.0, 9.0)
SUPPORTS = ("two-feet", "left-foot")
MAX_ENVS = 10_000_000  # a grid larger than this is a typo (its scenarios alone take ~3 GB of memory)


def _grid(values) -> tuple[float, ...]:
    """``--magnitudes LO HI N``: N evenly spaced values (N a whole number >= 1)."""
    lo, hi, n = (float(v) for v in values)
    if not (math.isfinite(lo) and math.isfinite(hi) and math.isfinite(n)):
        raise ValueError(f"--magnitudes LO HI N needs finite numbers, got {list(values)}")
    if n != int(n) or n < 1:
        raise ValueError(f"--magnitudes LO HI N: N must be a whole number >= 1, got {n:g}")
    return tuple(float(x) for x in np.linspace(lo, hi, int(n)))


def _show_grid(values) -> tuple:
    values = np.asarray(values, float)
    return (values[0], values[-1], len(values))


def _azimuths(count) -> tuple[float, ...]:
    """``--directions N``: N azimuths evenly spread over 360 deg from 0 (forward)."""
    n = float(count)
    if n != int(n) or n < 1:
        raise ValueError(f"--directions must be a whole number >= 1, got {count}")
    return tuple(float(x) for x in np.arange(int(n)) * 360.0 / int(n))


@dataclasses.dataclass(frozen=True)
class SweepConfig:
    """What a sweep covers; the defaults are the README's main job (a laptop CPU in a minute).
    The CLI flags of ``wbc-jax push-sweep`` are generated from these fields."""

    magnitudes: tuple[float, ...] = option(
        (20.0, 60.0, 100.0), "push force grid [N]: LO HI N", nargs=3, metavar=("LO", "HI", "N"),
        parse=_grid, show=_show_grid,
    )  # fmt: skip
    directions: tuple[float, ...] = option(
        (0.0, 90.0, 180.0, 270.0), "number of push azimuths over 360 deg (0 = forward, 90 = left)",
        metavar="N", parse=_azimuths, show=len,
    )  # fmt: skip
    elevation: float = option(0.0, "push elevation [deg]")
    push_duration: float = option(0.1, "push length [s]")
    push_onset: float = option(0.5, "push start [s]")
    body: str = option("chest", "pushed body")
    gains: str | None = option(None, "gains JSON file (the first gain set)", metavar="FILE")
    gain_sets: int = option(1, "gain sets: the first, then seeded log-uniform scalings of it")
    gain_scale_range: tuple[float, float] = option((0.5, 2.0), "range of those scalings", nargs=2)
    joint_noise: float = option(0.0, "initial joint noise std [rad]")
    friction: tuple[float, float] = option((1.0, 1.0), "floor friction range", nargs=2, metavar=("LO", "HI"))
    mass_scale: tuple[float, float] = option((1.0, 1.0), "plant mass scale range", nargs=2, metavar=("LO", "HI"))
    horizon: float = option(1.5, "seconds per rollout")
    task: str = option(
        "stand", "two feet (stand) or pushed in the single-support phase of the one-foot task "
        "(7-9 s: e.g. --push-onset 7.5 --horizon 9)", choices=SWEEP_TASKS,
    )  # fmt: skip
    forces: str = option("qp", "force distribution", choices=FORCE_MODES)
    postural: str = option("stable", "postural task variant", choices=POSTURAL_VARIANTS)
    angular_weight_soft: float = option(
        1.0, "soft momentum QP: weight of the angular-momentum rate against the linear one where a push asks for "
        "more than the feet can give (1: WBC; < 1: the CoM first, the upper body absorbs the rest)",
    )  # fmt: skip
    solver_iterations: int | None = option(None, "contact solver Newton iterations (default: the model's, 4)")
    seed: int = option(0, "seed of the random perturbations")
    tasks: str | None = option(None, "task/contact file (JSON/YAML), as balance --tasks", metavar="FILE")
    chunk_size: int = option(12, "environments per compiled batch")
    queue: int = option(
        1, "scenarios per batch slot (MJX backends): a fallen or diverged robot is retired and its slot "
        "starts the next scenario; same outcomes, fewer physics steps (1: off)",
    )  # fmt: skip
    backend: str = option("auto", "physics engine (auto: C MuJoCo on a CPU, MJX-Warp/JAX on a GPU)",
                          choices=physics.BACKENDS)  # fmt: skip
    out: str = option("runs/push_sweep", "output folder (a sweep resumes there)")

    def check(self) -> None:
        """Every check that needs no model or compilation (run first, before any file is written)."""
        if not self.magnitudes or not self.directions:
            raise ValueError("the grid is empty: give at least one magnitude and one direction")
        if any(not math.isfinite(m) or m < 0 for m in self.magnitudes):
            raise ValueError(f"--magnitudes: push forces must be finite and >= 0 N, got {list(self.magnitudes)}")
        if any(not math.isfinite(d) for d in self.directions):
            raise ValueError(f"--directions: azimuths must be finite, got {list(self.directions)}")
        for name in ("elevation", "push_duration", "push_onset", "horizon", "joint_noise"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value)):
                raise ValueError(f"--{name.replace('_', '-')} must be a finite number, got {value!r}")
            if name != "elevation" and value < 0:
                raise ValueError(f"--{name.replace('_', '-')} must be >= 0, got {value}")
        if self.horizon <= self.push_onset + self.push_duration:
            raise ValueError(
                f"--horizon {self.horizon} s must end after the push ({self.push_onset} + {self.push_duration} s)"
            )
        for name in ("gain_sets", "chunk_size", "queue"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"--{name.replace('_', '-')} must be a whole number >= 1, got {value!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"--seed must be a whole number >= 0, got {self.seed!r}")
        if self.size > MAX_ENVS:
            gb = self.size * 300 / 1e9  # bytes of scenario data per environment, roughly
            raise ValueError(f"the grid has {self.size:,} environments (about {gb:,.0f} GB of scenarios), more than "
                             f"{MAX_ENVS:,}; use a coarser grid")  # fmt: skip
        for name, path in (("tasks", self.tasks), ("gains", self.gains)):
            runs.check_input_file(path, name)
        if self.task not in SWEEP_TASKS:
            raise ValueError(f"unknown sweep task {self.task!r}; valid: {list(SWEEP_TASKS)}")
        if self.task == "one-foot":
            lo, hi = ONE_FOOT_WINDOW
            if not (lo <= self.push_onset and self.push_onset + self.push_duration <= hi):
                raise ValueError(
                    f"one-foot sweeps push during the single-support phase {lo}-{hi} s of the "
                    f"one-foot task: push onset {self.push_onset} s + duration "
                    f"{self.push_duration} s is outside it (e.g. --push-onset 7.5 --horizon 9)"
                )
        for name in ("friction", "mass_scale", "gain_scale_range"):
            lo, hi = getattr(self, name)
            if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo <= hi):
                raise ValueError(f"--{name.replace('_', '-')} range must be positive and ordered, got {(lo, hi)}")
        self.controller_config()
        physics.PhysicsConfig(backend=self.backend, solver_iterations=self.solver_iterations)

    def controller_config(self, base: ControllerConfig | None = None) -> ControllerConfig:
        """``base`` (default: the defaults) with this sweep's controller settings."""
        return with_job_settings(base, self.forces, self.postural, self.angular_weight_soft)

    @property
    def size(self) -> int:
        return len(self.magnitudes) * len(self.directions) * self.gain_sets

    @property
    def perturbs_plant(self) -> bool:
        return self.friction != (1.0, 1.0) or self.mass_scale != (1.0, 1.0)


def default_config() -> SweepConfig:
    return SweepConfig()
