"""Specs built from the package's set-ups (:func:`spec_from_setup`, :func:`make_spec`), J_G,ang from C
MuJoCo (:func:`centroidal_jacobian_ref`), and gains and pushes as batched float64 arrays."""

from __future__ import annotations

import math

import mujoco
import numpy as np

from wbc_jax.robot.robots import DEFAULT_ROBOT, describe

from .controller import skew
from .spec import GAIN_FIELDS, BaselineSpec, schedule_table, solver_model


def _check_feet_only(st) -> None:
    """The baseline implements the controller on the default contact set (the two soles) without
    motion tasks, on the nominal plant: refuse anything else, naming what differs."""
    from wbc_jax.robot import contacts as contacts_lib

    loop, idx = st.loop, st.robot.index
    ctrl = loop.controller
    if ctrl.stack is not None:
        raise ValueError("the CPU baseline has no motion tasks (hierarchy); use a setup without --tasks")
    if loop.cfg.perturb_plant:
        raise ValueError("the CPU baseline simulates the nominal plant (perturb_plant=False)")
    cset = ctrl.contact_set
    problems = []
    if len(cset.contacts) != 2:
        problems.append(f"{len(cset.contacts)} contacts")
    for k, c in enumerate(cset.contacts[:2]):
        if c.type != "surface" or c.foot != k or c.body != int(idx.foot_bodies[k]):
            problems.append(f"contact {k} ({c.name}) is not the {('left', 'right')[k]} sole")
        elif not (
            np.allclose(c.point, idx.foot_points[k])
            and np.allclose(np.reshape(c.R_body_contact, (3, 3)), idx.foot_rotations[k])
        ):
            problems.append(f"contact {c.name} is not at the sole site")
        if not math.isnan(c.normal_force):
            problems.append(f"contact {c.name} has a desired normal force")
        if c.activation != contacts_lib.ContactActivation():
            problems.append(f"contact {c.name} has its own activation schedule")
    if len(cset.contacts) == 2 and cset.contacts[0].params != cset.contacts[1].params:
        problems.append("the soles have different contact parameters")
    if problems:
        raise ValueError("the CPU baseline implements the two-feet contact set only: " + "; ".join(problems))


