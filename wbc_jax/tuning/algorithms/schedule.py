"""Gains scheduled on the push state: the 348-entry parameterisation of gain tuning.

Each of the 58 tuned gain entries of :mod:`wbc_jax.tuning.algorithms.params` (K_P,CoM, the CoM damping ratios,
K_I,w, the angular damping ratios, postural k_p and damping ratios) becomes a function of the state
of the robot at every control tick:

    z(s) = b + W phi(s),        value(s) = exp(log lo + sigmoid(z(s)) (log hi - log lo))

with b (58,) the plain parameters, W (58, F) the schedule's weights and phi(s) (F = 5) features of the
base's horizontal motion, each in (-1, 1):

    phi = tanh([dx / D, dy / D, vx / V, vy / V, |v| / V])

(d: the base's xy displacement from its nominal position, v: its world-axes xy velocity; D = 5 cm,
V = 0.2 m/s), so P = 58 x (1 + 5) = 348 entries. At rest phi = 0 and the schedule's gains are the
plain ones; W = 0 is the plain parameterisation. Every value stays inside its bounds whatever the
state: the gains keep the stability conditions of Nava et al. (2016) at every instant (a schedule
that varies in time is not covered by that constant-gain proof).

The schedule is a pytree (:class:`GainSchedule`): a batch of schedules runs as data in one compiled
program, and :func:`scheduled_loop` makes any closed loop evaluate it at each tick, so the held-out
grid, its variations and the sinusoid run it on every engine. A gains file cannot hold it: it is
written as JSON of its own (``kind: gain_schedule``, :func:`load_schedule`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax.control.gains import Gains
from wbc_jax.core import loader
from wbc_jax.core.types import Array, pytree_dataclass
from wbc_jax.sim import loop as loop_lib

FEATURES = ("dx", "dy", "vx", "vy", "speed")
POSITION_SCALE_M = 0.05
SPEED_SCALE_MPS = 0.2
GROUPS = ("kp_com", "zeta_com", "ki_ang", "zeta_ang", "kp_postural", "zeta_postural")
KIND = "gain_schedule"


def features(qpos: Array, qvel: Array, origin: Array) -> Array:
    """(F,) the schedule's features of a state: qpos (nq,), qvel (nv,) of the free-floating robot
    (MuJoCo's free joint: world-axes linear velocity first), origin (2,) the base's nominal xy."""
    d = (qpos[:2] - origin) / POSITION_SCALE_M
    v = qvel[:2] / SPEED_SCALE_MPS
    speed = jnp.sqrt(jnp.sum(v**2) + 1e-6)  # smooth at rest
    return jnp.tanh(jnp.concatenate([d, v, speed[None]]))


@pytree_dataclass
class GainSchedule:
    """Gains as bounded functions of the push state (module docstring).

    Attributes:
      base: {group: (k,)} the unconstrained values at phi = 0.
      weights: {group: (k, F)} the schedule's weights.
      lo, hi: {group: (k,)} the bounds of each entry (0 < lo < hi).
      ki_com: (3,) the CoM integral gain (not tuned).
      origin: (2,) the base's nominal xy [m].
    """

    base: dict
    weights: dict
    lo: dict
    hi: dict
    ki_com: Array
    origin: Array

    def values(self, phi: Array) -> dict:
        """{group: (k,)} the bounded values at features ``phi`` (F,)."""
        out = {}
        for k in GROUPS:
            z = self.base[k] + self.weights[k] @ phi
            llo, lhi = jnp.log(self.lo[k]), jnp.log(self.hi[k])
            out[k] = jnp.exp(llo + jax.nn.sigmoid(z) * (lhi - llo))
        return out

    def gains_at(self, qpos: Array, qvel: Array) -> Gains:
        """The controller's gains at a state."""
        return self._gains(self.values(features(qpos, qvel, self.origin)))

    def at_rest(self) -> Gains:
        """The gains at phi = 0 (the plain parameterisation's)."""
        return self._gains(self.values(jnp.zeros(len(FEATURES), self.origin.dtype)))

    def _gains(self, v: dict) -> Gains:
        return Gains(
            kp_com=v["kp_com"],
            kd_com=2.0 * v["zeta_com"] * jnp.sqrt(v["kp_com"]),
            ki_com=self.ki_com,
            kp_ang=2.0 * v["zeta_ang"] * jnp.sqrt(v["ki_ang"]),
            ki_ang=v["ki_ang"],
            kp_postural=v["kp_postural"],
            kd_postural=2.0 * v["zeta_postural"] * jnp.sqrt(v["kp_postural"]),
        )

    def to_dict(self) -> dict:
        arr = lambda t: {k: np.asarray(v, float).tolist() for k, v in t.items()}  # noqa: E731
        return {
            "kind": KIND,
            "features": list(FEATURES),
            "position_scale_m": POSITION_SCALE_M,
            "speed_scale_mps": SPEED_SCALE_MPS,
            "base": arr(self.base),
            "weights": arr(self.weights),
            "lo": arr(self.lo),
            "hi": arr(self.hi),
            "ki_com": np.asarray(self.ki_com, float).tolist(),
            "origin": np.asarray(self.origin, float).tolist(),
        }


def size(schedule_params: dict) -> int:
    """Number of tuned entries of schedule parameters {"base": {...}, "weights": {...}}."""
    return int(sum(np.size(v) for t in schedule_params.values() for v in t.values()))


def init_params(plain: dict) -> dict:
    """Schedule parameters that start at the plain parameters ``plain`` {group: (k,)}: W = 0."""
    base = {k: plain[k] for k in GROUPS}
    return {"base": base, "weights": {k: jnp.zeros(v.shape + (len(FEATURES),), v.dtype) for k, v in base.items()}}


def from_params(params: dict, bounds, ki_com, origin) -> GainSchedule:
    """The :class:`GainSchedule` of schedule parameters, with the tuning bounds (differentiable)."""
    return GainSchedule(
        base=params["base"],
        weights=params["weights"],
        lo={k: bounds.lo[k] for k in GROUPS},
        hi={k: bounds.hi[k] for k in GROUPS},
        ki_com=jnp.asarray(ki_com),
        origin=jnp.asarray(origin),
    )


def is_schedule_file(path) -> bool:
    try:
        return loader.read_json(path, "schedule").get("kind") == KIND
    except (OSError, ValueError, AttributeError):
        return False


def load_schedule(path, dtype=np.float32) -> GainSchedule:
    """A schedule file (:meth:`GainSchedule.to_dict`), checked: groups, shapes, finite values, bounds."""
    try:
        data = loader.read_json(path, "schedule")
    except OSError as err:
        raise ValueError(f"schedule file {path} is unreadable: {err}") from None
    if data.get("kind") != KIND or list(data.get("features", [])) != list(FEATURES):
        raise ValueError(f"schedule file {path}: not a gain schedule with features {list(FEATURES)}")
    try:
        t = {part: {k: np.asarray(data[part][k], dtype) for k in GROUPS} for part in ("base", "weights", "lo", "hi")}
        ki_com, origin = np.asarray(data["ki_com"], dtype), np.asarray(data["origin"], dtype)
    except (KeyError, TypeError, ValueError) as err:
        raise ValueError(f"schedule file {path}: missing or malformed entry {err}") from None
    for k in GROUPS:
        n = t["base"][k].shape
        if t["weights"][k].shape != n + (len(FEATURES),) or t["lo"][k].shape != n or t["hi"][k].shape != n:
            raise ValueError(f"schedule file {path}: {k} has inconsistent shapes")
        if not all(np.all(np.isfinite(t[p][k])) for p in t) or not np.all((0 < t["lo"][k]) & (t["lo"][k] < t["hi"][k])):
            raise ValueError(f"schedule file {path}: {k} has non-finite values or bounds not 0 < lo < hi")
    if ki_com.shape != (3,) or origin.shape != (2,):
        raise ValueError(f"schedule file {path}: ki_com must have 3 entries and origin 2")
    return GainSchedule(**t, ki_com=ki_com, origin=origin)


def gains_of_schedule(schedule: GainSchedule, qpos: Array, qvel: Array) -> Gains:
    """The gains function of :func:`scheduled_loop` (:data:`wbc_jax.sim.loop.GainsAt`): the
    schedule's gains at the state."""
    return schedule.gains_at(qpos, qvel)


def scheduled_loop(loop: loop_lib.ClosedLoop) -> loop_lib.ClosedLoop:
    """A copy of a closed loop that takes a :class:`GainSchedule` where it took gains and evaluates
    it at every tick (its recorders kept)."""
    if loop.gains_at is gains_of_schedule:
        return loop
    return loop_lib.compose(loop, gains_at=gains_of_schedule)
