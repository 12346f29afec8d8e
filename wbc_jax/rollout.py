"""[closed loop] MJX physics at 1 kHz, the controller at 100 Hz, zero-order hold, one ``lax.scan``.

``rollout`` is a pure function of (model, initial data, gains, pushes): jit it, vmap it over
gains, pushes, initial states or model parameters (explicit ``in_axes``), differentiate it.
This is the only module that writes ``ctrl`` and ``xfrc_applied`` and steps the physics.
Diverged environments (NaN) are frozen at their last finite state and flagged; a fall is
flagged and the simulation goes on, so one bad environment never poisons a batch.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from mujoco import mjx
from mujoco.mjx._src import support

from wbc_jax import contacts as contacts_lib
from wbc_jax import controller as ctrl_lib
from wbc_jax import dynamics
from wbc_jax import tasks as tasks_lib
from wbc_jax.model import Robot, RobotIndex
from wbc_jax.references import Schedule
from wbc_jax.types import Array, pytree_dataclass

RECOVERY_THRESHOLD = 0.01  # m: "recovered" = CoM back within 1 cm of its reference


@dataclasses.dataclass(frozen=True)
class SimConfig:
    """Static rollout settings.

    Attributes:
      control_dt: controller period (s); physics dt comes from the model (1 ms).
      duration: simulated time (s).
      solver_iterations / ls_iterations: MJX contact solver settings (None: the model's).
      push_body: body the pushes act on (at its CoM, world-axes force).
      record: keep per-tick trajectories (False in large sweeps: metrics only).
      fall_com_height: a fall is CoM height below this fraction of the initial one.
      loss_trace: per tick, emit a small :class:`LossTrace` (for smooth, differentiable losses;
        gain tuning) instead of a Trajectory; exclusive with ``record``.
      checkpoint: wrap the tick in ``jax.checkpoint`` (reverse mode: the residuals of one tick
        are recomputed instead of stored for the whole horizon; same values).
    """

    control_dt: float = 0.01
    duration: float = 10.0
    solver_iterations: int | None = None
    ls_iterations: int | None = None
    push_body: str = "chest"
    record: bool = True
    fall_com_height: float = 0.7
    loss_trace: bool = False
    checkpoint: bool = False

    def __post_init__(self):
        if not (self.control_dt > 0 and self.duration > 0):
            raise ValueError(f"control_dt and duration must be positive: {self}")
        for name in ("solver_iterations", "ls_iterations"):
            value = getattr(self, name)
            if value is not None and not (isinstance(value, int) and value >= 1):
                raise ValueError(f"{name} must be a positive integer or None, got {value!r}")
        if self.loss_trace and self.record:
            raise ValueError("loss_trace and record are exclusive (set record=False)")


@pytree_dataclass
class Push:
    """External pushes (P of them), world-axes forces at the CoM of ``SimConfig.push_body``.

    Attributes: force (P, 3) N; onset (P,) s; duration (P,) s.
    """

    force: Array
    onset: Array
    duration: Array


def no_push(dtype=jnp.float32) -> Push:
    return Push(force=jnp.zeros((1, 3), dtype), onset=jnp.zeros(1, dtype), duration=jnp.zeros(1, dtype))


def push_force(push: Push, t: Array) -> Array:
    """Total push force (3,) at time t."""
    on = (t >= push.onset) & (t < push.onset + push.duration)
    return jnp.sum(push.force * on[:, None], axis=0)


@pytree_dataclass
class Metrics:
    """Per-environment running metrics (scalars; a batch axis under vmap)."""

    com_sq_err_sum: Array
    com_max_err: Array
    max_abs_torque: Array
    max_violation: Array
    max_slip: Array
    qp_infeasible_ticks: Array
    fell: Array
    nan: Array
    last_time_off: Array  # last time the CoM error exceeded RECOVERY_THRESHOLD
    min_com_height: Array
    ticks: Array


@pytree_dataclass
class Trajectory:
    """Per-tick record (time-major), when ``SimConfig.record``.

    t (T,), qpos (T, nq), com (T, 3), com_ref (T, 3), tau (T, n), f_cmd (T, 12),
    f_meas (T, 12), Ldot_star (T, 6), Ldot_meas (T, 6), activation (T, 2), feet_pos (T, 2, 3),
    (with a general contact set of K contacts: f_cmd, f_meas (T, D), activation (T, K), feet_pos
    (T, K, 3) = the contact points),
    qp_infeasible (T,), qp_violation (T,), push (T, 3), s (T, n), s_des (T, n),
    task_err (T, m): the motion tasks' errors stacked in stack order (m = 0 without tasks),
    contact_normal (T, K, 3): each contact's normal (world; the feet: the soles' z axes).
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
    feet_pos: Array
    qp_infeasible: Array
    qp_violation: Array
    push: Array
    s: Array
    s_des: Array
    task_err: Array
    contact_normal: Array


