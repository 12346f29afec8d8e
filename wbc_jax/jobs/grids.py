"""The push grids' flags, shared by every job that sweeps pushes (push-sweep, envelope, limit, the
held-out evaluation): ``--magnitudes LO HI N`` and ``--directions N`` turned into values, each axis
checked against :data:`MAX_GRID_AXIS` before it is built."""

from __future__ import annotations

import math

import numpy as np

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
