"""The tuning loss: a smooth surrogate of strict push-recovery survival.

Strict survival (:data:`wbc_jax.core.constants.SURVIVAL_CRITERION`) fails in five ways: a fall, a
foot that slips (> 2 cm) or tilts (> 5 deg), a CoM still moving at the end (> 0.05 m/s), or a CoM
outside the support polygon at the end. Each has a smooth per-tick counterpart, averaged over the
T ticks of a rollout (B rollouts, F = 8 sole corners, n joints):

* ``capture``: the instantaneous capture point xi = c + v / omega (omega = sqrt(g / h0)) against
  the support polygon of the sole corners: relu(capture_margin - margin(xi))^2 / capture_scale^2
  (a linear inverted pendulum whose capture point leaves the polygon cannot stop on its feet);
* ``tilt``: 1 - n . n0 of each sole's normal against its initial one, over 1 - cos(tilt_scale)
  (~ (angle / 5 deg)^2);
* ``slip``: per sole, the mean squared xy displacement of its corners, over slip_scale^2;
* ``settle``: over the last ``settle_s`` of the rollout, |v_CoM|^2 / end_speed^2 and the CoM's
  own polygon margin (relu(-margin(c))^2 / capture_scale^2);
* ``height``: relu(height_frac h0 - h)^2 / capture_scale^2 (CoM dropping);
* ``com``: |c - c_ref|^2 / com_scale^2 (recovery of the reference);
* ``effort`` (tau / torque_scale)^2 and ``saturation`` relu(|tau| - 0.9 limit)^2 / (0.1 limit)^2, per
  joint: scale and limit are each joint's motor limit unless set (:meth:`LossConfig.with_motor_limits`:
  from the robot's model; one robot's motors may differ by a factor of ten between its joints).

The total per rollout is the weighted sum; training minimises the mean over the batch of
log(1 + total) (``robust``): a rollout that falls far saturates instead of dominating the batch's
gradient. Rank statistics (:func:`spearman`, :func:`auc`) measure how well the total predicts
strict survival on held-out pushes (``wbc-jax tune --phases predict``).

:func:`tuning_loop` is the closed loop of :mod:`wbc_jax.sim.loop` with a richer per-tick record
(:class:`TuneTrace`: the LossTrace plus the soles' normals and the QP-infeasibility flag, from
:func:`tune_trace`, the loop's recorder), read from the loop state the controller returns; nothing
of the closed loop itself changes.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax.core import constants
from wbc_jax.core.types import Array, pytree_dataclass
from wbc_jax.sim import loop as loop_lib
from wbc_jax.sim import metrics as metrics_lib
from wbc_jax.sim.state import LossTrace


@pytree_dataclass
class TuneTrace:
    """Per-tick record of a tuning rollout (time-major under scan; a batch axis under vmap).

    base: :class:`wbc_jax.sim.state.LossTrace` (com (T, 3), com_ref (T, 3), com_vel (T, 3), tau
    (T, n), support_xy (T, F, 2), com_height0 (T,)); foot_normal (T, 2, 3): the soles' normals
    (world); qp_infeasible (T,) bool: the force QP had no feasible solution (not differentiable).
    """

    base: LossTrace
    foot_normal: Array
    qp_infeasible: Array


def tune_trace(record: LossTrace, new_state, state, qpos: Array, qvel: Array) -> TuneTrace:
    """The recorder of :func:`tuning_loop` (:data:`wbc_jax.sim.loop.Recorder`): the tick's
    :class:`LossTrace` with the soles' normals and whether the force QP was infeasible this tick."""
    infeasible = new_state.metrics.qp_infeasible_ticks > state.metrics.qp_infeasible_ticks
    return TuneTrace(base=record, foot_normal=record.foot_normal, qp_infeasible=infeasible)


def tuning_loop(loop: loop_lib.ClosedLoop, remat: bool | str = False) -> loop_lib.ClosedLoop:
    """The closed loop (built with ``SimConfig.record`` False) whose per-tick record is a
    :class:`TuneTrace`, its tick rematerialised in reverse mode by ``remat``
    (:data:`wbc_jax.sim.loop.Trace`)."""
    return loop_lib.compose(loop, trace=loop_lib.smooth_trace, recorder=tune_trace, remat=remat)


TERMS = ("capture", "tilt", "slip", "settle", "height", "com", "effort", "saturation")
TORQUE_FIELDS = ("torque_scale", "torque_limit")  # N m, per joint where a tuple (LossConfig)


