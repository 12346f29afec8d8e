"""[closed loop] The controller at 100 Hz on a physics backend at 1 kHz, zero-order hold.

A tick is two pure JAX functions around the physics:

    control(gains, state, qpos, qvel, k) -> (state, ctrl, record)     # controller + metrics
    <physics: n_sub steps with ctrl held and the push applied>        # physics.py
    measure(record, contact slots) -> record                           # measured wrenches

With an MJX backend (``jax``, ``warp``) the whole horizon is one ``lax.scan`` of ticks: jit it,
vmap it over scenarios, differentiate it (``jax``). With C MuJoCo (``mujoco``) the ticks run in a
Python loop: the jitted, vmapped ``control`` and the threaded C physics alternate
(:meth:`ClosedLoop.run_host`). Both paths compute the controller and the metrics with the same
code. A diverged environment (NaN) is frozen at its last finite state and flagged; a fall is
flagged and the simulation goes on, so one bad environment never poisons a batch. A sweep may
instead queue several scenarios per batch slot (:meth:`ClosedLoop.rollout_queue`): a fallen or
diverged robot is retired and its slot starts the next scenario.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import math
import os
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from wbc_jax import constants, dynamics, forces, physics
from wbc_jax import metrics as metrics_lib
from wbc_jax._mjx import mjx
from wbc_jax.controller import Controller, ControllerState
from wbc_jax.gains import Gains
from wbc_jax.model import Robot
from wbc_jax.references import Schedule
from wbc_jax.types import Array, pytree_dataclass

# Compiled programs of closed loops, by ClosedLoop.structure_key and batch shape (loops built alike,
# e.g. by repeated runs of a job in one process, share them).
PROGRAMS: dict = {}


MATMUL_PRECISIONS = ("highest", "default")


def _traced_at_matmul_precision(method):
    """Trace ``method`` of a :class:`ClosedLoop` under its config's matmul precision (the setting
    is read when JAX traces, so it is part of every program built from the method)."""

    @functools.wraps(method)
    def traced(self, *args, **kwargs):
        with jax.default_matmul_precision(self.cfg.matmul_precision):
            return method(self, *args, **kwargs)

    return traced


@dataclasses.dataclass(frozen=True)
class SimConfig:
    """Static rollout settings.

    Attributes:
      control_dt: controller period (s); the physics step comes from the model (1 ms).
      duration: simulated time (s).
      push_body: body the pushes act on (at its CoM, world-axes force).
      record: keep per-tick trajectories (False in large sweeps: metrics only).
      loss_trace: per tick, emit a small :class:`LossTrace` (smooth, differentiable losses; gain
        tuning) instead of a Trajectory; exclusive with ``record``.
      checkpoint: wrap the tick in ``jax.checkpoint`` (reverse mode: the residuals of one tick are
        recomputed instead of stored for the whole horizon; same values).
      physics: the physics backend and its solver settings.
      perturb_plant: the plant's friction and masses differ per environment (sweeps); False: the
        nominal model is simulated.
      matmul_precision: of the float32 matrix products in the loop's programs (controller and MJX
        physics): "highest" (full float32), or "default" (XLA's choice: TensorFloat-32, a 10-bit
        mantissa, on recent NVIDIA GPUs). Survival near a push's fall boundary hangs on it
        (BENCHMARKS.md); CPUs compute both in full float32.
    """

    control_dt: float = constants.CONTROL_DT
    duration: float = 10.0
    push_body: str = "chest"
    record: bool = True
    loss_trace: bool = False
    checkpoint: bool = False
    physics: physics.PhysicsConfig = physics.PhysicsConfig()
    perturb_plant: bool = False
    matmul_precision: str = "highest"

    def __post_init__(self):
        for name in ("control_dt", "duration"):
            value = getattr(self, name)
            if (
                isinstance(value, bool)
                or not isinstance(value, (int, float))
                or not (math.isfinite(value) and value > 0)
            ):
                raise ValueError(f"{name} must be a positive finite number of seconds, got {value!r}")
        if self.loss_trace and self.record:
            raise ValueError("loss_trace and record are exclusive (set record=False)")
        if self.matmul_precision not in MATMUL_PRECISIONS:
            raise ValueError(f"unknown matmul_precision {self.matmul_precision!r}; valid: {list(MATMUL_PRECISIONS)}")


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
    return Push(force=jnp.zeros((1, 3), dtype), onset=jnp.zeros(1, dtype), duration=jnp.zeros(1, dtype),
                body=jnp.full(1, -1, jnp.int32))  # fmt: skip


def push_forces(push: Push, t):
    """Each push's force (..., P, 3) at time t (numpy or JAX arrays alike)."""
    on = (t >= push.onset) & (t < push.onset + push.duration)
    return push.force * on[..., None]


