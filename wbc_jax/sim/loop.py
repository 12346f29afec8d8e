"""One control tick of the closed loop: the controller at 100 Hz, zero-order hold on the physics.

A tick is two pure JAX functions around the physics:

    control(gains, state, qpos, qvel, k) -> (state, ctrl, record)     # controller + metrics
    <physics: n_sub steps with ctrl held and the push applied>        # physics.py
    measure(record, contact slots) -> record                           # measured wrenches

:class:`ClosedLoop` holds them with the static structure (robot, schedule, controller, settings)
closed over; what a use varies (the gains as a function of the state, a richer per-tick record) it
is given as values by :func:`compose`, never by a subclass. Two drivers run ticks over a horizon with the same code: :mod:`wbc_jax.sim.mjx_loop`
(MJX engines: a ``lax.scan`` of ticks to jit, vmap and differentiate) and
:mod:`wbc_jax.sim.host_loop` (C MuJoCo: the jitted, vmapped tick and the threaded C physics
alternate in a Python loop). A diverged environment (NaN) is frozen at its last finite state and
flagged; a fall is flagged and the simulation goes on, so one bad environment never poisons a batch.
"""

from __future__ import annotations

import functools
import hashlib
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from wbc_jax.control import constraints, qp, qp_eiquadprog
from wbc_jax.control.controller import Controller
from wbc_jax.control.gains import Gains
from wbc_jax.control.references import Schedule
from wbc_jax.core import mjx as mjx_device
from wbc_jax.core.types import Array
from wbc_jax.robot import dynamics
from wbc_jax.robot.model import Robot
from wbc_jax.sim import metrics as metrics_lib
from wbc_jax.sim import physics, warp_split
from wbc_jax.sim import state as state_lib
from wbc_jax.sim.state import Feedforward, LoopState, LossTrace, Push, SimConfig, Trajectory, push_force, push_forces
from wbc_jax.sim.state import traced_at_matmul_precision as _traced_at_matmul_precision

# Compiled programs of closed loops, by ClosedLoop.structure_key and batch shape (loops built alike,
# e.g. by repeated runs of a job in one process, share them).
PROGRAMS: dict = {}


# What a use of the loop varies is given as values, never by overriding its methods (a subclass
# silently missed the feedforward argument when the drivers began passing it):
#   gains_at(gains_arg, qpos, qvel) -> Gains: the tick's gains from the loop's gains argument (e.g. a
#     gain schedule evaluated at the state); None: the argument is the gains.
#   recorder(record, new_state, state, qpos, qvel) -> record: a richer per-tick record, from the
#     tick's record, the loop state after and before the tick and the physics state it started at.
#   trace(loop, state, terms, ref, out) -> record: the per-tick record of a loop whose rollouts are
#     differentiated (e.g. :func:`smooth_trace`), from the loop state before the tick, the dynamics
#     terms, the references and the controller's output; exclusive with ``SimConfig.record``.
#   remat: the tick under ``jax.checkpoint`` in reverse mode (its residuals recomputed instead of
#     stored for the whole horizon; same values): True, or a name of ``jax.checkpoint_policies``
#     (e.g. "checkpoint_dots": keep what that policy saves); False: stored.
GainsAt = Callable[[Any, Array, Array], Gains]
Recorder = Callable[[Any, LoopState, LoopState, Array, Array], Any]
Trace = Callable[[Any, LoopState, Any, Any, Any], Any]