@dataclasses.dataclass(frozen=True)
class LossConfig:
    """Weights (w_*) and scales of the tuning loss (module docstring); all finite, scales > 0.

    ``torque_scale`` and ``torque_limit`` (N m): one value for every joint, or one per joint (n,);
    None: each joint's motor limit, filled in by :meth:`with_motor_limits` (the tuning problem does,
    from its robot's model) before the loss is evaluated."""

    w_capture: float = 1.0
    w_tilt: float = 1.0
    w_slip: float = 1.0
    w_settle: float = 1.0
    w_height: float = 1.0
    w_com: float = 0.1
    w_effort: float = 0.01
    w_saturation: float = 0.1
    capture_margin: float = 0.01
    capture_scale: float = 0.02
    tilt_scale_deg: float = constants.SURVIVAL_MAX_TILT_DEG
    slip_scale: float = constants.SURVIVAL_MAX_SLIP_M
    end_speed: float = constants.SURVIVAL_END_COM_SPEED
    settle_s: float = 0.5
    height_frac: float = 0.9
    com_scale: float = 0.02
    torque_scale: float | tuple[float, ...] | None = None
    torque_limit: float | tuple[float, ...] | None = None
    robust: bool = True

    def __post_init__(self):
        for name in TORQUE_FIELDS:  # per joint, as read back from a run's config.json (a list)
            if isinstance(getattr(self, name), (list, np.ndarray)):
                object.__setattr__(self, name, tuple(float(x) for x in getattr(self, name)))
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, bool) or (v is None and f.name in TORQUE_FIELDS):
                continue
            for x in v if f.name in TORQUE_FIELDS and isinstance(v, tuple) else (v,):
                if not (isinstance(x, (int, float)) and math.isfinite(x) and x >= 0):
                    raise ValueError(f"LossConfig.{f.name} must be finite and >= 0, got {v!r}")
                if not f.name.startswith("w_") and f.name != "capture_margin" and not x > 0:
                    raise ValueError(f"LossConfig.{f.name} must be positive, got {v!r}")
        if not self.height_frac < 1:
            raise ValueError(f"LossConfig.height_frac must be < 1, got {self.height_frac}")

    def with_motor_limits(self, motor_limits) -> LossConfig:
        """This config with each torque field left None set to the motor limits (n,) N m per joint
        (a robot's ``RobotIndex.torque_limit``); fields already set stay."""
        limits = tuple(float(x) for x in np.asarray(motor_limits, float).reshape(-1))
        return dataclasses.replace(self, **{k: limits for k in TORQUE_FIELDS if getattr(self, k) is None})

    def torque_scales(self) -> tuple[Array, Array]:
        """(effort scale, saturation limit), each () or (n,) N m; ValueError while one is None."""
        if self.torque_scale is None or self.torque_limit is None:
            raise ValueError(
                "LossConfig.torque_scale/torque_limit are None (each joint's motor limit): fill them with "
                "LossConfig.with_motor_limits(robot.index.torque_limit) before evaluating the loss"
            )
        return jnp.asarray(self.torque_scale), jnp.asarray(self.torque_limit)


def _margins(points: Array, p: Array) -> Array:
    """(T,) signed distance of p (T, 2) inside the convex hull of points (T, F, 2)."""
    return jax.vmap(metrics_lib.polygon_margin)(points, p)


