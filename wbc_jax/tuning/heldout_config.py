"""The configuration of the held-out evaluation (``wbc-jax heldout``, and the phase ``heldout`` of
``wbc-jax tune``, which takes these flags too: the held-out fields it shares with the tuning run, ``robot``
and the controller's flags, once)."""

from __future__ import annotations

import dataclasses

import numpy as np

from wbc_jax.control.flags import ControllerFlags
from wbc_jax.core import constants
from wbc_jax.core.options import check_input_file, check_options, nested, option
from wbc_jax.jobs import grids
from wbc_jax.jobs.sweep_config import ONE_FOOT_WINDOW
from wbc_jax.robot.robots import robot_option
from wbc_jax.sim import physics
from wbc_jax.tuning.config import MAX_BATCH

# Held-out variations, name: (pushed body role, push duration s, floor friction); magnitudes keep the grid's
# impulses.
VARIATIONS = {
    "left_hand": ("left_hand", 0.1, 1.0),
    "right_thigh": ("right_thigh", 0.1, 1.0),
    "duration_0.02s": ("trunk", 0.02, 1.0),
    "duration_0.5s": ("trunk", 0.5, 1.0),
    "friction_0.5": ("trunk", 0.1, 0.5),
}


@dataclasses.dataclass(frozen=True)
class HeldoutConfig:
    """The held-out evaluation (``wbc-jax heldout``, and the phase ``heldout`` of ``wbc-jax tune``); the
    defaults are the comparison's: every field is a flag of both commands.

    grid: trunk pushes of ``grid_duration`` s at ``grid_onset`` s over ``grid_magnitudes`` x
    ``grid_directions``, ``grid_horizon`` s. variations (:data:`VARIATIONS`): ``variation_magnitudes`` x
    ``variation_directions`` over the grid's impulse range. one_foot: pushes at ``one_foot_onset`` s of the
    one-foot task. sinusoid_s: seconds of the seed's CoM sinusoid (0: skip). robot, controller: the robot and
    the controller's flags of every closed loop (in ``wbc-jax tune``: the tuning run's)."""

    robot: str = robot_option()
    out: str = option("runs/heldout", "output folder (resumes a run there)")
    sets: tuple[str, ...] = option(
        ("default", "critical"),
        "gain sets held out: 'default' (the robot's gains), "
        "'critical' (the robot's hand-set row, e.g. assets/gains/com_critical_100.json) or "
        "NAME=FILE (a gains file or a gain-schedule file); wbc-jax tune adds its own",
        nargs="*",
    )
    grid_magnitudes: tuple[float, ...] = grids.magnitudes_option(
        grids.magnitude_grid((10.0, 400.0, 64)), "held-out grid of trunk push forces [N]: LO HI N"
    )
    grid_directions: tuple[float, ...] = grids.directions_option(
        grids.azimuths(32), "held-out push azimuths over 360 deg"
    )
    grid_duration: float = grids.push_duration_option(0.1, "held-out push length [s]")
    grid_onset: float = grids.push_onset_option(0.5, "held-out push start [s]")
    grid_horizon: float = option(3.0, "seconds per held-out rollout", gt=0.0, le=constants.MAX_HORIZON_S, unit="s")
    variations: tuple[str, ...] = option(
        tuple(VARIATIONS), "unseen variations of the grid's pushes", nargs="*", choices=tuple(VARIATIONS)
    )
    variation_magnitudes: int = option(16, "impulses per direction of each variation", ge=1, le=grids.MAX_GRID_AXIS)
    variation_directions: int = option(
        16, "directions of each variation and of the one-foot pushes", ge=1, le=grids.MAX_GRID_AXIS
    )
    one_foot: bool = option(True, "also push during the one-foot task's single-support phase")
    one_foot_onset: float = grids.push_onset_option(7.5, "one-foot push start [s]")
    one_foot_horizon: float = option(9.0, "seconds per one-foot rollout", gt=0.0, le=constants.MAX_HORIZON_S, unit="s")
    sinusoid_s: float = option(
        20.0, "seconds of the seed's CoM sinusoid (its RMSE; 0: skip)", ge=0.0, le=constants.MAX_HORIZON_S, unit="s"
    )
    sinusoid_backend: str = option("mujoco", "physics of the sinusoid", choices=physics.BACKENDS)
    heldout_backend: str = option(
        "auto", "physics of the held-out pushes (auto: warp on a GPU, C MuJoCo on a CPU)", choices=physics.BACKENDS
    )
    chunk_size: int = option(16384, "held-out environments per compiled batch", ge=1, le=MAX_BATCH)
    controller: ControllerFlags = nested(ControllerFlags())

    def __post_init__(self):
        self.check()

    def check(self) -> None:
        """Every check that compiles nothing: the declared ranges, then what ties the flags together."""
        check_options(self)
        longest = max([self.grid_duration] + [VARIATIONS[v][1] for v in self.variations])
        if self.grid_horizon <= self.grid_onset + longest:
            raise ValueError(
                f"held-out horizon {self.grid_horizon} s ends before the pushes ({self.grid_onset} + {longest} s)"
            )
        lo, hi = ONE_FOOT_WINDOW
        if self.one_foot and not (
            lo <= self.one_foot_onset
            and self.one_foot_onset + self.grid_duration <= hi
            and self.one_foot_horizon > self.one_foot_onset + self.grid_duration
        ):
            raise ValueError(f"one-foot pushes must fall in the single-support phase {ONE_FOOT_WINDOW} s")
        seen = set()
        for spec in self.sets:
            name, _, path = spec.partition("=")
            if not name or name in seen:
                raise ValueError(f"--sets: gain set {name!r} is empty or given twice")
            seen.add(name)
            if not path and name not in ("default", "critical"):
                raise ValueError(f"--sets entries are 'default', 'critical' or NAME=FILE, got {spec!r}")
            if path:
                check_input_file(path, f"--sets {name}")

    @property
    def grid_impulses(self) -> np.ndarray:
        """(M,) the grid's impulses [N s]."""
        return np.asarray(self.grid_magnitudes, float) * self.grid_duration


def heldout_default_config() -> HeldoutConfig:
    return HeldoutConfig()