@pytree_dataclass
class LossTrace:
    """Per-tick quantities for smooth losses (time-major under scan), when ``SimConfig.loss_trace``.

    com (T, 3), com_ref (T, 3), com_vel (T, 3): CoM, its reference, its velocity (world);
    tau (T, n): applied torques; support_xy (T, F, 2): xy of the F foot contact geoms (world);
    com_height0 (T,): the initial CoM height (constant, for height losses).
    """

    com: Array
    com_ref: Array
    com_vel: Array
    tau: Array
    support_xy: Array
    com_height0: Array


def _contact_forces(m: mjx.Model, d: mjx.Data):
    """MJX's contact slots and the force (ncon, 3, world axes) on geom2 of each; zero where apart."""
    contact = d._impl.contact
    # efc addresses are static (numpy) in MJX: loop over the (few) contact slots.
    forces = jnp.stack(
        [support.contact_force(m, d, i, to_world_frame=True)[:3] for i in range(contact.dist.shape[0])]
    )
    return contact, jnp.where((contact.dist <= 0)[:, None], forces, 0.0)


def measured_feet_wrenches(m: mjx.Model, d: mjx.Data, idx: RobotIndex, W_p_feet: Array) -> Array:
    """Contact wrenches (12,) that MuJoCo applies on [left; right] foot, world axes, at the sole
    origins (sum over the contact points of each foot)."""
    contact, forces = _contact_forces(m, d)
    geom_foot = np.full(m.ngeom, -1)
    for k in range(2):
        geom_foot[idx.foot_geoms[k]] = k
    foot = jnp.asarray(geom_foot)[contact.geom[:, 1]]
    wrenches = []
    for k in range(2):
        sel = (foot == k)[:, None]
        F = jnp.where(sel, forces, 0.0)
        moment = jnp.cross(contact.pos - W_p_feet[k], F)
        wrenches.append(jnp.concatenate([F.sum(0), moment.sum(0)]))
    return jnp.concatenate(wrenches)


def measured_contact_wrenches(m: mjx.Model, d: mjx.Data, cset, W_p: Array) -> Array:
    """Contact wrenches (D,) that MuJoCo applies on each contact of a general set (world axes, at
    the contact points; a point contact: the force only), summed over its collision geoms."""
    contact, forces = _contact_forces(m, d)
    owner = np.full(m.ngeom, -1)
    for k, c in enumerate(cset.contacts):
        owner[list(c.geoms)] = k
    # contact_force is the force on geom2; the collision pipeline may order a pair either way
    # (a sphere on a box comes out as (sphere, box)), so find the robot's side of each contact.
    owner = jnp.asarray(owner)
    first, second = owner[contact.geom[:, 0]], owner[contact.geom[:, 1]]
    who = jnp.maximum(first, second)
    forces = jnp.where((second >= 0)[:, None], forces, -forces)
    out = []
    for k, c in enumerate(cset.contacts):
        F = jnp.where((who == k)[:, None], forces, 0.0)
        wrench = jnp.concatenate([F.sum(0), jnp.cross(contact.pos - W_p[k], F).sum(0)])
        out.append(wrench[: c.dim])
    return jnp.concatenate(out)


