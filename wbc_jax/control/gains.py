"""The controller's gains: a pytree (batches of gain sets vmap, gradients flow),
their WBC defaults, checks and gains files."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax.core import loader
from wbc_jax.core.constants import GAIN_FIELDS, GAIN_RANGES, NON_NEGATIVE_GAINS
from wbc_jax.core.loader import echo
from wbc_jax.core.types import Array, pytree_dataclass
from wbc_jax.robot.description import RobotDescription


@pytree_dataclass
class Gains:
    """Controller gains (n joints; a leading batch axis for several gain sets).

    Attributes:
      kp_com, kd_com, ki_com: (3,) CoM PID (ki_com = 0: the WBC law; > 0: the seed's PID)
      kp_ang: (3,) on the angular momentum;  ki_ang: (3,) on its (linearised) integral
      kp_postural, kd_postural: (n,) postural task
    """

    kp_com: Array
    kd_com: Array
    ki_com: Array
    kp_ang: Array
    ki_ang: Array
    kp_postural: Array
    kd_postural: Array


def default_gains(robot: RobotDescription, dtype=jnp.float32) -> Gains:
    """The robot's default gains (:meth:`wbc_jax.robot.description.RobotDescription.default_gain_values`)."""
    return Gains(**{k: jnp.asarray(v, dtype) for k, v in robot.default_gain_values().items()})


def validate_gains(gains: Gains, n: int) -> None:
    """Raise ValueError (before any compilation) for wrong shapes, NaN/inf, negative gains or
    gains outside their stated ranges (:data:`wbc_jax.core.constants.GAIN_RANGES`)."""
    for name in GAIN_FIELDS:
        size = n if name.endswith("postural") else 3
        value = np.asarray(getattr(gains, name))
        if value.shape[-1:] != (size,):
            raise ValueError(f"gain {name} must have {size} entries (last axis), got shape {value.shape}")
        if not np.all(np.isfinite(value)):
            raise ValueError(f"gain {name} has NaN or infinite entries: {value.tolist()}")
        if np.any(value < 0):
            raise ValueError(f"gain {name} has negative entries: {value.tolist()}")
        lo, hi = GAIN_RANGES[name]
        if np.any(value > hi):
            raise ValueError(f"gain {name} has entries above its range [{lo:g}, {hi:g}]: max {float(value.max()):g}")


def gains_to_dict(gains: Gains) -> dict:
    """JSON-ready dict of lists."""
    return {k: np.asarray(getattr(gains, k)).tolist() for k in GAIN_FIELDS}


def gains_from_dict(values: dict, n: int = 23, dtype=jnp.float32, source: str = "gains") -> Gains:
    """Gains from a dict (e.g. a JSON gains file); names unknown/missing keys, checks values.

    A gains file must have strictly positive gains (a zero gain disables a task); only the CoM
    integral ki_com may be 0 (the WBC law has none)."""
    if not isinstance(values, dict):
        raise ValueError(f"{source}: must be a JSON object with keys {list(GAIN_FIELDS)}")
    unknown = sorted(set(values) - set(GAIN_FIELDS))
    missing = sorted(set(GAIN_FIELDS) - set(values))
    if unknown or missing:
        raise ValueError(f"{source}: unknown keys {unknown}, missing keys {missing}; expected {list(GAIN_FIELDS)}")
    arrays = {}
    for k in GAIN_FIELDS:
        size = n if k.endswith("postural") else 3
        try:
            arrays[k] = np.asarray(values[k], dtype=float)
        except (TypeError, ValueError):
            raise ValueError(f"{source}: gain {k} must be a list of {size} numbers, got {echo(values[k])}") from None
        if arrays[k].shape != (size,):  # one gain set: a list, not a table
            raise ValueError(f"{source}: gain {k} must be a list of {size} numbers, got shape {arrays[k].shape}")
    gains = Gains(**arrays)
    try:
        validate_gains(gains, n)
    except ValueError as err:
        raise ValueError(f"{source}: {err}") from None
    zero = {
        k: np.flatnonzero(arrays[k] <= 0).tolist()
        for k in GAIN_FIELDS
        if k not in NON_NEGATIVE_GAINS and np.any(arrays[k] <= 0)
    }
    if zero:
        raise ValueError(f"{source}: gains must be positive: non-positive entries (indices) {zero}")
    return jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype), gains)


def load_gains(path, n: int = 23, dtype=jnp.float32) -> Gains:
    """Read a gains JSON file (as written by ``wbc-jax tune`` or :func:`gains_to_dict`)."""
    values = loader.read_json(path, "gains")
    return gains_from_dict(values, n, dtype, source=f"gains file {path}")