def loss_terms(
    trace: TuneTrace,
    lc: LossConfig,
    n_ticks: int | None = None,
    control_dt: float = constants.CONTROL_DT,
    reference=None,
) -> dict:
    """Per-rollout loss terms (each (), a mean over ticks) of one trace, on its first ``n_ticks``
    ticks (None: all; a prefix equals the loss of a rollout of that horizon). ``reference``: (foot
    normals (2, 3), support corners (F, 2)) that tilt and slip are measured from (default: the
    trace's first tick; a window of a rollout passes the rollout's).

    Returns {term: ()} for :data:`TERMS` and ``total`` (the weighted sum)."""
    torque_scale, torque_limit = lc.torque_scales()  # first: a config without them fails before any work
    tr = jax.tree_util.tree_map(lambda x: x[:n_ticks], trace) if n_ticks is not None else trace
    b = tr.base
    T = b.com.shape[0]
    m_xi = _margins(b.support_xy, capture_point(b))
    capture = jnp.mean(jax.nn.relu(lc.capture_margin - m_xi) ** 2) / lc.capture_scale**2
    n0, support0 = (tr.foot_normal[0], b.support_xy[0]) if reference is None else reference
    cos_tilt = jnp.einsum("tfi,fi->tf", tr.foot_normal, n0)
    tilt = jnp.mean(jnp.sum(1.0 - cos_tilt, -1)) / (1.0 - math.cos(math.radians(lc.tilt_scale_deg)))
    F = b.support_xy.shape[1]
    d = b.support_xy - support0  # (T, F, 2)
    per_foot = jnp.mean(jnp.sum(d**2, -1).reshape(T, 2, F // 2), -1)  # (T, 2)
    slip = jnp.mean(jnp.sum(per_foot, -1)) / lc.slip_scale**2
    w = max(1, min(T, int(round(lc.settle_s / control_dt))))
    speed2 = jnp.sum(b.com_vel[-w:] ** 2, -1) / lc.end_speed**2
    m_com = _margins(b.support_xy[-w:], b.com[-w:, :2])
    settle = jnp.mean(speed2 + jax.nn.relu(-m_com) ** 2 / lc.capture_scale**2)
    height = jnp.mean(jax.nn.relu(lc.height_frac * b.com_height0 - b.com[:, 2]) ** 2) / lc.capture_scale**2
    com = jnp.mean(jnp.sum((b.com - b.com_ref) ** 2, -1)) / lc.com_scale**2
    effort = jnp.mean((b.tau / torque_scale) ** 2)
    saturation = jnp.mean((jax.nn.relu(jnp.abs(b.tau) - 0.9 * torque_limit) / (0.1 * torque_limit)) ** 2)
    terms = {
        "capture": capture,
        "tilt": tilt,
        "slip": slip,
        "settle": settle,
        "height": height,
        "com": com,
        "effort": effort,
        "saturation": saturation,
    }
    terms["total"] = sum(getattr(lc, f"w_{k}") * v for k, v in terms.items())
    return terms


def capture_point(b: LossTrace) -> Array:
    """(T, 2) the instantaneous capture point c + v / omega of a trace, omega = sqrt(g / h0)."""
    omega = jnp.sqrt(constants.GRAVITY / b.com_height0)[:, None]  # (T, 1)
    return b.com[:, :2] + b.com_vel[:, :2] / omega


def terminal_cost(trace: TuneTrace, lc: LossConfig) -> Array:
    """() the capturability of a window's last state: the capture term and the CoM-height term of
    :func:`loss_terms` at the last tick alone (a robot whose capture point is inside its support
    polygon, standing at height, can still stop on its feet)."""
    b = jax.tree_util.tree_map(lambda x: x[-1:], trace.base)
    m_xi = _margins(b.support_xy, capture_point(b))[0]
    capture = jax.nn.relu(lc.capture_margin - m_xi) ** 2 / lc.capture_scale**2
    height = jax.nn.relu(lc.height_frac * b.com_height0[0] - b.com[0, 2]) ** 2 / lc.capture_scale**2
    return lc.w_capture * capture + lc.w_height * height


def env_objective(total: Array, lc: LossConfig) -> Array:
    """Per-rollout objective of totals (any shape): log1p (``robust``) or the total itself."""
    return jnp.log1p(total) if lc.robust else total


def batch_objective(total: Array, lc: LossConfig) -> Array:
    """() the training objective of per-rollout totals (B,): the mean of :func:`env_objective`."""
    return jnp.mean(env_objective(total, lc))


def batch_objective_rows(total: Array, lc: LossConfig) -> Array:
    """(P,) the objective of each row of per-rollout totals (P, b): the mean of :func:`env_objective`."""
    return jnp.mean(env_objective(total, lc), axis=-1)


# ---------------------------------------------------------------------------------------------
# Does the loss predict survival? Rank statistics (host side, numpy)


def _ranks(x: np.ndarray) -> np.ndarray:
    """Average ranks (ties share their mean rank), 1-based."""
    x = np.asarray(x, float)
    order = np.argsort(x, kind="mergesort")
    ranks = np.empty(len(x))
    ranks[order] = np.arange(1, len(x) + 1)
    for v in np.unique(x):
        tie = x == v
        if tie.sum() > 1:
            ranks[tie] = ranks[tie].mean()
    return ranks


def spearman(x, y) -> float:
    """Spearman rank correlation of two (N,) samples (NaN if either is constant)."""
    rx, ry = _ranks(x), _ranks(y)
    if np.std(rx) == 0 or np.std(ry) == 0:
        return float("nan")
    return float(np.corrcoef(rx, ry)[0, 1])


def auc(loss, survived) -> float:
    """Probability that a survived rollout has a lower loss than a failed one (ties count 1/2):
    the ROC area of -loss as a survival predictor (NaN without both outcomes)."""
    loss, survived = np.asarray(loss, float), np.asarray(survived, bool)
    pos, neg = loss[survived], loss[~survived]
    if not len(pos) or not len(neg):
        return float("nan")
    less = (pos[:, None] < neg[None, :]).mean()
    ties = (pos[:, None] == neg[None, :]).mean()
    return float(less + 0.5 * ties)