def spec_from_setup(st, controller_state=None) -> BaselineSpec:
    """Build the spec of a :class:`wbc_jax.sim.scenario.Setup` (same task, settings and references).

    Args:
      st: the setup (``scenario.setup``): ``st.loop.schedule``, ``st.loop.controller.config``,
        ``st.loop.cfg`` (control period, duration, push body, solver settings), ``st.robot``,
        ``st.qpos0``. Its physics backend does not matter (the baseline runs C MuJoCo).
      controller_state: the JAX controller state (``st.loop.controller.init(terms at qpos0)``),
        for J_G,ang at the reference; None: computed with C MuJoCo (:func:`centroidal_jacobian_ref`,
        equal to ~1e-12, tests/test_baseline_cpu.py), so that building a spec evaluates no JAX.
    """
    from wbc_jax.control import constraints

    _check_feet_only(st)
    loop, robot = st.loop, st.robot
    idx, config, cfg = robot.index, loop.controller.config, loop.cfg
    m = solver_model(robot.mj_model, cfg.physics.solver_iterations, cfg.physics.ls_iterations)
    integrators = mujoco.mjtIntegrator
    if m.opt.integrator not in (integrators.mjINT_EULER, integrators.mjINT_IMPLICIT, integrators.mjINT_IMPLICITFAST):
        # mj_step1 + mj_step2 equals mj_step for these only (RK4 would fall back to Euler).
        raise ValueError("the CPU baseline needs the Euler or an implicit integrator (mj_step1/2)")
    params = loop.controller.contact_set.contacts[0].params
    C_foot, b_foot = constraints.contact_constraints(params, "surface")
    times = np.arange(loop.n_ticks) * cfg.control_dt
    ref = schedule_table(loop.schedule, times)
    qpos0 = np.asarray(st.qpos0, float)
    if controller_state is None:
        d = mujoco.MjData(robot.mj_model)
        d.qpos[:] = qpos0
        mujoco.mj_forward(robot.mj_model, d)
        J_G = centroidal_jacobian_ref(
            robot.mj_model, d, idx.dof_perm, idx.foot_sites, idx.base_body, config.base_vel_damping
        )
    else:
        J_G = np.asarray(controller_state.centroidal_jacobian_ref, float)
    return BaselineSpec(
        mj_model=m,
        nq=idx.nq,
        nv=idx.nv,
        n=idx.n,
        qpos_joints=np.asarray(idx.qpos_joints),
        dof_joints=np.asarray(idx.dof_joints),
        actuators=np.asarray(idx.actuators),
        dof_perm=np.asarray(idx.dof_perm),
        base_body=int(idx.base_body),
        foot_sites=np.asarray(idx.foot_sites),
        foot_bodies=np.asarray(idx.foot_bodies),
        mass=float(idx.mass),
        push_body=int(loop.push_body),
        non_foot_bodies=np.asarray(loop.non_foot_bodies),
        forces=config.forces,
        postural=config.postural,
        pinv_damping=float(config.pinv_damping),
        pinv_tol=float(config.pinv_tol),
        kp_postural_reg=float(config.kp_postural_reg),
        hessian_reg=float(config.hessian_reg),
        torque_limit=np.asarray(config.saturation(idx), float),
        torque_weight_soft=float(config.torque_weight_soft),
        angular_weight_soft=float(config.angular_weight_soft),
        compensate_passive=bool(config.compensate_passive),
        C_foot=C_foot,
        b_foot=b_foot,
        fz_row=int(constraints.constraint_rows(params, "surface").unilateral),
        fz_min=float(params.fz_min),
        foot_size=params.foot_size,
        centroidal_jacobian_ref=J_G,
        control_dt=float(cfg.control_dt),
        physics_dt=float(loop.physics_dt),
        n_sub=int(loop.n_sub),
        n_ticks=int(loop.n_ticks),
        qpos0=qpos0,
        ref_com_pos=ref["com_pos"],
        ref_com_vel=ref["com_vel"],
        ref_com_acc=ref["com_acc"],
        ref_s_des=ref["s_des"],
        ref_activation=ref["activation"],
    )


def make_spec(
    task: str = "stand",
    *,
    duration: float | None = None,
    forces: str = "qp",
    postural: str = "stable",
    solver_iterations: int | None = None,
    ls_iterations: int | None = None,
    controller: dict | None = None,
    push_body: str = "chest",
    robot_name: str = "icub",
):
    """The spec of a task on the two feet, built as :func:`wbc_jax.sim.scenario.setup` builds the
    closed loop (same schedule, settings and indices), without evaluating JAX: J_G,ang comes
    from C MuJoCo (:func:`spec_from_setup` without a controller state).

    ``controller``: further :class:`wbc_jax.control.controller.ControllerConfig` fields.
    Returns ``(spec, gains)``: gains = the WBC default gains as a dict of float64 numpy arrays."""
    from wbc_jax.control.controller import ControllerConfig
    from wbc_jax.sim import physics, scenario
    from wbc_jax.sim.state import SimConfig

    sim = SimConfig(
        record=False,
        push_body=push_body,
        # No compilation either way; 'mujoco' is valid on every machine.
        physics=physics.PhysicsConfig(
            backend="mujoco", solver_iterations=solver_iterations, ls_iterations=ls_iterations
        ),
    )
    config = ControllerConfig(forces=forces, postural=postural, **(controller or {}))
    st = scenario.setup(task, duration=duration, controller=config, sim=sim, robot_name=robot_name)
    spec = spec_from_setup(st)
    return spec, describe(robot_name).default_gain_values(spec.n)