def initial_data(robot: Robot, qpos: np.ndarray | None = None, dtype=None) -> mjx.Data:
    """MJX data at the home keyframe (or ``qpos``), zero velocity."""
    qpos = robot.home_qpos() if qpos is None else np.asarray(qpos)
    if qpos.shape != (robot.index.nq,):
        raise ValueError(f"qpos must have shape ({robot.index.nq},), got {qpos.shape}")
    d = mjx.make_data(robot.mj_model)
    return d.replace(qpos=jnp.asarray(qpos, d.qpos.dtype if dtype is None else dtype))


def configure_model(mx: mjx.Model, cfg: SimConfig) -> mjx.Model:
    """Apply the solver overrides of ``cfg`` to the MJX model."""
    opt = mx.opt
    if cfg.solver_iterations is not None:
        opt = opt.replace(iterations=int(cfg.solver_iterations))
    if cfg.ls_iterations is not None:
        opt = opt.replace(ls_iterations=int(cfg.ls_iterations))
    return mx.replace(opt=opt)


class Rollout:
    """Closed-loop rollout of one environment, built by :func:`make_rollout`.

    ``rollout(mx, d0, gains, consts, push) -> (Metrics, Trajectory | None)`` runs the whole
    horizon in one ``lax.scan``: jit it, vmap it (e.g. ``in_axes=(None, None, 0, None, 0)``
    for batches of gains and pushes), differentiate it. ``init`` + ``chunk`` run the same
    ticks in fixed-size pieces (one compilation) so that long runs can show progress.
    Static structure (schedule, settings, indices) is closed over.
    """

    def __init__(self, robot: Robot, schedule: Schedule, config, cfg: SimConfig, stack=None, contact_set=None):
        idx = robot.index
        self.contact_set = contact_set
        self.stack = stack if stack is not None and stack.tasks else None
        self.physics_dt = float(robot.mj_model.opt.timestep)
        n_sub = int(round(cfg.control_dt / self.physics_dt))
        if n_sub < 1 or abs(n_sub * self.physics_dt - cfg.control_dt) > 1e-9:
            raise ValueError(
                f"control_dt {cfg.control_dt} must be a multiple of the physics timestep "
                f"{self.physics_dt}"
            )
        self.n_sub = n_sub
        self.n_ticks = int(round(cfg.duration / cfg.control_dt))
        self.push_body = idx.body_id(cfg.push_body)
        # Bodies that must stay off the floor: all but the feet and the ankle links above them.
        feet_and_ankles = set(idx.foot_bodies.tolist()) | set(
            robot.mj_model.body_parentid[idx.foot_bodies].tolist()
        )
        self.non_foot_bodies = np.array(
            [b for b in range(1, robot.mj_model.nbody) if b not in feet_and_ankles]
        )
        self.idx, self.schedule, self.config, self.cfg = idx, schedule, config, cfg

    def init(self, mx, d0):
        """Initial carry (data, controller state, metrics, foot anchors, initial CoM height)."""
        mx = configure_model(mx, self.cfg)
        t0 = dynamics.terms(mx, d0, self.idx)
        zero = jnp.zeros((), d0.qpos.dtype)
        anchors = t0.W_p_feet
        if self.contact_set is not None:
            ones = jnp.ones(2, d0.qpos.dtype)
            anchors = contacts_lib.contact_terms(mx, d0, self.idx, self.contact_set, zero, ones).W_p
        metrics0 = Metrics(
            com_sq_err_sum=zero, com_max_err=zero, max_abs_torque=zero, max_violation=zero,
            max_slip=zero, qp_infeasible_ticks=jnp.zeros((), jnp.int32),
            fell=jnp.zeros((), bool), nan=jnp.zeros((), bool), last_time_off=zero,
            min_com_height=t0.W_p_CoM[2], ticks=jnp.zeros((), jnp.int32),
        )  # fmt: skip
        return (d0, ctrl_lib.init_state(d0.qpos.dtype), metrics0, anchors, t0.W_p_CoM[2])

    def _tick(self, mx, gains, consts, push, carry, k, mx_plant=None):
        idx, cfg, config = self.idx, self.cfg, self.config
        d, cstate, met, anchors, com0_height = carry
        dtype = d.qpos.dtype
        t_now = k * cfg.control_dt
        terms = dynamics.terms(mx, d, idx)
        ref = self.schedule.at(t_now, dtype)
        levels, task_err = (), jnp.zeros(0, dtype)
        if self.stack is not None:
            frames = dynamics.frame_terms(mx, d, idx, self.stack.bodies, self.stack.offsets)
            levels = tasks_lib.levels(self.stack, frames, terms, t_now)
            task_err = jnp.concatenate(list(tasks_lib.task_errors(self.stack, frames, terms, t_now).values()))
        cset, cterms = self.contact_set, None
        if cset is not None:
            cterms = contacts_lib.contact_terms(mx, d, idx, cset, t_now, jnp.clip(ref.activation, 0.0, 1.0))
        out, cstate_new = ctrl_lib.step(
            gains, consts, cstate, terms, ref, config=config, mass=idx.mass, dt=cfg.control_dt,
            levels=levels, contact_set=cset, contacts=cterms,
        )
        ctrl = jnp.zeros(mx.nu, dtype).at[idx.actuators].set(out.tau)

        def substep(dd, j):
            t = t_now + j * self.physics_dt
            xfrc = jnp.zeros((mx.nbody, 6), dtype).at[self.push_body, :3].set(push_force(push, t))
            plant = mx if mx_plant is None else mx_plant
            return mjx.step(plant, dd.replace(ctrl=ctrl, xfrc_applied=xfrc)), None

        d_new, _ = jax.lax.scan(substep, d, jnp.arange(self.n_sub))
        finite = jnp.all(jnp.isfinite(d_new.qpos)) & jnp.all(jnp.isfinite(d_new.qvel))
        d_new = jax.tree_util.tree_map(lambda a, b: jnp.where(finite, a, b), d_new, d)

        # Metrics, measured at the tick (the state this tick's torques were computed from).
        com_err = jnp.linalg.norm(terms.W_p_CoM - ref.com_pos)
        activation, contact_pos = ref.activation, terms.W_p_feet
        if cset is not None:
            activation, contact_pos = cterms.activation, cterms.W_p
        fully_active = activation >= 1.0
        anchors = jnp.where(fully_active[:, None], anchors, contact_pos)
        # Slip: displacement of each fully active contact (tangential to its surface).
        dp = contact_pos - anchors
        if cset is not None:
            dp = dp - jnp.einsum("ki,ki->k", dp, cterms.W_R[:, :, 2])[:, None] * cterms.W_R[:, :, 2]
        slip_k = jnp.linalg.norm(dp[:, :2] if cset is None else dp, axis=1)
        slip = jnp.max(jnp.where(fully_active, slip_k, 0.0))
        # d_new.xpos: kinematics of the last substep (d0 from make_data has none yet).
        body_low = jnp.min(d_new.xpos[self.non_foot_bodies, 2]) < 0.05
        fell = met.fell | (terms.W_p_CoM[2] < cfg.fall_com_height * com0_height) | body_low
        met = Metrics(
            com_sq_err_sum=met.com_sq_err_sum + com_err**2,
            com_max_err=jnp.maximum(met.com_max_err, com_err),
            max_abs_torque=jnp.maximum(met.max_abs_torque, jnp.max(jnp.abs(out.tau))),
            max_violation=jnp.maximum(met.max_violation, out.qp_violation),
            max_slip=jnp.maximum(met.max_slip, slip),
            qp_infeasible_ticks=met.qp_infeasible_ticks + out.qp_infeasible.astype(jnp.int32),
            fell=fell,
            nan=met.nan | ~finite | ~jnp.all(jnp.isfinite(out.tau)),
            last_time_off=jnp.where(com_err > RECOVERY_THRESHOLD, t_now, met.last_time_off),
            min_com_height=jnp.minimum(met.min_com_height, terms.W_p_CoM[2]),
            ticks=met.ticks + 1,
        )
        record = None
        if cfg.record:
            # Contact forces that the solver applied during this tick's last physics step.
            if cset is None:
                f_meas = measured_feet_wrenches(mx, d_new, idx, terms.W_p_feet)
                A = ctrl_lib.momentum.wrench_map(terms.W_p_feet, terms.W_p_CoM)
            else:
                f_meas = measured_contact_wrenches(mx, d_new, cset, cterms.W_p)
                A = contacts_lib.wrench_map(cset, cterms.W_p, terms.W_p_CoM)
            record = Trajectory(
                t=t_now, qpos=d.qpos, com=terms.W_p_CoM, com_ref=ref.com_pos, tau=out.tau,
                f_cmd=out.f, f_meas=f_meas, Ldot_star=out.Ldot_star,
                Ldot_meas=A @ f_meas + ctrl_lib.momentum.gravity_wrench(idx.mass, dtype),
                activation=activation, feet_pos=contact_pos,
                qp_infeasible=out.qp_infeasible, qp_violation=out.qp_violation,
                push=push_force(push, t_now), s=terms.s, s_des=ref.s_des, task_err=task_err,
                contact_normal=(terms.W_R_feet if cset is None else cterms.W_R)[:, :, 2],
            )  # fmt: skip
        elif cfg.loss_trace:
            record = LossTrace(
                com=terms.W_p_CoM, com_ref=ref.com_pos, com_vel=terms.W_v_CoM, tau=out.tau,
                support_xy=d_new.geom_xpos[np.asarray(idx.foot_geoms).ravel(), :2],
                com_height0=com0_height,
            )  # fmt: skip
        return (d_new, cstate_new, met, anchors, com0_height), record

    def chunk(self, mx, gains, consts, push, carry, k0, n_ticks: int, mx_plant=None):
        """Run ``n_ticks`` (static) ticks from tick ``k0`` (traced): (carry, Trajectory | None).

        ``mx`` is the controller's model; ``mx_plant`` (default: the same) is simulated, so a
        sweep can perturb the plant (mass, friction) while the controller keeps the nominal one.
        """
        mx = configure_model(mx, self.cfg)
        plant = None if mx_plant is None else configure_model(mx_plant, self.cfg)
        body = lambda c, k: self._tick(mx, gains, consts, push, c, k, plant)  # noqa: E731
        if self.cfg.checkpoint:
            body = jax.checkpoint(body)
        return jax.lax.scan(body, carry, k0 + jnp.arange(n_ticks))

    def __call__(self, mx, d0, gains, consts, push, mx_plant=None):
        carry0 = self.init(mx, d0)
        carry, traj = self.chunk(mx, gains, consts, push, carry0, 0, self.n_ticks, mx_plant)
        return carry[2], traj


