"""The closed loop's data: its settings, pushes, scenarios, carry and per-tick records.

Everything here is a frozen dataclass: :class:`SimConfig` (static settings) or a pytree of arrays
(:class:`Push`, :class:`Feedforward`, :class:`Scenario`, :class:`LoopState`, :class:`Trajectory`,
:class:`LossTrace`),
shared by the tick (:mod:`wbc_jax.sim.loop`) and its two drivers (:mod:`wbc_jax.sim.mjx_loop`,
:mod:`wbc_jax.sim.host_loop`).
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax.control.controller import ControllerState
from wbc_jax.control.gains import Gains
from wbc_jax.core import constants
from wbc_jax.core.types import Array, pytree_dataclass
from wbc_jax.sim import metrics as metrics_lib
from wbc_jax.sim import physics

MATMUL_PRECISIONS = ("highest", "default")
HOST_LOOPS = ("auto", "compiled", "python")


def traced_at_matmul_precision(fn):
    """Trace ``fn(loop, ...)`` (a method of :class:`wbc_jax.sim.loop.ClosedLoop` or a driver
    function taking the loop first) under the loop's matmul precision: the setting is read when
    JAX traces, so it is part of every program built from ``fn``."""

    @functools.wraps(fn)
    def traced(loop, *args, **kwargs):
        with jax.default_matmul_precision(loop.cfg.matmul_precision):
            return fn(loop, *args, **kwargs)

    return traced


@dataclasses.dataclass(frozen=True)
class SimConfig:
    """Static rollout settings.

    Attributes:
      control_dt: controller period (s); the physics step comes from the model (1 ms).
      duration: simulated time (s).
      push_body: body the pushes act on (at its CoM, world-axes force): a body name or a role of the
        robot description (``trunk``).
      record: keep per-tick trajectories (False in large sweeps: metrics only). A loop that
        differentiates its rollouts composes its own per-tick record instead
        (:func:`wbc_jax.sim.loop.compose`: ``trace``, ``remat``).
      physics: the physics backend and its solver settings.
      perturb_plant: the plant's friction and masses differ per environment (sweeps); False: the
        nominal model is simulated.
      matmul_precision: of the float32 matrix products in the loop's programs (controller and MJX
        physics): "highest" (full float32), or "default" (XLA's choice: TensorFloat-32, a 10-bit
        mantissa, on recent NVIDIA GPUs). Survival near a push's fall boundary hangs on it
        (BENCHMARKS.md); CPUs compute both in full float32.
      host_loop: how the C MuJoCo engine (``mujoco``) runs the ticks: "compiled" (the whole
        horizon as one XLA program calling C MuJoCo, :mod:`wbc_jax.sim.host_scan`), "python" (a
        Python loop of jitted ticks and threaded physics, :mod:`wbc_jax.sim.host_loop`; batches
        run in two pipelined halves), "auto" (compiled where the native step builds, python otherwise).
    """

    control_dt: float = constants.CONTROL_DT
    duration: float = 10.0
    push_body: str = "trunk"
    record: bool = True
    physics: physics.PhysicsConfig = physics.PhysicsConfig()
    perturb_plant: bool = False
    matmul_precision: str = "highest"
    host_loop: str = "auto"

    def __post_init__(self):
        for name in ("control_dt", "duration"):
            value = getattr(self, name)
            if (
                isinstance(value, bool)
                or not isinstance(value, (int, float))
                or not (math.isfinite(value) and value > 0)
            ):
                raise ValueError(f"{name} must be a positive finite number of seconds, got {value!r}")
        if self.matmul_precision not in MATMUL_PRECISIONS:
            raise ValueError(f"unknown matmul_precision {self.matmul_precision!r}; valid: {list(MATMUL_PRECISIONS)}")
        if self.host_loop not in HOST_LOOPS:
            raise ValueError(f"unknown host_loop {self.host_loop!r}; valid: {list(HOST_LOOPS)}")


@pytree_dataclass
class Push:
    """External pushes (P of them), world-axes forces at the CoM of a body.

    Attributes: force (P, 3) N; onset (P,) s; duration (P,) s; body (P,) int32 body ids
    (-1: ``SimConfig.push_body``).
    """

    force: Array
    onset: Array
    duration: Array
    body: Array


def no_push(dtype=jnp.float32) -> Push:
    return Push(
        force=jnp.zeros((1, 3), dtype),
        onset=jnp.zeros(1, dtype),
        duration=jnp.zeros(1, dtype),
        body=jnp.full(1, -1, jnp.int32),
    )


SHARE_SNAP = 1e-6


def push_forces(push: Push, t, step: float | None = None):
    """Each push's force (..., P, 3) at time t (numpy or JAX arrays alike).

    With ``step`` (the physics step, s): the mean force over the step [t, t + step), i.e. the force
    times the fraction of the step the push covers. A physics step applies its force for the whole
    step, so the simulated impulse is then exactly force x duration for any onset and duration (a
    push edge that is not on a step, or float rounding of t at an edge, would otherwise add or drop
    a whole step: a 10 % error on a 10 ms push)."""
    if step is None:
        on = (t >= push.onset) & (t < push.onset + push.duration)
        return push.force * on[..., None]
    lo = t if hasattr(t, "clip") else np.asarray(t)
    covered = (lo + step).clip(None, push.onset + push.duration) - lo.clip(push.onset, None)
    share = covered.clip(0.0, step) / step
    # Within SHARE_SNAP of 0 or 1 (1 ns of a 1 ms step): exactly 0 or 1, so that a push edge on the
    # step grid gives the same force in programs that round t differently (a compiled and a Python
    # loop), bit for bit; pushes off the grid keep their exact share.
    share = (share >= 1.0 - SHARE_SNAP) + (share > SHARE_SNAP) * (share < 1.0 - SHARE_SNAP) * share
    return push.force * share[..., None]


def push_force(push: Push, t) -> Array:
    """Total push force (3,) at time t (numpy or JAX arrays alike)."""
    return push_forces(push, t).sum(-2)


@pytree_dataclass
class Feedforward:
    """Joint torques added to the controller's over a window of ticks (zero-order hold at the
    control rate): at tick ``k`` with ``0 <= k - start < T`` the plant gets
    ``clip(tau_WBC + torque[k - start], -limit, limit)``, the controller's own torques otherwise
    (:func:`feedforward_torque`). A driver argument, None by default (the loop's programs are then
    those without it); the trajectory optimiser of ``wbc-jax limit`` searches over ``torque``.

    Attributes: start () int32, the window's first tick; torque (T, n) N m.
    """

    start: Array
    torque: Array


def feedforward_torque(ff: Feedforward | None, k, tau: Array, limit) -> Array:
    """(n,) the torques the plant gets at tick ``k``: the controller's saturated ``tau`` (n,)
    plus ``ff``'s torque of that tick, saturated at +-``limit`` N m (a number or per joint (n,);
    ``ff`` None: ``tau``)."""
    if ff is None:
        return tau
    i = k - ff.start
    T = ff.torque.shape[0]
    inside = (i >= 0) & (i < T)
    u = ff.torque[jnp.clip(i, 0, T - 1)].astype(tau.dtype)
    limit = jnp.asarray(limit, tau.dtype)
    return jnp.where(inside, jnp.clip(tau + u, -limit, limit), tau)


@pytree_dataclass
class Scenario:
    """What an environment of a batch varies (a leading batch axis in a sweep).

    push: :class:`Push`; gains: :class:`wbc_jax.control.gains.Gains`; joint_offset (n,) rad added to the
    initial posture; friction () floor friction of the plant; mass_scale () of the plant's masses.
    """

    push: Push
    gains: Gains
    joint_offset: Array
    friction: Array
    mass_scale: Array


@pytree_dataclass
class LoopState:
    """Carry of the closed loop besides the physics: controller state, metrics, where each fully
    active contact was set down (K, 3) and its normal then (K, 3), the initial CoM height, and
    the normal force (K,) the simulator applied at each contact in the last physics step (+inf
    before the first step: every contact counts as touching) along the tick's contact normals
    (K, 3), for contact detection."""

    controller: ControllerState
    metrics: metrics_lib.Metrics
    anchors: Array
    anchor_normals: Array
    com0_height: Array
    contact_normals: Array
    measured_normal: Array


@pytree_dataclass
class Trajectory:
    """Per-tick record (time-major), when ``SimConfig.record``; K contacts, D wrench rows.

    t (T,), qpos (T, nq), com (T, 3), com_ref (T, 3), tau (T, n), f_cmd (T, D), f_meas (T, D),
    Ldot_star (T, 6), Ldot_meas (T, 6), activation (T, K), contact_pos (T, K, 3),
    contact_normal (T, K, 3), qp_infeasible (T,), qp_violation (T,), push (T, 3), s (T, n),
    s_des (T, n), task_err (T, m): the motion tasks' errors in stack order (m = 0 without tasks).
    ``f_meas`` is what the simulator applied during the tick's last physics step (NaN on the
    'warp' backend, which does not expose it per environment).
    """

    t: Array
    qpos: Array
    com: Array
    com_ref: Array
    tau: Array
    f_cmd: Array
    f_meas: Array
    Ldot_star: Array
    Ldot_meas: Array
    activation: Array
    contact_pos: Array
    contact_normal: Array
    qp_infeasible: Array
    qp_violation: Array
    push: Array
    s: Array
    s_des: Array
    task_err: Array


@pytree_dataclass
class LossTrace:
    """Per-tick quantities for smooth losses (time-major under scan): the record of a loop composed
    with ``trace=``:func:`wbc_jax.sim.loop.smooth_trace`.

    com (T, 3), com_ref (T, 3), com_vel (T, 3): CoM, its reference, its velocity (world);
    tau (T, n): applied torques; support_xy (T, F, 2): xy of the F support corners (the CoP
    rectangles' corners of the soles, world); com_height0 (T,): the initial CoM height;
    foot_normal (T, 2, 3): the soles' normals (world).
    """

    com: Array
    com_ref: Array
    com_vel: Array
    tau: Array
    support_xy: Array
    com_height0: Array
    foot_normal: Array