def centroidal_jacobian_ref(
    m: mujoco.MjModel,
    d: mujoco.MjData,
    dof_perm,
    foot_sites,
    base_body: int,
    base_damping: float = 1e-7,
) -> np.ndarray:
    """J_G,ang (2, 3, n) of momentum.centroidal_jacobian_at_posture for a left/right stance, at
    the (kinematics-computed) state of ``d``, from C MuJoCo Jacobians.

    A_G = sum over bodies of [m Jp; I_W Jr + m S(c_b - c) Jp] (Jacobians at the body CoMs), in
    the mixed representation; with the stance foot fixed, v_b = -(J_b'J_b + eps I)^-1 J_b'J_s
    s_dot and J_G,ang = (A_G,s + A_G,b dv_b/ds_dot)[3:]."""
    nv = m.nv
    c = d.subtree_com[base_body]
    jacp, jacr = np.zeros((3, nv)), np.zeros((3, nv))
    A = np.zeros((6, nv))
    for b in range(1, m.nbody):
        mujoco.mj_jac(m, d, jacp, jacr, d.xipos[b], b)
        R = d.ximat[b].reshape(3, 3)
        I_W = R @ np.diag(m.body_inertia[b]) @ R.T
        A[:3] += m.body_mass[b] * jacp
        A[3:] += I_W @ jacr + m.body_mass[b] * skew(d.xipos[b] - c) @ jacp
    R_B = d.xmat[base_body].reshape(3, 3)

    def to_mixed(J):
        J = J[:, dof_perm]
        J[:, 3:6] = J[:, 3:6] @ R_B.T
        return J

    A = to_mixed(A)
    out = []
    for site in foot_sites:
        mujoco.mj_jacSite(m, d, jacp, jacr, int(site))
        J = to_mixed(np.concatenate([jacp, jacr]))
        J_b, J_s = J[:, :6], J[:, 6:]
        v_b = -np.linalg.solve(J_b.T @ J_b + base_damping * np.eye(6), J_b.T @ J_s)
        out.append((A[:, 6:] + A[:, :6] @ v_b)[3:])
    return np.stack(out)


def gains_to_numpy(gains, n_envs: int, n: int) -> dict:
    """Gains (wbc_jax.control.gains.Gains, a dict, or None: the default robot's gains,
    ``RobotDescription.default_gain_values``) -> dict of (n_envs, dim) float64 arrays."""
    if gains is None:
        gains = describe(DEFAULT_ROBOT).default_gain_values(n)
    out = {}
    for name in GAIN_FIELDS:
        value = gains[name] if isinstance(gains, dict) else getattr(gains, name)
        value = np.asarray(value, float)
        size = n if name.endswith("postural") else 3
        if value.shape[-1:] != (size,) or value.ndim > 2:
            raise ValueError(f"gain {name} must have shape ({size},) or (n_envs, {size}), got {value.shape}")
        if not np.all(np.isfinite(value)) or np.any(value < 0):
            raise ValueError(f"gain {name} must be finite and non-negative")
        out[name] = np.ascontiguousarray(np.broadcast_to(value, (n_envs, size)))
    return out


def push_to_numpy(push, n_envs: int) -> dict:
    """Push (wbc_jax.sim.state.Push, dict with force/onset/duration, or None) -> force (B, P, 3), onset
    (B, P), duration (B, P) float64; unbatched pushes are broadcast to every environment."""
    if push is None:
        return {"force": np.zeros((n_envs, 1, 3)), "onset": np.zeros((n_envs, 1)), "duration": np.zeros((n_envs, 1))}
    get = (lambda k: push[k]) if isinstance(push, dict) else (lambda k: getattr(push, k))
    force = np.asarray(get("force"), float)
    onset, dur = np.asarray(get("onset"), float), np.asarray(get("duration"), float)
    if force.ndim == 1:
        force, onset, dur = force[None], np.atleast_1d(onset), np.atleast_1d(dur)
    if force.ndim == 2:
        force, onset, dur = force[None], onset[None], dur[None]
    if force.shape[-1] != 3 or onset.shape != force.shape[:-1] or dur.shape != onset.shape:
        raise ValueError(f"push shapes: force {force.shape}, onset {onset.shape}, duration {dur.shape}")
    P = force.shape[1]
    return {
        "force": np.ascontiguousarray(np.broadcast_to(force, (n_envs, P, 3))),
        "onset": np.ascontiguousarray(np.broadcast_to(onset, (n_envs, P))),
        "duration": np.ascontiguousarray(np.broadcast_to(dur, (n_envs, P))),
    }