class ClosedLoop:
    """The closed loop of one environment, built by :func:`make_closed_loop` (and varied by
    :func:`compose`, never by subclassing).

    Static structure (robot, schedule, controller, settings, the gains function and recorders) is
    closed over; every method is pure in its array arguments.
    """

    def __init__(
        self,
        robot: Robot,
        schedule: Schedule,
        controller: Controller,
        cfg: SimConfig,
        gains_at: GainsAt | None = None,
        recorders: tuple[Recorder, ...] = (),
        trace: Trace | None = None,
        remat: bool | str = False,
    ):
        if trace is not None and cfg.record:
            raise ValueError("a trace and SimConfig.record are exclusive (set record=False)")
        if isinstance(remat, str) and not hasattr(jax.checkpoint_policies, remat):
            raise ValueError(f"remat {remat!r} is not a policy of jax.checkpoint_policies")
        idx = robot.index
        self.robot, self.idx, self.schedule, self.controller, self.cfg = robot, idx, schedule, controller, cfg
        self.gains_at, self.recorders, self.trace, self.remat = gains_at, tuple(recorders), trace, remat
        self.physics_dt = float(robot.mj_model.opt.timestep)
        self.n_sub = physics.steps_per_tick(cfg.control_dt, self.physics_dt)
        self.n_ticks = int(round(cfg.duration / cfg.control_dt))
        if self.n_ticks < 1:
            raise ValueError(f"duration {cfg.duration} s is shorter than one control tick ({cfg.control_dt} s)")
        self.push_body = idx.pushable_body_id(cfg.push_body)
        # Bodies that must stay off the floor: all but the feet and the ankle links above them.
        feet_and_ankles = set(idx.foot_bodies.tolist()) | set(robot.mj_model.body_parentid[idx.foot_bodies].tolist())
        self.non_foot_bodies = np.array([b for b in range(1, robot.mj_model.nbody) if b not in feet_and_ankles])
        # A traced loop (differentiated rollouts) is computed in MJX: on 'jax' (gradients) or on 'warp'
        # (the gradient-free searches' forward rollouts); 'auto' then means 'jax'.
        requested = cfg.physics.backend
        self.backend = physics.resolve_backend(requested, differentiable=trace is not None and requested != "warp")
        engine = controller.config.qp_engine
        for name, what in (  # the settings whose values name Warp kernels ("warp", "warp_active_set")
            ("qp_engine", "the force QP"),
            ("mass_solve_engine", "the torque law's mass-matrix solve"),
            ("ritz_engine", "the postural projector's Ritz decomposition"),
        ):
            value = getattr(controller.config, name)
            if value in qp.WARP_ENGINES and not physics.has_warp():
                raise ValueError(
                    f"controller setting {name} {value!r} ({what} as one Warp kernel) needs warp-lang: "
                    "pip install 'wbc_jax[cuda]'; valid here: ['jax']"
                )
        if engine == "eiquadprog" and (problem := qp_eiquadprog.available()) is not None:
            raise ValueError(f"controller setting qp_engine 'eiquadprog': {problem}; valid here: ['jax']")
        # Where the controller's dynamics terms come from on this backend (PhysicsConfig.warp_terms).
        self.warp_terms = warp_split.resolve_terms(cfg.physics.warp_terms, self.backend, cfg.perturb_plant)
        if self.warp_terms == "step1" and (self.backend != "warp" or cfg.perturb_plant):
            raise ValueError(
                "warp_terms 'step1' reads the controller's dynamics terms off the plant's own step: it needs the "
                f"'warp' backend (here {self.backend!r}) and an unperturbed plant (perturb_plant "
                f"{cfg.perturb_plant}); valid here: ['jax']"
            )
        if self.backend == "warp" and controller.config.contact_detection:
            raise ValueError(
                "contact detection reads the simulator's contact forces, which the 'warp' backend does not "
                "expose per environment; use --backend jax or mujoco"
            )

    @functools.cached_property
    def mx(self):
        """The controller's own model: MJX's JAX implementation, whatever steps the plant (built
        when a program is first traced, as concrete arrays)."""
        with jax.ensure_compile_time_eval():
            return mjx_device.put_model(self.robot.mj_model)

    @functools.cached_property
    def _d_template(self):
        with jax.ensure_compile_time_eval():
            return mjx_device.make_data(self.robot.mj_model)

    @property
    def contact_set(self):
        return self.controller.contact_set

    @functools.cached_property
    def structure_key(self) -> str:
        """A hash of everything that shapes this loop's compiled programs (the model, schedule,
        controller, contact set, motion tasks and settings): loops built alike share programs."""
        buf = np.zeros(mujoco.mj_sizeModel(self.robot.mj_model), np.uint8)
        mujoco.mj_saveModel(self.robot.mj_model, None, buf)
        sched = {
            k: np.asarray(v).tolist() if isinstance(v, np.ndarray) else repr(v) for k, v in vars(self.schedule).items()
        }
        parts = (
            buf.tobytes(),
            repr(sched),
            repr(self.controller.config),
            repr(self.contact_set),
            repr(self.controller.stack),
            repr(self.cfg),
        )
        if self.gains_at is not None or self.recorders:  # a plain loop's key is as it always was
            parts += (repr([None if f is None else _qualified_name(f) for f in (self.gains_at, *self.recorders)]),)
        if self.trace is not None or self.remat:
            parts += (repr([None if self.trace is None else _qualified_name(self.trace), self.remat]),)
        return hashlib.sha256(b"".join(p if isinstance(p, bytes) else p.encode() for p in parts)).hexdigest()

    # -- the controller side ------------------------------------------------------------------

    def terms(self, qpos: Array, qvel: Array) -> dynamics.DynamicsTerms:
        d = self._d_template.replace(qpos=qpos, qvel=jnp.asarray(qvel, qpos.dtype))
        return dynamics.terms(self.mx, d, self.idx, self.controller.frames)

    @_traced_at_matmul_precision
    def init(self, qpos0: Array, terms: dynamics.DynamicsTerms | None = None) -> LoopState:
        """Loop state at the initial posture ``qpos0`` (nq,), zero velocity; it is also the
        controller's postural reference. ``terms``: the dynamics terms there, where the engine
        computed them (None: :meth:`terms`)."""
        dtype = qpos0.dtype
        t0 = self.terms(qpos0, jnp.zeros(self.idx.nv, dtype)) if terms is None else terms
        cset = self.contact_set
        R_bc = jnp.asarray(np.array([c.R_body_contact for c in cset.contacts]).reshape(-1, 3, 3), dtype)
        K = len(cset.contacts)
        normals = jnp.einsum("kij,kj->ki", t0.W_R_frames[:K], R_bc[:, :, 2])
        metrics = metrics_lib.initial(t0.W_p_CoM[2], dtype)
        return LoopState(
            controller=self.controller.init(t0),
            metrics=metrics,
            anchors=t0.W_p_frames[:K],
            anchor_normals=normals,
            com0_height=t0.W_p_CoM[2],
            contact_normals=normals,
            measured_normal=jnp.full(K, jnp.inf, dtype),
        )

    @_traced_at_matmul_precision
    def control(
        self,
        gains: Gains,
        state: LoopState,
        qpos: Array,
        qvel: Array,
        k: Array,
        physics_ok: Array,
        push: Push,
        feedforward: Feedforward | None = None,
        terms: dynamics.DynamicsTerms | None = None,
    ):
        """One control tick at the state (qpos, qvel) of tick ``k``.

        ``physics_ok``: () False when the last physics steps diverged (the state was frozen).
        ``feedforward``: torques added to the controller's in a window of ticks (None: none); the
        records and metrics then see the torques applied. ``terms``: the dynamics terms at the
        state, where the engine computed them (C MuJoCo's compiled loop); None: :meth:`terms`. Returns ``(state, ctrl (nu,), record)``; record is a :class:`Trajectory` (``f_meas`` and
        ``Ldot_meas`` still zero), a :class:`LossTrace` or None, by the settings."""
        cfg, idx = self.cfg, self.idx
        dtype = qpos.dtype
        t_now = k * cfg.control_dt
        terms = self.terms(qpos, qvel) if terms is None else terms
        ref = self.schedule.at(t_now, dtype)
        if self.gains_at is not None:
            gains = self.gains_at(gains, qpos, qvel)
        out, cstate = self.controller.step(gains, state.controller, terms, ref, t_now, state.measured_normal)
        if feedforward is not None:
            limit = self.controller.config.saturation(idx)
            out = out.replace(tau=state_lib.feedforward_torque(feedforward, k, out.tau, limit))
        ctrl = jnp.zeros(self.robot.mj_model.nu, dtype).at[idx.actuators].set(out.tau)
        metrics, anchors, normals = self._metrics(state, terms, ref, out, t_now, physics_ok)
        new_state = state.replace(
            controller=cstate,
            metrics=metrics,
            anchors=anchors,
            anchor_normals=normals,
            contact_normals=out.contact_R[:, :, 2],
        )
        record = None
        if cfg.record:
            record = Trajectory(
                t=t_now,
                qpos=qpos,
                com=terms.W_p_CoM,
                com_ref=ref.com_pos,
                tau=out.tau,
                f_cmd=out.f,
                f_meas=jnp.zeros_like(out.f),
                Ldot_star=out.Ldot_star,
                Ldot_meas=jnp.zeros(6, dtype),
                activation=out.activation,
                contact_pos=out.contact_pos,
                contact_normal=out.contact_R[:, :, 2],
                qp_infeasible=out.qp_infeasible,
                qp_violation=out.qp_violation,
                push=push_force(push, t_now),
                s=terms.s,
                s_des=ref.s_des,
                task_err=out.task_err,
            )
        elif self.trace is not None:
            record = self.trace(self, state, terms, ref, out)
        for recorder in self.recorders:
            record = recorder(record, new_state, state, qpos, qvel)
        return new_state, ctrl, record

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
            state.metrics,
            com=terms.W_p_CoM,
            com_ref=ref.com_pos,
            com_vel=terms.W_v_CoM,
            tau=out.tau,
            violation=out.qp_violation,
            infeasible=out.qp_infeasible,
            contact_pos=out.contact_pos,
            normals=normal,
            anchors=anchors,
            anchor_normals=anchor_normals,
            fully_active=fully_active,
            body_heights=terms.xpos[self.non_foot_bodies, 2],
            trunk_z=terms.W_R_B[:, 2],
            support=corners[:, :2],
            com0_height=state.com0_height,
            t_now=t_now,
            physics_ok=physics_ok,
        )
        return new, anchors, anchor_normals

    def push_forces_at(self, push: Push, k, i):
        """(P, 3) each push's force during physics step i (traced) of tick k: the one place push timing is
        computed (the host loop scatters these, so every backend pushes alike)."""
        return push_forces(push, k * self.cfg.control_dt + self.physics_dt * i, self.physics_dt)

    def step_push_forces(self, push: Push, k):
        """(n_sub, P, 3) each push's force during the physics steps of tick k (:meth:`push_forces_at`)."""
        return jax.vmap(lambda i: self.push_forces_at(push, k, i))(jnp.arange(self.n_sub))

    def push_bodies(self, push: Push):
        """(P,) the body id of each push."""
        return jnp.where(push.body >= 0, push.body, self.push_body)

    def xfrc_at(self, push: Push, k, i):
        """(nbody, 6) body wrenches of physics step i (traced) of tick k (each push at its body). The MJX loop
        builds each step's inside its scan: a stack of the tick's steps, sliced per step, cost the loop more on a
        GPU than the steps' wrenches themselves (BENCHMARKS.md, issue 46)."""
        force = self.push_forces_at(push, k, i)
        out = jnp.zeros((self.robot.mj_model.nbody, 6), force.dtype)
        return out.at[self.push_bodies(push), :3].add(force)

    def xfrc(self, push: Push, k):
        """(n_sub, nbody, 6) body wrenches of the physics steps of tick k (:meth:`xfrc_at`)."""
        return jax.vmap(lambda i: self.xfrc_at(push, k, i))(jnp.arange(self.n_sub))

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
        f = constraints.measured_wrenches(
            cset,
            contact_pos.astype(dtype),
            contact_force.astype(dtype),
            contact_geom,
            self.robot.mj_model.ngeom,
            jnp.zeros((K, 3), dtype),
        )
        n = state.contact_normals
        normal = jnp.stack([n[k] @ f[sl.start : sl.start + 3] for k, sl in enumerate(cset.slices())])
        return state.replace(measured_normal=normal)

    @_traced_at_matmul_precision
    def measure(self, record, contact_pos, contact_force, contact_geom):
        """Fill the measured wrenches of a Trajectory record from the contact slots after the
        tick's physics (:func:`wbc_jax.sim.physics.contacts`)."""
        cset = self.contact_set
        dtype = record.f_cmd.dtype
        f_meas = constraints.measured_wrenches(
            cset,
            contact_pos.astype(dtype),
            contact_force.astype(dtype),
            contact_geom,
            self.robot.mj_model.ngeom,
            record.contact_pos,
        )
        A = constraints.wrench_map(cset, record.contact_pos, record.com)
        return record.replace(f_meas=f_meas, Ldot_meas=A @ f_meas + constraints.gravity_wrench(self.idx.mass, dtype))

    def initial_qpos(self, qpos0: Array, joint_offset: Array) -> Array:
        return qpos0.at[self.idx.qpos_joints].add(joint_offset.astype(qpos0.dtype))