def make_rollout(robot: Robot, schedule: Schedule, config, cfg: SimConfig, stack=None, contact_set=None) -> Rollout:
    """Build the closed-loop :class:`Rollout` of one environment (see its docstring).

    ``stack``: an optional resolved :class:`wbc_jax.tasks.TaskStack` of motion tasks between the
    force task and the postural task. ``contact_set``: an optional
    :class:`wbc_jax.contacts.ContactSet` (with ``robot`` its scene, :func:`wbc_jax.contacts.build_scene`)
    instead of the two feet."""
    return Rollout(robot, schedule, config, cfg, stack, contact_set)


def summarize(metrics: Metrics, push_end: float = 0.0) -> dict:
    """Host-side summary of (unbatched) metrics as plain floats."""
    m = jax.tree_util.tree_map(np.asarray, metrics)
    ticks = max(int(m.ticks), 1)
    return {
        "fell": bool(m.fell),
        "nan": bool(m.nan),
        "com_rmse_m": float(np.sqrt(m.com_sq_err_sum / ticks)),
        "com_max_err_m": float(m.com_max_err),
        "max_constraint_violation": float(m.max_violation),
        "max_foot_slip_m": float(m.max_slip),
        "max_abs_torque_nm": float(m.max_abs_torque),
        "qp_infeasible_ticks": int(m.qp_infeasible_ticks),
        "time_to_recover_s": float(max(0.0, float(m.last_time_off) - push_end)),
        "min_com_height_m": float(m.min_com_height),
    }