def push_force(push: Push, t) -> Array:
    """Total push force (3,) at time t (numpy or JAX arrays alike)."""
    return push_forces(push, t).sum(-2)


@pytree_dataclass
class Scenario:
    """What an environment of a batch varies (a leading batch axis in a sweep).

    push: :class:`Push`; gains: :class:`wbc_jax.gains.Gains`; joint_offset (n,) rad added to the
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
    """Per-tick quantities for smooth losses (time-major under scan), when ``SimConfig.loss_trace``.

    com (T, 3), com_ref (T, 3), com_vel (T, 3): CoM, its reference, its velocity (world);
    tau (T, n): applied torques; support_xy (T, F, 2): xy of the F support corners (the CoP
    rectangles' corners of the soles, world); com_height0 (T,): the initial CoM height.
    """

    com: Array
    com_ref: Array
    com_vel: Array
    tau: Array
    support_xy: Array
    com_height0: Array


class ClosedLoop:
    """The closed loop of one environment, built by :func:`make_closed_loop`.

    Static structure (robot, schedule, controller, settings) is closed over; every method is pure
    in its array arguments.
    """

    def __init__(self, robot: Robot, schedule: Schedule, controller: Controller, cfg: SimConfig):
        idx = robot.index
        self.robot, self.idx, self.schedule, self.controller, self.cfg = robot, idx, schedule, controller, cfg
        self.physics_dt = float(robot.mj_model.opt.timestep)
        self.n_sub = physics.steps_per_tick(cfg.control_dt, self.physics_dt)
        self.n_ticks = int(round(cfg.duration / cfg.control_dt))
        if self.n_ticks < 1:
            raise ValueError(f"duration {cfg.duration} s is shorter than one control tick ({cfg.control_dt} s)")
        self.push_body = idx.body_id(cfg.push_body)
        # Bodies that must stay off the floor: all but the feet and the ankle links above them.
        feet_and_ankles = set(idx.foot_bodies.tolist()) | set(robot.mj_model.body_parentid[idx.foot_bodies].tolist())
        self.non_foot_bodies = np.array([b for b in range(1, robot.mj_model.nbody) if b not in feet_and_ankles])
        # The controller's own model: MJX's JAX implementation, whatever steps the plant.
        self.mx = mjx.put_model(robot.mj_model)
        self._d_template = mjx.make_data(robot.mj_model)
        # Gradients (a LossTrace) need MJX's JAX implementation.
        self.backend = physics.resolve_backend(cfg.physics.backend, differentiable=cfg.loss_trace)
        if self.backend == "warp" and controller.config.contact_detection:
            raise ValueError(
                "contact detection reads the simulator's contact forces, which the 'warp' backend does not "
                "expose per environment; use --backend jax or mujoco"
            )

    @property
    def contact_set(self):
        return self.controller.contact_set

    @functools.cached_property
    def structure_key(self) -> str:
        """A hash of everything that shapes this loop's compiled programs (the model, schedule,
        controller, contact set, motion tasks and settings): loops built alike share programs."""
        buf = np.zeros(mujoco.mj_sizeModel(self.robot.mj_model), np.uint8)
        mujoco.mj_saveModel(self.robot.mj_model, None, buf)
        sched = {k: np.asarray(v).tolist() if isinstance(v, np.ndarray) else repr(v)
                 for k, v in vars(self.schedule).items()}  # fmt: skip
        parts = (buf.tobytes(), repr(sched), repr(self.controller.config), repr(self.contact_set),
                 repr(self.controller.stack), repr(self.cfg))  # fmt: skip
        return hashlib.sha256(b"".join(p if isinstance(p, bytes) else p.encode() for p in parts)).hexdigest()

    # -- the controller side ------------------------------------------------------------------

    def terms(self, qpos: Array, qvel: Array) -> dynamics.DynamicsTerms:
        d = self._d_template.replace(qpos=qpos, qvel=jnp.asarray(qvel, qpos.dtype))
        return dynamics.terms(self.mx, d, self.idx, self.controller.frames)

    @_traced_at_matmul_precision
    def init(self, qpos0: Array) -> LoopState:
        """Loop state at the initial posture ``qpos0`` (nq,), zero velocity; it is also the
        controller's postural reference."""
        dtype = qpos0.dtype
        t0 = self.terms(qpos0, jnp.zeros(self.idx.nv, dtype))
        cset = self.contact_set
        R_bc = jnp.asarray(np.array([c.R_body_contact for c in cset.contacts]).reshape(-1, 3, 3), dtype)
        K = len(cset.contacts)
        normals = jnp.einsum("kij,kj->ki", t0.W_R_frames[:K], R_bc[:, :, 2])
        metrics = metrics_lib.initial(t0.W_p_CoM[2], dtype)
        return LoopState(
            controller=self.controller.init(t0), metrics=metrics, anchors=t0.W_p_frames[:K],
            anchor_normals=normals, com0_height=t0.W_p_CoM[2], contact_normals=normals,
            measured_normal=jnp.full(K, jnp.inf, dtype),
        )  # fmt: skip

    @_traced_at_matmul_precision
    def control(self, gains: Gains, state: LoopState, qpos: Array, qvel: Array, k: Array,
                physics_ok: Array, push: Push):  # fmt: skip
        """One control tick at the state (qpos, qvel) of tick ``k``.

        ``physics_ok``: () False when the last physics steps diverged (the state was frozen).
        Returns ``(state, ctrl (nu,), record)``; record is a :class:`Trajectory` (``f_meas`` and
        ``Ldot_meas`` still zero), a :class:`LossTrace` or None, by the settings."""
        cfg, idx = self.cfg, self.idx
        dtype = qpos.dtype
        t_now = k * cfg.control_dt
        terms = self.terms(qpos, qvel)
        ref = self.schedule.at(t_now, dtype)
        out, cstate = self.controller.step(gains, state.controller, terms, ref, t_now, state.measured_normal)
        ctrl = jnp.zeros(self.robot.mj_model.nu, dtype).at[idx.actuators].set(out.tau)
        metrics, anchors, normals = self._metrics(state, terms, ref, out, t_now, physics_ok)
        state = state.replace(controller=cstate, metrics=metrics, anchors=anchors, anchor_normals=normals,
                              contact_normals=out.contact_R[:, :, 2])  # fmt: skip
        record = None
        if cfg.record:
            record = Trajectory(
                t=t_now, qpos=qpos, com=terms.W_p_CoM, com_ref=ref.com_pos, tau=out.tau, f_cmd=out.f,
                f_meas=jnp.zeros_like(out.f), Ldot_star=out.Ldot_star, Ldot_meas=jnp.zeros(6, dtype),
                activation=out.activation, contact_pos=out.contact_pos,
                contact_normal=out.contact_R[:, :, 2], qp_infeasible=out.qp_infeasible,
                qp_violation=out.qp_violation, push=push_force(push, t_now), s=terms.s, s_des=ref.s_des,
                task_err=out.task_err,
            )  # fmt: skip
        elif cfg.loss_trace:
            record = LossTrace(
                com=terms.W_p_CoM, com_ref=ref.com_pos, com_vel=terms.W_v_CoM, tau=out.tau,
                support_xy=metrics_lib.support_corners(self.contact_set, out.contact_pos, out.contact_R)[:, :2],
                com_height0=state.com0_height,
            )  # fmt: skip
        return state, ctrl, record

    def _metrics(self, state: LoopState, terms, ref, out, t_now, physics_ok):
        """The running metrics after this tick, and the contacts' anchors (where and at what normal
        each fully active contact was set down). Evaluation only: no gradient flows through."""
        terms, ref, out = jax.lax.stop_gradient((terms, ref, out))
        normal = out.contact_R[:, :, 2]
        fully_active = out.activation >= 1.0
        anchors = jnp.where(fully_active[:, None], state.anchors, out.contact_pos)
        anchor_normals = jnp.where(fully_active[:, None], state.anchor_normals, normal)
        corners = metrics_lib.support_corners(self.contact_set, out.contact_pos, out.contact_R)
        new = metrics_lib.update(
            state.metrics, com=terms.W_p_CoM, com_ref=ref.com_pos, com_vel=terms.W_v_CoM, tau=out.tau,
            violation=out.qp_violation, infeasible=out.qp_infeasible, contact_pos=out.contact_pos,
            normals=normal, anchors=anchors, anchor_normals=anchor_normals, fully_active=fully_active,
            body_heights=terms.xpos[self.non_foot_bodies, 2], support=corners[:, :2],
            com0_height=state.com0_height, t_now=t_now, physics_ok=physics_ok,
        )  # fmt: skip
        return new, anchors, anchor_normals

    def step_push_forces(self, push: Push, k):
        """(n_sub, P, 3) each push's force during the physics steps of tick k: the one place push
        timing is computed (the host loop scatters these, so every backend pushes alike)."""
        t = k * self.cfg.control_dt + self.physics_dt * jnp.arange(self.n_sub)
        return jax.vmap(lambda s: push_forces(push, s))(t)

    def push_bodies(self, push: Push):
        """(P,) the body id of each push."""
        return jnp.where(push.body >= 0, push.body, self.push_body)

    def xfrc(self, push: Push, k):
        """(n_sub, nbody, 6) body wrenches of the physics steps of tick k (each push at its body)."""
        force = self.step_push_forces(push, k)
        out = jnp.zeros((self.n_sub, self.robot.mj_model.nbody, 6), force.dtype)
        return out.at[:, self.push_bodies(push), :3].add(force)

    @property
    def observes_contacts(self) -> bool:
        """The controller reads the measured contact forces (contact detection)."""
        return self.controller.config.contact_detection

    @_traced_at_matmul_precision
    def observe(self, state: LoopState, contact_pos, contact_force, contact_geom) -> LoopState:
        """Store the normal force (K,) the simulator applied at each contact (from the contact
        slots after the tick's physics, along the contact normals of the tick) for the next
        tick's contact detection."""
        cset = self.contact_set
        dtype = state.measured_normal.dtype
        K = len(cset.contacts)
        f = forces.measured_wrenches(cset, contact_pos.astype(dtype), contact_force.astype(dtype), contact_geom,
                                     self.robot.mj_model.ngeom, jnp.zeros((K, 3), dtype))  # fmt: skip
        n = state.contact_normals
        normal = jnp.stack([n[k] @ f[sl.start : sl.start + 3] for k, sl in enumerate(cset.slices())])
        return state.replace(measured_normal=normal)

    @_traced_at_matmul_precision
    def measure(self, record, contact_pos, contact_force, contact_geom):
        """Fill the measured wrenches of a Trajectory record from the contact slots after the
        tick's physics (:func:`wbc_jax.physics.contacts`)."""
        cset = self.contact_set
        dtype = record.f_cmd.dtype
        f_meas = forces.measured_wrenches(
            cset, contact_pos.astype(dtype), contact_force.astype(dtype), contact_geom,
            self.robot.mj_model.ngeom, record.contact_pos,
        )  # fmt: skip
        A = forces.wrench_map(cset, record.contact_pos, record.com)
        return record.replace(f_meas=f_meas, Ldot_meas=A @ f_meas + forces.gravity_wrench(self.idx.mass, dtype))

    # -- MJX backends: the whole loop in XLA --------------------------------------------------

    def initial_qpos(self, qpos0: Array, joint_offset: Array) -> Array:
        return qpos0.at[self.idx.qpos_joints].add(joint_offset.astype(qpos0.dtype))

    @_traced_at_matmul_precision
    def start(self, qpos: Array, batch: int = 1):
        """Initial carry (physics data, loop state, physics_ok) of an MJX backend at ``qpos``;
        ``batch``: the number of environments run together (Warp's contact buffer)."""
        d = physics.device_data(self.robot.mj_model, self.backend, self.cfg.physics, qpos, qpos.dtype, batch)
        return d, self.init(qpos), jnp.ones((), bool)

    @_traced_at_matmul_precision
    def chunk(self, plant: mjx.Model, gains: Gains, push: Push, carry, k0, n_ticks: int):
        """Run ``n_ticks`` (static) ticks from tick ``k0`` (traced) on an MJX backend:
        (carry, records with a leading time axis or None)."""

        def tick(carry, k):
            d, state, ok = carry
            state, ctrl, record = self.control(gains, state, d.qpos, d.qvel, k, ok, push)
            xfrc = self.xfrc(push, k).astype(d.qpos.dtype)
            d_new, _ = jax.lax.scan(lambda dd, x: (physics.step(plant, dd, ctrl, x), None), d, xfrc)
            finite = physics.state_ok(d_new.qpos, d_new.qvel)
            d_new = d_new.where(~finite, d)  # a diverged env keeps its last sound state
            if self.cfg.record and self.backend == "warp":  # no per-environment contact forces there
                nan = jnp.full_like(record.f_meas, jnp.nan)
                record = record.replace(f_meas=nan, Ldot_meas=jnp.full_like(record.Ldot_meas, jnp.nan))
            elif self.cfg.record or self.observes_contacts:
                slots = physics.contacts(plant, d_new)
                if self.cfg.record:
                    record = self.measure(record, *slots)
                if self.observes_contacts:
                    state = self.observe(state, *slots)
            return (d_new, state, finite), record

        if self.cfg.checkpoint:
            tick = jax.checkpoint(tick)
        return jax.lax.scan(tick, carry, k0 + jnp.arange(n_ticks))

    def rollout(self, plant: mjx.Model, qpos0: Array, gains: Gains, push: Push, controller_overrides=None,
                batch: int = 1):  # fmt: skip
        """The whole horizon on an MJX backend: (Metrics, records or None). ``plant``: the MJX model
        simulated (:func:`wbc_jax.physics.plant_model` of the nominal one for a perturbed plant).
        ``controller_overrides``: fields of the controller state to replace (regularisation as
        differentiable arrays, gain tuning's gradient check)."""
        d, state, ok = self.start(qpos0, batch)
        if controller_overrides:
            state = state.replace(controller=state.controller.replace(**controller_overrides))
        carry = (d, state, ok)
        (d, state, ok), records = self.chunk(plant, gains, push, carry, 0, self.n_ticks)
        return metrics_lib.final(state.metrics, ok), records

    @_traced_at_matmul_precision
    def rollout_queue(self, plant_of: Callable, qpos0: Array, scens: Scenario, slot: Array, segment: int,
                      axis_name: str, batch: int = 1):  # fmt: skip
        """One of S batch slots (``jax.vmap`` over ``slot`` with ``axis_name``) working through a
        shared queue of N scenarios on an MJX backend; returns the N scenarios' Metrics.

        Slot s starts scenario s. Each scenario runs until it has fallen or diverged (its outcome
        is then decided: neither upright nor survived) or reaches the horizon; every ``segment``
        ticks (static, a divisor of the horizon's) the slots whose scenario is decided hand in its
        metrics and take the next pending scenarios in slot order, so the batch stops paying
        solver iterations for robots on the floor. The loop runs until the queue is empty, with
        one predicate for all slots (a per-slot predicate would make JAX merge the loop's carry
        leaf by leaf, which Warp's batch-shared contact buffer does not allow). Each slot keeps its
        own tick, so the tick is batched under vmap and a branch on the time runs both sides: the
        force distribution's contact-ramp branch (:func:`wbc_jax.forces.distribute`) stays a
        branch only because a contact that never ramps has a constant activation
        (:func:`wbc_jax.contacts.activation_at`; BENCHMARKS.md).

        Args:
          plant_of: Scenario -> MJX model simulated (the nominal one, or perturbed).
          qpos0: (nq,) nominal initial posture.
          scens: the queue, Scenario with a leading axis N (the same for every slot).
          slot: () this slot's index s < N (the vmapped argument).
          segment: ticks between hand-ins.
          axis_name: the vmap axis of the slots.
          batch: environments run together (Warp's contact buffer).

        Returns:
          Metrics with a leading axis N, not mapped over the slots (``out_axes=None``). A retired
          environment's metrics cover its ticks up to the hand-in (``ticks``); the others equal
          :meth:`rollout`'s.
        """
        if self.n_ticks % segment:
            raise ValueError(f"segment {segment} must divide the horizon's {self.n_ticks} ticks")
        N = int(jax.tree_util.tree_leaves(scens)[0].shape[0])
        pick = lambda i: jax.tree_util.tree_map(lambda x: x[jnp.minimum(i, N - 1)], scens)  # noqa: E731

        def fresh(i):
            return self.start(self.initial_qpos(qpos0, pick(i).joint_offset), batch)

        def select(decided, new, old):
            d = old[0].where(decided, new[0])  # Data.where: Warp's batch-shared buffers stay whole
            rest = jax.tree_util.tree_map(lambda a, b: jnp.where(decided, a, b), new[1:], old[1:])
            return (d, *rest)

        carry = fresh(slot)
        outcome = metrics_lib.final(carry[1].metrics, carry[2])
        out = jax.tree_util.tree_map(lambda x: jnp.zeros((N, *x.shape), x.dtype), outcome)
        gather = lambda x: jax.lax.all_gather(x, axis_name)  # noqa: E731  (S, ...) the same in every slot

        def body(loop_state):
            idx, k, carry, out, next_free = loop_state
            s = pick(idx)
            carry, _ = self.chunk(plant_of(s), s.gains, s.push, carry, k, segment)
            k = k + segment
            met = metrics_lib.final(carry[1].metrics, carry[2])
            decided = (met.fell | met.nan | (k >= self.n_ticks)) & (idx < N)
            flags = gather(decided)
            rows = jnp.where(flags, gather(idx), N)  # N: out of bounds, dropped
            out = jax.tree_util.tree_map(lambda o, m: o.at[rows].set(m, mode="drop"), out, gather(met))
            counts = flags.astype(jnp.int32)
            rank = (jnp.cumsum(counts, dtype=jnp.int32) - counts)[jax.lax.axis_index(axis_name)]
            new_idx = jnp.where(decided, next_free + rank, idx)
            carry = select(decided & (new_idx < N), fresh(new_idx), carry)
            return new_idx, jnp.where(decided, 0, k), carry, out, next_free + jnp.sum(counts, dtype=jnp.int32)

        def pending(loop_state):
            return jnp.any(gather(loop_state[0]) < N)

        S = jax.lax.psum(1, axis_name)
        start = (jnp.asarray(slot, jnp.int32), jnp.zeros((), jnp.int32), carry, out, jnp.asarray(S, jnp.int32))
        return jax.lax.while_loop(pending, body, start)[3]

    # -- C MuJoCo: ticks in a Python loop -----------------------------------------------------

    def run_host(self, scen: Scenario, qpos0: np.ndarray, dtype, *, on_tick=None, threads: int | None = None):
        """Every tick of a batch of B environments on C MuJoCo (``mujoco`` backend).

        An even batch of 2 or more without records runs as two halves in a pipeline: while XLA
        computes one half's controller (one core), C MuJoCo steps the other half (the other
        cores), so the controller and the physics overlap; one XLA execution at a time.

        Args:
          scen: Scenario with a leading batch axis B (numpy or JAX arrays).
          qpos0: (nq,) nominal initial posture (each env adds its joint offset).
          dtype: the controller's float dtype.
          on_tick: called with the number of ticks done (progress bars).
          threads: C MuJoCo worker threads (None: all cores, one fewer when pipelined).

        Returns:
          (Metrics with a batch axis, records with axes (B, T, ...) or None, seconds compiling).
        """
        scen = jax.tree_util.tree_map(np.asarray, scen)
        B = int(scen.friction.shape[0])
        base = physics.solver_mj_model(self.robot.mj_model, self.cfg.physics)
        if self.cfg.perturb_plant:
            models = [
                physics.plant_mj_model(base, float(f), float(s))
                for f, s in zip(scen.friction, scen.mass_scale, strict=True)
            ]
        else:
            models = [base] * B
        qpos = np.asarray(qpos0, float)[None].repeat(B, 0)
        qpos[:, self.idx.qpos_joints] += scen.joint_offset
        cast = lambda x: jnp.asarray(x, dtype if np.asarray(x).dtype.kind == "f" else None)  # noqa: E731
        pipelined = B >= 2 and B % 2 == 0 and not (self.cfg.record or self.observes_contacts)
        parts = [slice(0, B // 2), slice(B // 2, B)] if pipelined else [slice(0, B)]
        take = lambda tree, part: jax.tree_util.tree_map(lambda x: cast(np.asarray(x)[part]), tree)  # noqa: E731
        gains = [take(scen.gains, part) for part in parts]
        push = [take(scen.push, part) for part in parts]
        fns, compile_s = self._host_programs(gains[0], cast(qpos[parts[0]]), push[0])
        states = [fns["init"](cast(qpos[part])) for part in parts]
        cores = threads or os.cpu_count() or 1
        hosts = [physics.HostBatch(models[part], qpos[part], max(1, cores - 1) if pipelined else cores)
                 for part in parts]  # fmt: skip
        records = []
        n_con = physics.max_contacts(self.robot.mj_model)

        def control(h, k):  # dispatched: XLA computes while the caller goes on
            q, v = hosts[h].state()
            return fns["control"](gains[h], states[h], cast(q), cast(v), np.int32(k), ~hosts[h].diverged, push[h])

        def physics_tick(h, out):
            states[h], ctrl, record, forces, bodies = out
            hosts[h].step(np.asarray(ctrl, float), self._host_xfrc(forces, bodies))
            return record

        try:
            if pipelined:
                # C0(k+1) and C1(k) each run beside the other half's physics of tick k.
                out0 = jax.block_until_ready(control(0, 0))
                for k in range(self.n_ticks):
                    out1 = control(1, k)
                    physics_tick(0, out0)
                    jax.block_until_ready(out1)
                    if k + 1 < self.n_ticks:
                        out0 = control(0, k + 1)
                    physics_tick(1, out1)
                    if k + 1 < self.n_ticks:
                        jax.block_until_ready(out0)
                    if on_tick is not None:
                        on_tick(k + 1)
            else:
                for k in range(self.n_ticks):
                    record = physics_tick(0, control(0, k))
                    if self.cfg.record or self.observes_contacts:
                        slots = hosts[0].contacts(n_con)
                        if self.cfg.record:
                            records.append(fns["measure"](record, *slots))
                        if self.observes_contacts:
                            states[0] = fns["observe"](states[0], *slots)
                    if on_tick is not None:
                        on_tick(k + 1)
        finally:
            for host in hosts:
                host.close()
        diverged = np.concatenate([host.diverged for host in hosts])
        metrics = jax.tree_util.tree_map(lambda *xs: np.concatenate([np.asarray(x) for x in xs]),
                                         *[state.metrics for state in states])  # fmt: skip
        metrics = metrics.replace(nan=metrics.nan | diverged)
        if not records:
            return metrics, None, compile_s
        stacked = jax.tree_util.tree_map(lambda *xs: np.stack([np.asarray(x) for x in xs], axis=1), *records)
        return metrics, stacked, compile_s

    def _host_xfrc(self, force: np.ndarray, body: np.ndarray) -> np.ndarray:
        """(B, n_sub, nbody, 6) body wrenches from the pushes' forces (B, n_sub, P, 3) on bodies
        (B, P), as :meth:`step_push_forces` / :meth:`push_bodies` computed them in the control step."""
        force, body = np.asarray(force, float), np.asarray(body)
        B, S, P = force.shape[:3]
        out = np.zeros((B, S, self.robot.mj_model.nbody, 6))
        b_idx = np.broadcast_to(np.arange(B)[:, None, None], (B, S, P))
        s_idx = np.broadcast_to(np.arange(S)[None, :, None], (B, S, P))
        np.add.at(out, (b_idx, s_idx, np.broadcast_to(body[:, None, :], (B, S, P)), slice(0, 3)), force)
        return out

    def control_host(self, gains, state, qpos, qvel, k, physics_ok, push):
        """:meth:`control` plus the pushes' forces of the tick's physics steps (host loop)."""
        state, ctrl, record = self.control(gains, state, qpos, qvel, k, physics_ok, push)
        return state, ctrl, record, self.step_push_forces(push, k).astype(ctrl.dtype), self.push_bodies(push)

    def _host_programs(self, gains, qpos, push):
        """The compiled, vmapped init, control and measure of the host loop for this batch shape
        (compiled once per loop and shape): (programs, seconds spent compiling now)."""
        cache = PROGRAMS
        key = ("host", self.structure_key, qpos.shape, str(qpos.dtype))
        if key in cache:
            return cache[key], 0.0
        t0 = time.perf_counter()
        B = qpos.shape[0]
        init = jax.jit(jax.vmap(self.init))
        state = jax.eval_shape(init, qpos)
        control = jax.jit(jax.vmap(self.control_host, in_axes=(0, 0, 0, 0, None, 0, 0)))
        ok = np.ones(B, bool)
        programs = {
            "init": init.lower(qpos).compile(),
            "control": control.lower(gains, state, qpos, qpos[:, : self.idx.nv], np.int32(0), ok, push).compile(),
        }
        n_con = physics.max_contacts(self.robot.mj_model)
        slots = (np.zeros((B, n_con, 3)), np.zeros((B, n_con, 3)), np.zeros((B, n_con, 2), np.int64))
        if self.cfg.record:
            record = jax.eval_shape(control, gains, state, qpos, qpos[:, : self.idx.nv], np.int32(0), ok, push)[2]
            programs["measure"] = jax.jit(jax.vmap(self.measure)).lower(record, *slots).compile()
        if self.observes_contacts:
            programs["observe"] = jax.jit(jax.vmap(self.observe)).lower(state, *slots).compile()
        cache[key] = programs
        return programs, time.perf_counter() - t0


def make_closed_loop(robot: Robot, schedule: Schedule, controller: Controller, cfg: SimConfig) -> ClosedLoop:
    """Build the :class:`ClosedLoop` of one environment (see its docstring)."""
    return ClosedLoop(robot, schedule, controller, cfg)