def make_closed_loop(robot: Robot, schedule: Schedule, controller: Controller, cfg: SimConfig) -> ClosedLoop:
    """Build the :class:`ClosedLoop` of one environment (see its docstring)."""
    return ClosedLoop(robot, schedule, controller, cfg)


def compose(
    loop: ClosedLoop,
    *,
    gains_at: GainsAt | None = None,
    recorder: Recorder | None = None,
    trace: Trace | None = None,
    remat: bool | str | None = None,
) -> ClosedLoop:
    """A copy of ``loop`` (same robot, schedule, controller, settings) whose gains argument goes
    through ``gains_at`` (where given: it replaces the loop's), whose per-tick record is ``trace``'s
    (where given: it replaces the loop's) and then goes through ``recorder`` (where given: after the
    loop's own recorders), with the tick's rematerialisation ``remat`` (where given)."""
    return ClosedLoop(
        loop.robot,
        loop.schedule,
        loop.controller,
        loop.cfg,
        gains_at=loop.gains_at if gains_at is None else gains_at,
        recorders=loop.recorders + (() if recorder is None else (recorder,)),
        trace=loop.trace if trace is None else trace,
        remat=loop.remat if remat is None else remat,
    )


def smooth_trace(loop: ClosedLoop, state: LoopState, terms, ref, out) -> LossTrace:
    """The :class:`LossTrace` of a tick (a :data:`Trace`): smooth, differentiable quantities of the
    losses of gain tuning and of the limit job's trajectory optimisation."""
    cset = loop.contact_set
    return LossTrace(
        com=terms.W_p_CoM,
        com_ref=ref.com_pos,
        com_vel=terms.W_v_CoM,
        tau=out.tau,
        support_xy=metrics_lib.support_corners(cset, out.contact_pos, out.contact_R)[:, :2],
        com_height0=state.com0_height,
        foot_normal=out.contact_R[jnp.asarray(cset.feet), :, 2],
    )


def _qualified_name(fn) -> str:
    """A function's stable name (its module and qualified name): it goes into compiled programs' keys."""
    return f"{fn.__module__}.{fn.__qualname__}"
