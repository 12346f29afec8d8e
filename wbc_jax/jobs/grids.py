"""The push grids' flags, shared by every job that sweeps pushes (push-sweep, envelope, limit, its
crocoddyl cross-check, the held-out evaluation, balance's push): ``--magnitudes LO HI N`` and
``--directions N`` turned into values, each axis checked against :data:`MAX_GRID_AXIS` before it is
built, and the push's length and start. Each is declared once here (its parsing, shown default and valid
range); a config names its default and help."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from wbc_jax.core import constants
from wbc_jax.core.options import option

MAX_GRID_AXIS = 100_000  # magnitudes (or directions) of one grid axis, checked before the axis is built


def magnitude_grid(values) -> tuple[float, ...]:
    """``--magnitudes LO HI N``: N evenly spaced values (N a whole number in [1, MAX_GRID_AXIS])."""
    lo, hi, n = (float(v) for v in values)
    if not (math.isfinite(lo) and math.isfinite(hi) and math.isfinite(n)):
        raise ValueError(f"--magnitudes LO HI N needs finite numbers, got {list(values)}")
    if n != int(n) or not 1 <= n <= MAX_GRID_AXIS:
        raise ValueError(f"--magnitudes LO HI N: N must be a whole number in [1, {MAX_GRID_AXIS:,}], got {n:g}")
    return tuple(float(x) for x in np.linspace(lo, hi, int(n)))


def show_magnitude_grid(values) -> tuple:
    """A grid of :func:`magnitude_grid` shown as the flag's ``LO HI N``."""
    values = np.asarray(values, float)
    return (values[0], values[-1], len(values))


def azimuths(count) -> tuple[float, ...]:
    """``--directions N``: N azimuths evenly spread over 360 deg from 0 (forward)."""
    n = float(count)
    if not math.isfinite(n) or n != int(n) or not 1 <= n <= MAX_GRID_AXIS:
        raise ValueError(f"--directions must be a whole number in [1, {MAX_GRID_AXIS:,}], got {count}")
    return tuple(float(x) for x in np.arange(int(n)) * 360.0 / int(n))


DIRECTIONS_HELP = "number of push azimuths over 360 deg (0 = forward, 90 = left)"


def magnitudes_option(default: tuple[float, ...], help: str, *, positive: bool = False) -> Any:
    """A ``LO HI N`` grid of push forces [N] in [0, MAX_PUSH_N] (``positive``: above 0)."""
    lower = {"gt": 0.0} if positive else {"ge": 0.0}
    return option(
        default,
        help,
        nargs=3,
        metavar=("LO", "HI", "N"),
        parse=magnitude_grid,
        show=show_magnitude_grid,
        **lower,
        le=constants.MAX_PUSH_N,
        unit="N",
        nonempty=True,
    )


def directions_option(default: tuple[float, ...], help: str = DIRECTIONS_HELP) -> Any:
    """``N`` push azimuths [deg] over 360 deg (:func:`azimuths`); shown as their number."""
    return option(default, help, metavar="N", parse=azimuths, show=len, ge=-360.0, le=360.0, unit="deg", nonempty=True)


def push_duration_option(default: float = 0.1, help: str = "push length [s]") -> Any:
    """A push's length [s], at least one physics step."""
    return option(default, help, ge=constants.MIN_PUSH_DURATION_S, le=constants.MAX_PUSH_DURATION_S, unit="s")


def push_onset_option(default: float = 0.5, help: str = "push start [s]") -> Any:
    """A push's start [s] from the rollout's start."""
    return option(default, help, ge=0.0, lt=constants.MAX_HORIZON_S, unit="s")
