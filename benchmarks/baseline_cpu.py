"""[CPU baseline] C MuJoCo stepping + the balancing controller in NumPy, one process per core.

This is the baseline a user would write without JAX/MJX, used only by the benchmark
(``benchmarks/benchmark.py``): the controller of :mod:`wbc_jax.control.controller` on the default contact
set (the two soles) reproduced equation for equation in NumPy (batched over the environments of a
worker with stacked ``np.linalg`` calls), the dynamics terms read from C MuJoCo, the contact-wrench
QPs solved with ``quadprog`` (Goldfarb-Idnani, C), physics with ``mujoco.mj_step`` at 1 kHz, the
controller at 100 Hz with zero-order hold, pushes through ``xfrc_applied`` on the CoM of the push
body, and the metrics of :class:`wbc_jax.sim.loop.ClosedLoop`.

Dynamics terms from C MuJoCo (mixed representation, controller joint order, as
:func:`wbc_jax.robot.dynamics.terms` with the two sole frames; ``T = blkdiag(I3, W_R_B, I_n)``):

* ``M = T^-T M_mj T^-1`` with ``M_mj`` from ``mj_fullM``; ``h = T^-T qfrc_bias``,
  ``tau_passive = T^-T qfrc_passive``;
* sole Jacobians ``J = J_mj T^-1`` from ``mj_jacSite`` (``J_frames``); ``Jdot nu = Jdot_mj qvel``
  from ``mj_jacDot`` (exact: d/dt(T^-1) nu = 0, see :mod:`wbc_jax.robot.dynamics`); the sole frames
  ``site_xmat`` (= ``W_R_frames[k] @ foot_rotations[k]``, the contact frames of the feet);
* CoM, CoM velocity and the centroidal angular momentum from ``subtree_com``,
  ``mj_subtreeVel`` -> ``subtree_linvel``/``subtree_angmom`` of the base body;
* J_G,ang (Nava 2016) at the postural reference: from C MuJoCo Jacobians
  (:func:`centroidal_jacobian_ref`), or taken from the JAX controller state
  (``controller.init``, :func:`spec_from_setup`).

The loop uses the split step of C MuJoCo: ``mj_step1`` (position- and velocity-dependent
computations at the current state, which the controller reads) -> controller -> ``ctrl`` ->
``mj_step2``; with the Euler integrator this is exactly ``mj_step``, so the controller costs no
extra ``mj_forward``. The other 9 physics steps of a tick are plain ``mj_step``.

Force distribution (:func:`wbc_jax.control.forces.distribute` for the two feet): with activations a_k,
the engaged feet (a_k > 0) and the fully active ones (a_k = 1) each get the formulation, restricted
to them, and ``f = w f_engaged + (1 - w) f_active`` with ``w = min a_k`` over the engaged feet.
The formulation (:func:`wbc_jax.control.forces.wbc_qp`): the momentum-equality QP ``min |tau_model +
Sigma f|^2 s.t. A f = L_dot* - f_grav, C f <= b`` in ``f = f1 + Z y``; where it is infeasible, the
soft momentum QP ``min |A f - w|^2 + c |tau_model + Sigma f|^2 + eps |f|^2 s.t. C f <= b``. For
two feet the orthonormal basis Z of null(A) comes from a QR factorisation instead of an SVD
(changes y by a rotation, not f); for one foot null(A) is empty: ``f1 = A_k^-1 w`` is the equality
QP's only point, kept if it meets the foot's constraints (to the JAX solver's relative tolerance),
else the soft QP. quadprog solves ``min 1/2 x'Gx - a'x, C'x >= b``, so it is called with
``(H, -g, -C', -b)``; when it reports infeasibility the result is ``-(H + ridge I)^-1 g`` and the
tick is flagged, as in the JAX code. Formulations the JAX code skips by ``lax.cond`` (the active
feet's one while no foot ramps, the soft QP while the equality is feasible) are skipped here too.
The postural projector pinv(X, tol) X = V diag(sigma > tol) V' is built from ``eigh(X'X)``
instead of the SVD of X (same V and sigma^2, cheaper).

Workers: ``run_parallel`` starts ``n_workers`` processes with the ``spawn`` context; each runs
*this file* through ``runpy.run_path`` (not ``import wbc_jax...``, whose package ``__init__``
imports JAX/MJX, ~3 s and ~200 MB per worker), so a worker imports only numpy, mujoco, quadprog
and ``wbc_jax/core/constants.py`` (loaded by file path, below). (As always with ``spawn``, the parent's
``__main__`` script is re-imported in the children: keep heavy imports of a driver script under
``if __name__ == "__main__"`` or inside functions.) The parent builds a picklable, JAX-free job
(model, indices, references at the ticks, constants) with :func:`spec_from_setup` (from a
:class:`wbc_jax.sim.scenario.Setup`) or :func:`make_spec` (the same, from a task name).
"""

from __future__ import annotations

import copy
import dataclasses
import importlib.util
import math
import os
import pathlib
import sys
import time
from collections.abc import Sequence
from typing import Any

import mujoco
import numpy as np
import quadprog

from wbc_jax.robot.robots import DEFAULT_ROBOT, describe


def _load_constants():
    """``wbc_jax/core/constants.py``, loaded by file path.

    The numbers and names shared with the package live there (gravity, gain names and
    defaults, the minimum-jerk ramp, thresholds, metric names). It is loaded from its file, not
    imported as ``wbc_jax.core.constants``: importing that name runs ``wbc_jax/__init__.py``, which
    imports ``mujoco.mjx`` and so JAX (~3 s and ~200 MB in every worker process, and the
    baseline is meant to be JAX-free). constants.py itself imports only numpy."""
    name = "_wbc_jax_constants_by_path"  # its own name: no clash with a normal import
    module = sys.modules.get(name)
    if module is None:
        path = pathlib.Path(__file__).resolve().parent.parent / "wbc_jax" / "core" / "constants.py"
        spec = importlib.util.spec_from_file_location(name, path)
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    return module


constants = _load_constants()
GRAVITY = constants.GRAVITY
GAIN_FIELDS = constants.GAIN_FIELDS
RECOVERY_THRESHOLD = constants.RECOVERY_THRESHOLD
METRIC_NAMES = constants.METRIC_NAMES
min_jerk = constants.min_jerk
# Copies of names of modules that import JAX (wbc_jax.control.forces / wbc_jax.control.torques); checked
# against them in tests/test_baseline_cpu.py.
FORCE_MODES = ("qp", "analytic")
POSTURAL_VARIANTS = ("stable", "seed")
QP_FALLBACK_TOL = 1e-6  # wbc_jax.control.qp.default_tolerances(float64)[1]
_NULL_DIM = 6
_WORKER_RUN_NAME = "__wbc_baseline_cpu_worker__"
_THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS")


# --------------------------------------------------------------------------------------
# Spec: everything a worker needs, numpy only (no JAX objects)
# --------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class BaselineSpec:
    """Static description of one closed-loop task (same for every environment of a batch).

    Attributes:
      mj_model: C MuJoCo model (solver overrides of the setup's PhysicsConfig applied, no
        auto-reset, as :func:`wbc_jax.sim.physics.solver_mj_model`).
      nq, nv, n: sizes; qpos_joints, dof_joints, actuators (n,), dof_perm (nv,): as RobotIndex.
      base_body: floating-base body; foot_sites, foot_bodies (2,); mass (kg).
      push_body: body the pushes act on; non_foot_bodies: bodies that must stay off the floor.
      forces, postural, pinv_damping, pinv_tol, kp_postural_reg, hessian_reg, torque_limit,
        torque_weight_soft, angular_weight_soft, compensate_passive: as ControllerConfig.
      C_foot (m, 6), b_foot (m,): contact constraints of a sole in its frame
        (:func:`wbc_jax.control.constraints.contact_constraints`); fz_row: the row of ``-f_z <= -fz_min``;
        fz_min (N); foot_size ((x_min, x_max), (y_min, y_max)): the CoP rectangle (m).
      centroidal_jacobian_ref: (2, 3, n) J_G,ang at the reference (left, right stance).
      control_dt, physics_dt, n_sub, n_ticks: as the ClosedLoop / SimConfig.
      qpos0: (nq,) initial configuration (zero velocity).
      ref_*: references at the ticks t_k = k control_dt: com_pos/com_vel/com_acc (T, 3),
        s_des (T, n), activation (T, 2).
    """

    mj_model: Any
    nq: int
    nv: int
    n: int
    qpos_joints: np.ndarray
    dof_joints: np.ndarray
    actuators: np.ndarray
    dof_perm: np.ndarray
    base_body: int
    foot_sites: np.ndarray
    foot_bodies: np.ndarray
    mass: float
    push_body: int
    non_foot_bodies: np.ndarray
    forces: str
    postural: str
    pinv_damping: float
    pinv_tol: float
    kp_postural_reg: float
    hessian_reg: float
    torque_limit: np.ndarray  # (n,) N m, or () where one limit for all
    torque_weight_soft: float
    angular_weight_soft: float
    compensate_passive: bool
    C_foot: np.ndarray
    b_foot: np.ndarray
    fz_row: int
    fz_min: float
    foot_size: tuple
    centroidal_jacobian_ref: np.ndarray
    control_dt: float
    physics_dt: float
    n_sub: int
    n_ticks: int
    qpos0: np.ndarray
    ref_com_pos: np.ndarray
    ref_com_vel: np.ndarray
    ref_com_acc: np.ndarray
    ref_s_des: np.ndarray
    ref_activation: np.ndarray

    def __post_init__(self):
        if self.forces not in FORCE_MODES:
            raise ValueError(f"unknown forces mode {self.forces!r}; valid: {list(FORCE_MODES)}")
        if self.postural not in POSTURAL_VARIANTS:
            raise ValueError(f"unknown postural variant {self.postural!r}; valid: {list(POSTURAL_VARIANTS)}")
        act = np.clip(np.asarray(self.ref_activation, float), 0.0, 1.0)
        engaged, active = act > 0, act >= 1
        ramping = np.any(engaged & ~active, axis=1)
        bad = ~np.any(engaged, axis=1) | (ramping & ~np.any(active, axis=1))
        if np.any(bad):
            # forces.distribute has no formulation for these (its restricted momentum equality
            # has no contact to act on): the baseline does not simulate them.
            k = int(np.flatnonzero(bad)[0])
            raise ValueError(
                f"foot activations {act[k].tolist()} at tick {k}: the force distribution needs a "
                "foot in contact, and a fully active one while the other ramps"
            )

    def reference(self, k: int) -> dict:
        """References at tick k (shared by all environments)."""
        return {
            "com_pos": self.ref_com_pos[k], "com_vel": self.ref_com_vel[k],
            "com_acc": self.ref_com_acc[k], "s_des": self.ref_s_des[k],
            "activation": self.ref_activation[k],
        }  # fmt: skip

    def to_dict(self) -> dict:
        """Plain dict (picklable without importing this module)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}


def _segments(t: np.ndarray, x0: np.ndarray, starts, durations, deltas):
    """Sum of minimum-jerk segments at the times t (T,): pos, vel, acc, each (T, d)
    (references.segments for many times at once)."""
    starts, durations = np.asarray(starts, float), np.asarray(durations, float)
    x0 = np.asarray(x0, float)
    T = t.shape[0]
    if len(starts) == 0:
        zero = np.zeros((T,) + x0.shape)
        return np.broadcast_to(x0, (T,) + x0.shape).copy(), zero, zero.copy()
    deltas = np.asarray(deltas, float)
    p, v, a = min_jerk((t[:, None] - starts) / durations)
    return x0 + p @ deltas, (v / durations) @ deltas, (a / durations**2) @ deltas


def schedule_table(schedule, times: np.ndarray) -> dict:
    """Evaluate a :class:`wbc_jax.control.references.Schedule` at the times (T,) in NumPy (float64).

    Returns a dict of com_pos, com_vel, com_acc (T, 3), s_des (T, n), activation (T, 2)."""
    t = np.asarray(times, float)
    com, com_v, com_a = _segments(t, schedule.com0, *schedule.com_segments)
    if schedule.sine_amplitude:
        w = 2 * np.pi * schedule.sine_frequency
        axis = np.asarray(schedule.sine_axis, float)
        amp = schedule.sine_amplitude
        com = com + amp * np.sin(w * t)[:, None] * axis
        com_v = com_v + amp * w * np.cos(w * t)[:, None] * axis
        com_a = com_a - amp * w**2 * np.sin(w * t)[:, None] * axis
    s0 = np.asarray(schedule.s0, float)
    post = schedule.posture_segments
    if post[2] is None:
        s_des = np.broadcast_to(s0, (t.shape[0],) + s0.shape).copy()
    else:
        s_des = _segments(t, s0, *post)[0]
    act = _segments(t, np.ones(2), *schedule.activation_segments)[0]
    return {"com_pos": com, "com_vel": com_v, "com_acc": com_a, "s_des": s_des, "activation": act}


def solver_model(m: mujoco.MjModel, iterations: int | None = None,
                 ls_iterations: int | None = None) -> mujoco.MjModel:  # fmt: skip
    """A copy of the C model with the solver overrides, never resetting a diverged state on its
    own (as :func:`wbc_jax.sim.physics.solver_mj_model`; the loop restores and flags it)."""
    m = copy.copy(m)
    if iterations is not None:
        m.opt.iterations = int(iterations)
    if ls_iterations is not None:
        m.opt.ls_iterations = int(ls_iterations)
    m.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_AUTORESET
    return m


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
        elif not (np.allclose(c.point, idx.foot_points[k]) and
                  np.allclose(np.reshape(c.R_body_contact, (3, 3)), idx.foot_rotations[k])):  # fmt: skip
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
        J_G = centroidal_jacobian_ref(robot.mj_model, d, idx.dof_perm, idx.foot_sites, idx.base_body,
                                      config.base_vel_damping)  # fmt: skip
    else:
        J_G = np.asarray(controller_state.centroidal_jacobian_ref, float)
    return BaselineSpec(
        mj_model=m, nq=idx.nq, nv=idx.nv, n=idx.n,
        qpos_joints=np.asarray(idx.qpos_joints), dof_joints=np.asarray(idx.dof_joints),
        actuators=np.asarray(idx.actuators), dof_perm=np.asarray(idx.dof_perm),
        base_body=int(idx.base_body), foot_sites=np.asarray(idx.foot_sites),
        foot_bodies=np.asarray(idx.foot_bodies), mass=float(idx.mass),
        push_body=int(loop.push_body), non_foot_bodies=np.asarray(loop.non_foot_bodies),
        forces=config.forces, postural=config.postural, pinv_damping=float(config.pinv_damping),
        pinv_tol=float(config.pinv_tol), kp_postural_reg=float(config.kp_postural_reg),
        hessian_reg=float(config.hessian_reg), torque_limit=np.asarray(config.saturation(idx), float),
        torque_weight_soft=float(config.torque_weight_soft), angular_weight_soft=float(config.angular_weight_soft),
        compensate_passive=bool(config.compensate_passive),
        C_foot=C_foot, b_foot=b_foot, fz_row=int(constraints.constraint_rows(params, "surface").unilateral),
        fz_min=float(params.fz_min), foot_size=params.foot_size,
        centroidal_jacobian_ref=J_G,
        control_dt=float(cfg.control_dt), physics_dt=float(loop.physics_dt),
        n_sub=int(loop.n_sub), n_ticks=int(loop.n_ticks), qpos0=qpos0,
        ref_com_pos=ref["com_pos"], ref_com_vel=ref["com_vel"], ref_com_acc=ref["com_acc"],
        ref_s_des=ref["s_des"], ref_activation=ref["activation"],
    )  # fmt: skip


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
        record=False, push_body=push_body,
        # No compilation either way; 'mujoco' is valid on every machine.
        physics=physics.PhysicsConfig(backend="mujoco", solver_iterations=solver_iterations,
                                      ls_iterations=ls_iterations),
    )  # fmt: skip
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
        A[3:] += I_W @ jacr + m.body_mass[b] * _skew(d.xipos[b] - c) @ jacp
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
        return {"force": np.zeros((n_envs, 1, 3)), "onset": np.zeros((n_envs, 1)),
                "duration": np.zeros((n_envs, 1))}  # fmt: skip
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


def _push_force(push: dict, t, step: float | None = None) -> np.ndarray:
    """Total push force (..., B, 3) at the time(s) t (as wbc_jax.sim.state.push_forces); t: scalar or
    (..., 1, 1) to broadcast against onset (B, P). With ``step``: the mean force over [t, t + step),
    so the physics steps carry exactly force x duration (as the package's engines)."""
    if step is None:
        share = (t >= push["onset"]) & (t < push["onset"] + push["duration"])
    else:
        t = np.asarray(t, float)
        covered = np.minimum(t + step, push["onset"] + push["duration"]) - np.maximum(t, push["onset"])
        share = np.clip(covered, 0.0, step) / step
        share = np.where(share >= 1 - 1e-6, 1.0, np.where(share <= 1e-6, 0.0, share))  # as the package's
    return np.sum(push["force"] * share[..., None], axis=-2)


# --------------------------------------------------------------------------------------
# The controller in NumPy
# --------------------------------------------------------------------------------------


@dataclasses.dataclass
class Terms:
    """Batched dynamics terms (B environments), mixed representation, controller joint order;
    the quantities of :class:`wbc_jax.robot.dynamics.DynamicsTerms` (sole frames) that the controller
    and the metrics use.

    nu (B, nv), s/s_dot (B, n), W_R_B (B, 3, 3), M (B, nv, nv), h/tau_passive (B, nv),
    J_feet (B, 2, 6, nv) (= ``J_frames``), Jdot_nu_feet (B, 2, 6) (= ``Jdot_nu_frames``),
    W_p_feet (B, 2, 3) (= ``W_p_frames``), W_R_feet (B, 2, 3, 3): the SOLE frames, i.e. the feet's
    contact frames (= ``W_R_frames[k] @ foot_rotations[k]``), W_p_CoM/W_v_CoM/L_ang (B, 3).
    """

    nu: np.ndarray
    s: np.ndarray
    s_dot: np.ndarray
    W_R_B: np.ndarray
    M: np.ndarray
    h: np.ndarray
    tau_passive: np.ndarray
    J_feet: np.ndarray
    Jdot_nu_feet: np.ndarray
    W_p_feet: np.ndarray
    W_R_feet: np.ndarray
    W_p_CoM: np.ndarray
    W_v_CoM: np.ndarray
    L_ang: np.ndarray


def _T(x: np.ndarray) -> np.ndarray:
    return np.swapaxes(x, -1, -2)


def _solve(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    return np.linalg.solve(A, B)


def _mv(A: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Batched matrix-vector product A (..., i, j) x (..., j) -> (..., i)."""
    return (A @ x[..., None])[..., 0]


_SKEW_IDX = (np.array([2, 0, 1, 1, 2, 0]), np.array([1, 2, 0, 2, 0, 1]))  # (row, col) of +-v
_SKEW_SRC = np.array([0, 1, 2, 0, 1, 2])
_SKEW_SIGN = np.array([1.0, 1.0, 1.0, -1.0, -1.0, -1.0])


def _skew(v: np.ndarray) -> np.ndarray:
    """S(v) (..., 3, 3) with S(v) w = v x w."""
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., _SKEW_IDX[0], _SKEW_IDX[1]] = v[..., _SKEW_SRC] * _SKEW_SIGN
    return S


def _world_constraints(C_foot: np.ndarray, R: np.ndarray) -> np.ndarray:
    """C (..., m, 6) = C_foot blkdiag(R', R') for rotations R (..., 3, 3)."""
    Rt = _T(R)
    return np.concatenate([C_foot[:, :3] @ Rt, C_foot[:, 3:] @ Rt], -1)


def solve_qp(H: np.ndarray, g: np.ndarray, C: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, bool]:
    """``min 1/2 x'Hx + g'x  s.t.  C x <= b`` with quadprog; on failure ``-(H + ridge I)^-1 g``
    (ridge = n eps max|diag H|, as wbc_jax.control.qp) and ``infeasible = True``.

    Returns ``(x, infeasible)``."""
    H = 0.5 * (H + H.T)
    try:
        x = quadprog.solve_qp(H, -g, -C.T, -b, 0)[0]
        if np.all(np.isfinite(x)):
            return x, False
    except ValueError:
        pass
    n = H.shape[0]
    ridge = n * np.finfo(float).eps * np.max(np.abs(np.diag(H)))
    try:
        L = np.linalg.cholesky(H + ridge * np.eye(n))
        x = -np.linalg.solve(L.T, np.linalg.solve(L, g))
    except np.linalg.LinAlgError:
        x = np.full(n, np.nan)
    if not np.all(np.isfinite(x)):
        x = np.zeros(n)
    return x, True


class NumpyController:
    """The controller tick of :func:`wbc_jax.control.controller.make_controller` (``step``) on the two
    feet, in NumPy, batched over environments.

    Usage per tick: the MjData must hold the position- and velocity-dependent quantities of
    their current state (``mj_forward``, or ``mj_step1`` in a loop), then
    ``out, state = ctrl(datas, gains, spec.reference(k), state)``.
    """

    def __init__(self, spec: BaselineSpec):
        self.spec = spec
        self.m = spec.mj_model
        s = spec
        self.f_grav = np.array([0.0, 0.0, -s.mass * GRAVITY, 0.0, 0.0, 0.0])
        self._eye6 = np.eye(6)
        self._eye12 = np.eye(12)
        self._eye_n = np.eye(s.n)
        self._buffers = None

    def init_state(self, n_envs: int) -> np.ndarray:
        """Controller memory: the integral of the CoM error (B, 3)."""
        return np.zeros((n_envs, 3))

    def _alloc(self, B: int):
        nv, nq = self.spec.nv, self.spec.nq
        self._buffers = dict(
            M=np.zeros((B, nv, nv)), J=np.zeros((B, 2, 6, nv)), Jd=np.zeros((B, 2, 6, nv)),
            qpos=np.zeros((B, nq)), qvel=np.zeros((B, nv)), bias=np.zeros((B, nv)),
            passive=np.zeros((B, nv)), xmat=np.zeros((B, 9)), site_xpos=np.zeros((B, 2, 3)),
            site_xmat=np.zeros((B, 2, 9)), com=np.zeros((B, 3)), vcom=np.zeros((B, 3)),
            angmom=np.zeros((B, 3)),
        )  # fmt: skip

    def terms(self, datas: Sequence[mujoco.MjData]) -> Terms:
        """Gather the dynamics terms of each MjData (C calls), then convert in batch."""
        sp, m = self.spec, self.m
        B = len(datas)
        if self._buffers is None or self._buffers["M"].shape[0] != B:
            self._alloc(B)
        buf = self._buffers
        M, J, Jd = buf["M"], buf["J"], buf["Jd"]
        base = sp.base_body
        (s0, s1), (b0, b1) = sp.foot_sites.tolist(), sp.foot_bodies.tolist()
        for i, d in enumerate(datas):
            mujoco.mj_fullM(m, d, M[i])
            mujoco.mj_jacSite(m, d, J[i, 0, :3], J[i, 0, 3:], s0)
            mujoco.mj_jacSite(m, d, J[i, 1, :3], J[i, 1, 3:], s1)
            sx = d.site_xpos
            mujoco.mj_jacDot(m, d, Jd[i, 0, :3], Jd[i, 0, 3:], sx[s0], b0)
            mujoco.mj_jacDot(m, d, Jd[i, 1, :3], Jd[i, 1, 3:], sx[s1], b1)
            mujoco.mj_subtreeVel(m, d)
            buf["qpos"][i] = d.qpos
            buf["qvel"][i] = d.qvel
            buf["bias"][i] = d.qfrc_bias
            buf["passive"][i] = d.qfrc_passive
            buf["xmat"][i] = d.xmat[base]
            buf["site_xpos"][i, 0], buf["site_xpos"][i, 1] = sx[s0], sx[s1]
            buf["site_xmat"][i, 0], buf["site_xmat"][i, 1] = d.site_xmat[s0], d.site_xmat[s1]
            buf["com"][i] = d.subtree_com[base]
            buf["vcom"][i] = d.subtree_linvel[base]
            buf["angmom"][i] = d.subtree_angmom[base]
        return self.terms_from_arrays(buf)

    def terms_from_arrays(self, buf: dict) -> Terms:
        """Mixed-representation terms from the raw MuJoCo-order arrays of :meth:`terms`."""
        sp = self.spec
        perm = sp.dof_perm
        qvel = buf["qvel"]
        B = qvel.shape[0]
        R = buf["xmat"].reshape(B, 3, 3)
        Rt = _T(R)
        nu = np.concatenate([qvel[:, :3], _mv(R, qvel[:, 3:6]), qvel[:, sp.dof_joints]], 1)
        # M_mixed = T^-T M_mj T^-1 (columns: J T^-1; rows: T^-T), controller order.
        M = buf["M"][:, perm][:, :, perm]
        M[:, :, 3:6] = M[:, :, 3:6] @ Rt
        M[:, 3:6, :] = R @ M[:, 3:6, :]
        h = buf["bias"][:, perm]
        h[:, 3:6] = _mv(R, h[:, 3:6])
        tp = buf["passive"][:, perm]
        tp[:, 3:6] = _mv(R, tp[:, 3:6])
        J = buf["J"][..., perm]
        J[..., 3:6] = J[..., 3:6] @ Rt[:, None]
        return Terms(
            nu=nu, s=buf["qpos"][:, sp.qpos_joints], s_dot=nu[:, 6:], W_R_B=R, M=M, h=h,
            tau_passive=tp, J_feet=J, Jdot_nu_feet=_mv(buf["Jd"], qvel[:, None]),
            W_p_feet=buf["site_xpos"].copy(), W_R_feet=buf["site_xmat"].reshape(B, 2, 3, 3).copy(),
            W_p_CoM=buf["com"].copy(), W_v_CoM=buf["vcom"].copy(), L_ang=buf["angmom"].copy(),
        )  # fmt: skip

    def __call__(self, datas, gains: dict, ref: dict, state: np.ndarray):
        return self.step(self.terms(datas), gains, ref, state)

    def step(self, t: Terms, gains: dict, ref: dict, state: np.ndarray):
        """One control tick for B environments (shared references, per-environment gains).

        Args:
          t: batched :class:`Terms`. gains: dict of (B, dim) arrays (:func:`gains_to_numpy`).
          ref: com_pos/com_vel/com_acc (3,), s_des (n,), activation (2,).
          state: (B, 3) integral of the CoM error.

        Returns:
          ``(out, new_state)``; out: dict of tau, tau_unsat (B, n), f (B, 12), Ldot_star,
          Ldot_cmd (B, 6), qp_infeasible (B,) bool, qp_violation (B,).
        """
        sp = self.spec
        n = sp.n
        B = t.M.shape[0]
        act = np.clip(np.asarray(ref["activation"], float), 0.0, 1.0)
        stance = int(np.argmax(act))
        g = gains

        # Momentum task (controller.step / momentum.momentum_rate_reference).
        J_G = sp.centroidal_jacobian_ref[stance]
        ang_integral = (t.s - ref["s_des"]) @ J_G.T
        com_err = t.W_p_CoM - ref["com_pos"]
        new_state = state + sp.control_dt * com_err
        acc = (
            ref["com_acc"]
            - g["kp_com"] * com_err
            - g["kd_com"] * (t.W_v_CoM - ref["com_vel"])
            - g["ki_com"] * new_state
        )
        Ldot_ang = -g["kp_ang"] * t.L_ang - g["ki_ang"] * ang_integral
        Ldot_star = np.concatenate([sp.mass * acc, Ldot_ang], 1)
        wrench_des = Ldot_star - self.f_grav

        # Torque law (torques.torque_terms), contact rows scaled by the activations.
        M = t.M
        h = t.h - t.tau_passive if sp.compensate_passive else t.h
        J_c = (t.J_feet * act[None, :, None, None]).reshape(B, 12, -1)
        Jdot_nu_c = (t.Jdot_nu_feet * act[None, :, None]).reshape(B, 12)
        sol = _solve(M, np.concatenate([_T(J_c), h[:, :, None]], 2))
        Minv_JcT, Minv_h = sol[:, :, :12], sol[:, :, 12]
        Lambda = _T(Minv_JcT)[:, :, 6:]  # (B, 12, n)
        LLt = Lambda @ _T(Lambda) + sp.pinv_damping * self._eye12
        Lambda_pinv = _T(_solve(LLt, Lambda))  # (B, n, 12)
        N_Lambda = self._eye_n - Lambda_pinv @ Lambda
        M_b, M_bs, M_sb, M_s = M[:, :6, :6], M[:, :6, 6:], M[:, 6:, :6], M[:, 6:, 6:]
        Mb_inv = _solve(M_b, np.concatenate([M_bs, h[:, :6, None], _T(J_c[:, :, :6])], 2))
        Mb_inv_Mbs, Mb_inv_hb, Mb_inv_JbT = Mb_inv[:, :, :n], Mb_inv[:, :, n], Mb_inv[:, :, n + 1 :]
        Mbar = M_s - M_sb @ Mb_inv_Mbs
        s_err, s_dot = t.s - ref["s_des"], t.s_dot
        if sp.postural == "seed":
            u0 = -g["kp_postural"] * s_err - g["kd_postural"] * s_dot
        else:
            # P = pinv(X, tol) X = V diag(sigma > tol) V' (torques.postural_torque): the right
            # singular vectors and sigma^2 from eigh(X'X), cheaper than the SVD of X.
            X = N_Lambda @ Mbar
            lam, V = np.linalg.eigh(_T(X) @ X)
            keep = lam > sp.pinv_tol**2
            P = (V * keep[:, None, :]) @ _T(V)
            u0 = (
                -g["kp_postural"] * _mv(P, s_err)
                - sp.kp_postural_reg * _mv(X, s_err)
                - g["kd_postural"] * _mv(P, s_dot)
            )
        Sigma = -(Lambda_pinv @ (J_c @ Minv_JcT) + N_Lambda @ (_T(J_c[:, :, 6:]) - M_sb @ Mb_inv_JbT))
        mv = _mv
        tau_model = mv(Lambda_pinv, mv(J_c, Minv_h) - Jdot_nu_c) + mv(N_Lambda, h[:, 6:] - mv(M_sb, Mb_inv_hb) + u0)

        # Force task (forces.distribute): the engaged feet's formulation blended with the fully
        # active feet's while a foot ramps, f = w f_engaged + (1 - w) f_active.
        A = self.wrench_map(t.W_p_feet, t.W_p_CoM)
        C_feet = _world_constraints(sp.C_foot, t.W_R_feet)  # (B, 2, m, 6)
        engaged, active = act > 0, act >= 1
        w = float(np.min(act[engaged])) if np.any(engaged) else 1.0
        args = (A, wrench_des, Sigma, tau_model, C_feet, t.W_p_feet)
        f, bad = self.formulation(engaged, *args)
        infeasible = bad.copy()
        if w < 1:  # lax.cond in forces.distribute: only while a foot ramps
            f_active, bad_active = self.formulation(active, *args)
            f = w * f + (1.0 - w) * f_active
            infeasible |= bad_active

        tau_unsat = tau_model + mv(Sigma, f)
        tau = np.clip(tau_unsat, -sp.torque_limit, sp.torque_limit)
        out = {
            "tau": tau, "tau_unsat": tau_unsat, "f": f, "Ldot_star": Ldot_star,
            "Ldot_cmd": mv(A, f) + self.f_grav, "qp_infeasible": infeasible,
            "qp_violation": self.constraint_violation(f, t.W_R_feet, act, C_feet),
        }  # fmt: skip
        return out, new_state

    def formulation(self, mask, A, wrench_des, Sigma, tau_model, C_feet, W_p_feet):
        """The wrenches (B, 12) of the feet with ``mask`` (2,) True, the other's zero
        (forces.wbc_qp, or forces.analytic), and the infeasibility flags (B,)."""
        B = A.shape[0]
        feet = np.flatnonzero(mask).tolist()
        if len(feet) == 2:
            return self._two_feet(A, wrench_des, Sigma, tau_model, C_feet, W_p_feet)
        if len(feet) == 0:  # excluded by BaselineSpec (forces.distribute has no formulation)
            return np.full((B, 12), np.nan), np.ones(B, bool)
        k = feet[0]
        return self._one_foot(k, A, wrench_des, Sigma, tau_model, C_feet)

    def _two_feet(self, A, wrench_des, Sigma, tau_model, C_feet, W_p_feet):
        """The momentum-equality QP on both feet in f = f1 + Z y, f1 = A^+ w; where it is
        infeasible, the soft momentum QP over f (12,)."""
        sp = self.spec
        B = A.shape[0]
        mv = _mv
        eps = sp.hessian_reg
        A_pinv = _T(_solve(A @ _T(A), A))
        f1 = mv(A_pinv, wrench_des)
        Z = self.null_basis(W_p_feet)
        SZ = Sigma @ Z
        H = _T(SZ) @ SZ + eps * np.eye(_NULL_DIM)
        gq = mv(_T(SZ), tau_model + mv(Sigma, f1))
        infeasible = np.zeros(B, bool)
        if sp.forces == "analytic":
            y = -_solve(H, gq[:, :, None])[:, :, 0]
            return f1 + mv(Z, y), infeasible
        m_ = len(sp.b_foot)
        C2 = np.zeros((B, 2 * m_, 12))
        C2[:, :m_, :6], C2[:, m_:, 6:] = C_feet[:, 0], C_feet[:, 1]
        b2 = np.concatenate([sp.b_foot, sp.b_foot])
        Cq = C2 @ Z
        bq = b2 - mv(C2, f1)
        y = np.empty((B, _NULL_DIM))
        bad = np.zeros(B, bool)
        for i in range(B):
            y[i], bad[i] = solve_qp(H[i], gq[i], Cq[i], bq[i])
        f = f1 + mv(Z, y)
        # The equality is infeasible (A f = L_dot* - f_grav not realisable): the soft momentum QP.
        rows = np.array([1.0, 1.0, 1.0] + [sp.angular_weight_soft] * 3)  # soft QP row weights
        for i in np.flatnonzero(bad):
            c = sp.torque_weight_soft
            Hs = A[i].T @ (rows[:, None] * A[i]) + c * Sigma[i].T @ Sigma[i] + eps * self._eye12
            gs = -A[i].T @ (rows * wrench_des[i]) + c * Sigma[i].T @ tau_model[i]
            f[i], infeasible[i] = solve_qp(Hs, gs, C2[i], b2)
        return f, infeasible

    def _one_foot(self, k, A, wrench_des, Sigma, tau_model, C_feet):
        """Foot k alone: null(A_k) is empty, so the momentum-equality QP's only point is
        f1 = A_k^-1 w, kept where it meets the foot's constraints C_k f1 <= b (the JAX solver's
        test: a violation above QP_FALLBACK_TOL relative to the data); else the soft momentum QP
        over the foot's wrench (6,)."""
        sp = self.spec
        B = A.shape[0]
        cols = slice(6 * k, 6 * k + 6)
        A_k = A[:, :, cols]
        f = np.zeros((B, 12))
        infeasible = np.zeros(B, bool)
        f1 = _solve(A_k, wrench_des[:, :, None])[:, :, 0]
        f[:, cols] = f1
        if sp.forces == "analytic":
            return f, infeasible
        C_k = C_feet[:, k]
        slack = sp.b_foot - _mv(C_k, f1)  # (B, m)
        # Scaled as wbc_jax.control.qp: the other foot's rows (0 <= 1) put 1 in the data scale.
        scale = np.maximum(np.max(np.abs(slack), axis=1), 1.0)
        bad = np.max(-slack, axis=1) > QP_FALLBACK_TOL * scale
        eps, c = sp.hessian_reg, sp.torque_weight_soft
        rows = np.array([1.0, 1.0, 1.0] + [sp.angular_weight_soft] * 3)  # soft QP row weights
        for i in np.flatnonzero(bad):
            S_k = Sigma[i][:, cols]
            Hs = A_k[i].T @ (rows[:, None] * A_k[i]) + c * S_k.T @ S_k + eps * self._eye6
            gs = -A_k[i].T @ (rows * wrench_des[i]) + c * S_k.T @ tau_model[i]
            f[i, cols], infeasible[i] = solve_qp(Hs, gs, C_k[i], sp.b_foot)
        return f, infeasible

    @staticmethod
    def null_basis(W_p_feet: np.ndarray) -> np.ndarray:
        """Orthonormal basis Z (B, 12, 6) of null(A) = range(N_A).

        forces.range_basis takes the top singular vectors of N_A; the QPs' solution
        f = f1 + Z y does not depend on which orthonormal basis is used (the regulariser
        |y|^2 = |Z y|^2 too), so Z comes from the QR factorisation of the closed-form basis
        [I 0; 0 I; -I 0; -S(p_L - p_R) -I] (A f = 0 <=> F_R = -F_L,
        M_R = -M_L - S(p_L - p_R) F_L), several times cheaper than an SVD."""
        B = W_p_feet.shape[0]
        N = np.zeros((B, 12, 6))
        i3 = np.arange(3)
        N[:, i3, i3] = 1.0
        N[:, 3 + i3, 3 + i3] = 1.0
        N[:, 6 + i3, i3] = -1.0
        N[:, 9 + i3, 3 + i3] = -1.0
        N[:, 9:, :3] = -_skew(W_p_feet[:, 0] - W_p_feet[:, 1])
        return np.linalg.qr(N)[0]

    @staticmethod
    def wrench_map(W_p_feet: np.ndarray, W_p_CoM: np.ndarray) -> np.ndarray:
        """A (B, 6, 12) of forces.wrench_map for W_p_feet (B, 2, 3), W_p_CoM (B, 3)."""
        B = W_p_feet.shape[0]
        A = np.zeros((B, 6, 2, 6))
        i6 = np.arange(6)
        A[:, i6, :, i6] = 1.0
        A[:, 3:, :, :3] = _skew(W_p_feet - W_p_CoM[:, None]).transpose(0, 2, 1, 3)
        return A.reshape(B, 6, 12)

    def constraint_violation(self, f, W_R_feet, act, C_feet=None) -> np.ndarray:
        """forces.violation, batched: (B,). f (B, 12), W_R_feet (B, 2, 3, 3), act (2,);
        C_feet (B, 2, m, 6): the world-axes constraints, if already computed."""
        sp = self.spec
        if C_feet is None:
            C_feet = _world_constraints(sp.C_foot, W_R_feet)
        b = np.stack([sp.b_foot, sp.b_foot])
        b[:, sp.fz_row] *= act
        f_k = f.reshape(-1, 2, 6)
        fz = np.maximum(np.sum(W_R_feet[..., :, 2] * f_k[..., :3], axis=-1), sp.fz_min)
        v = np.max(np.maximum(_mv(C_feet, f_k) - b, 0.0), axis=-1) / fz  # (B, 2)
        return np.max(np.where(act > 0, v, 0.0), axis=-1)


# --------------------------------------------------------------------------------------
# Closed loop
# --------------------------------------------------------------------------------------


def _batch_size(gains, push) -> int:
    """Leading axis of batched (2-D) gains or (3-D) push forces; 1 if none is batched."""
    get = lambda x, k: x[k] if isinstance(x, dict) else getattr(x, k)  # noqa: E731
    sizes = [] if gains is None else [np.shape(get(gains, k))[0] for k in GAIN_FIELDS
                                      if np.ndim(get(gains, k)) == 2]  # fmt: skip
    if push is not None and np.ndim(get(push, "force")) == 3:
        sizes.append(np.shape(get(push, "force"))[0])
    if len(set(sizes)) > 1:
        raise ValueError(f"inconsistent batch sizes of gains/push: {sorted(set(sizes))}")
    return sizes[0] if sizes else 1


def support_corners(spec: BaselineSpec, W_p_feet: np.ndarray, W_R_feet: np.ndarray) -> np.ndarray:
    """(B, 8, 3) corners of the soles' CoP rectangles, world axes (wbc_jax.sim.metrics.support_corners)."""
    return rectangle_corners(spec.foot_size, W_p_feet, W_R_feet)


def rectangle_corners(foot_size, W_p_feet: np.ndarray, W_R_feet: np.ndarray) -> np.ndarray:
    """(B, 8, 3) corners of the CoP rectangles ``foot_size`` ((x_min, x_max), (y_min, y_max)) m of
    the soles at W_p_feet (B, 2, 3), W_R_feet (B, 2, 3, 3), world axes."""
    (x0, x1), (y0, y1) = foot_size
    local = np.array([[x, y, 0.0] for x in (x0, x1) for y in (y0, y1)])  # (4, 3)
    corners = W_p_feet[:, :, None, :] + np.einsum("cj,bkij->bkci", local, W_R_feet)
    return corners.reshape(W_p_feet.shape[0], -1, 3)


def polygon_margin(points: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(B,) signed distance of p (B, 2) inside the convex hull of points (B, N, 2): the smallest
    distance to a hull edge, negative outside (wbc_jax.sim.metrics.polygon_margin: hull edges = the ordered
    pairs with every point on their left)."""
    a = points[:, :, None, :]
    e = points[:, None, :, :] - a  # (B, N, N, 2)
    length = np.sqrt(np.sum(e * e, -1) + 1e-30)
    normal = np.stack([-e[..., 1], e[..., 0]], -1) / length[..., None]  # left normal
    offset = np.sum(normal * a, -1)  # (B, N, N)
    side = np.einsum("bijk,blk->bijl", normal, points) - offset[..., None]
    is_edge = (length > 1e-9) & np.all(side >= -1e-9, axis=-1)
    dist = np.einsum("bijk,bk->bij", normal, p) - offset
    return np.min(np.where(is_edge, dist, np.inf), axis=(1, 2))


class LoopMetrics:
    """The metrics of ``wbc_jax.sim.loop.ClosedLoop._metrics``, accumulated tick by tick for B environments.

    One implementation for every C MuJoCo closed loop of ``benchmarks/`` (:func:`simulate` here,
    the TSID peer of ``benchmarks/tsid_baseline.py``): build it at the initial state, call
    :meth:`update` once per control tick with the quantities at the tick's state, then read
    ``metrics`` (the dict :func:`simulate` returns as ``"metrics"``, named by
    :func:`summary_columns` / :func:`summarize` as ``constants.METRIC_NAMES``).

    Args:
      foot_size: ((x_min, x_max), (y_min, y_max)) m, the soles' CoP rectangle (support margin).
      W_p_feet (B, 2, 3), W_R_feet (B, 2, 3, 3): the sole frames at the initial state (the slip and
        tilt anchors).
      com0_height (B,): the initial CoM height (m; the fall threshold is a fraction of it).
    """

    def __init__(self, foot_size, W_p_feet: np.ndarray, W_R_feet: np.ndarray, com0_height: np.ndarray):
        self.foot_size = foot_size
        self.anchors = np.array(W_p_feet, float)
        self.anchor_normals = np.array(W_R_feet, float)[..., :, 2]  # (B, 2, 3)
        self.com0_height = np.array(com0_height, float)
        B = self.com0_height.shape[0]
        self.metrics = {
            "com_sq_err_sum": np.zeros(B), "com_max_err": np.zeros(B), "max_abs_torque": np.zeros(B),
            "max_violation": np.zeros(B), "max_slip": np.zeros(B), "max_tilt": np.zeros(B),
            "qp_infeasible_ticks": np.zeros(B, np.int64), "fell": np.zeros(B, bool),
            "nan": np.zeros(B, bool), "last_time_off": np.zeros(B),
            "min_com_height": self.com0_height.copy(), "end_com_speed": np.zeros(B),
            "end_support_margin": np.zeros(B), "ticks": np.zeros(B, np.int64),
        }  # fmt: skip

    def update(
        self,
        t_now: float,
        ref_com: np.ndarray,
        activation: np.ndarray,
        com: np.ndarray,
        com_vel: np.ndarray,
        W_p_feet: np.ndarray,
        W_R_feet: np.ndarray,
        tau: np.ndarray,
        violation: np.ndarray,
        infeasible: np.ndarray,
        finite: np.ndarray,
        body_low: np.ndarray,
    ) -> None:
        """Add one tick (wbc_jax.sim.loop.ClosedLoop._metrics).

        Args:
          t_now: the tick's time (s). ref_com (3,): the CoM reference; activation (2,): the feet's.
          com, com_vel (B, 3): CoM position and velocity at the tick's state (world).
          W_p_feet (B, 2, 3), W_R_feet (B, 2, 3, 3): the sole frames at the tick's state.
          tau (B, n): the applied (saturated) torques; violation (B,): the contact-constraint
            violation of the commanded wrenches; infeasible (B,) bool: the QP failed this tick.
          finite (B,) bool: the physics stayed finite over the tick (False: a NaN run).
          body_low (B,) bool: a body other than the feet/ankles below ``BODY_FLOOR_HEIGHT``, or the trunk
            tilted past ``FALL_TRUNK_TILT_DEG`` (a fall, as wbc_jax.sim.metrics counts it).
        """
        met = self.metrics
        com_err = np.linalg.norm(com - ref_com, axis=1)
        pos, normal = W_p_feet, W_R_feet[..., :, 2]  # (B, 2, 3)
        fully_active = np.clip(activation, 0.0, 1.0) >= 1.0  # (2,)
        self.anchors = np.where(fully_active[None, :, None], self.anchors, pos)
        self.anchor_normals = np.where(fully_active[None, :, None], self.anchor_normals, normal)
        dp = pos - self.anchors  # slip: tangential to the contact surface
        dp = dp - np.sum(dp * normal, -1, keepdims=True) * normal
        slip = np.max(np.where(fully_active[None], np.linalg.norm(dp, axis=-1), 0.0), axis=1)
        cos = np.sum(normal * self.anchor_normals, -1)
        sin = np.linalg.norm(np.cross(normal, self.anchor_normals), axis=-1)
        tilt = np.max(np.where(fully_active[None], np.arctan2(sin, cos), 0.0), axis=1)
        corners = rectangle_corners(self.foot_size, pos, W_R_feet)
        met["fell"] |= (com[:, 2] < constants.FALL_COM_HEIGHT * self.com0_height) | body_low
        met["com_sq_err_sum"] += com_err**2
        met["com_max_err"] = np.maximum(met["com_max_err"], com_err)
        met["max_abs_torque"] = np.maximum(met["max_abs_torque"], np.max(np.abs(tau), axis=1))
        met["max_violation"] = np.maximum(met["max_violation"], violation)
        met["max_slip"] = np.maximum(met["max_slip"], slip)
        met["max_tilt"] = np.maximum(met["max_tilt"], tilt)
        met["qp_infeasible_ticks"] += infeasible
        met["nan"] |= ~finite | ~np.all(np.isfinite(tau), axis=1)
        met["last_time_off"] = np.where(com_err > RECOVERY_THRESHOLD, t_now, met["last_time_off"])
        met["min_com_height"] = np.minimum(met["min_com_height"], com[:, 2])
        met["end_com_speed"] = np.linalg.norm(com_vel, axis=1)
        met["end_support_margin"] = polygon_margin(corners[:, :, :2], com[:, :2])
        met["ticks"] += 1


def simulate(
    spec: BaselineSpec,
    gains=None,
    push=None,
    *,
    n_envs: int | None = None,
    record: bool = True,
    timing: bool = False,
    n_ticks: int | None = None,
) -> dict:
    """Closed-loop simulation of a batch of environments with C MuJoCo (as wbc_jax.sim.loop.ClosedLoop).

    Args:
      spec: the task (:func:`spec_from_setup` / :func:`make_spec`).
      gains: per-environment gains, (B, dim) or (dim,) arrays (dict or wbc_jax.control.gains.Gains);
        None: the WBC defaults.
      push: pushes on ``spec.push_body``: force (B, P, 3) or (P, 3), onset/duration (B, P)
        or (P,) (dict or wbc_jax.sim.state.Push); None: no push.
      n_envs: batch size (default: from the batched gains/push, else 1).
      record: keep per-tick trajectories (CoM, torques, wrenches).
      timing: measure the time spent in physics and in the controller (perf_counter).
      n_ticks: simulate fewer ticks than the spec's horizon.

    Returns:
      dict with ``t`` (T,), ``com_ref`` (T, 3), ``metrics`` (dict of (B,) arrays, the fields of
      wbc_jax.sim.metrics.Metrics; :func:`summarize` names them as ``constants.METRIC_NAMES``), with
      ``record``: ``com`` (B, T, 3), ``tau`` (B, T, n), ``f_cmd`` (B, T, 12), ``qp_infeasible``
      (B, T); with ``timing``: ``timing`` (dict: wall and CPU seconds of the loop, seconds in
      physics (mj_step1/mj_step2/mj_step) and in the controller (terms + tick), microseconds per
      mj_step and per environment-tick; perf_counter).
    """
    sp = spec
    B = int(_batch_size(gains, push) if n_envs is None else n_envs)
    g = gains_to_numpy(gains, B, sp.n)
    pu = push_to_numpy(push, B)
    T = sp.n_ticks if n_ticks is None else int(n_ticks)
    m = sp.mj_model
    ctrl = NumpyController(sp)
    datas = [mujoco.MjData(m) for _ in range(B)]
    for d in datas:
        d.qpos[:] = sp.qpos0
        d.qvel[:] = 0.0
    state = ctrl.init_state(B)
    acts, pb = sp.actuators, sp.push_body

    # Metrics as wbc_jax.sim.loop.ClosedLoop.init / _metrics.
    for d in datas:
        mujoco.mj_forward(m, d)
    t0 = ctrl.terms(datas)
    tracker = LoopMetrics(sp.foot_size, t0.W_p_feet, t0.W_R_feet, t0.W_p_CoM[:, 2])
    rec = None
    if record:
        rec = {"com": np.zeros((B, T, 3)), "tau": np.zeros((B, T, sp.n)),
               "f_cmd": np.zeros((B, T, 12)), "qp_infeasible": np.zeros((B, T), bool)}  # fmt: skip
    t_phys = t_ctrl = 0.0
    clock = time.perf_counter
    saved = [None] * B
    loop_start, cpu_start = clock(), time.process_time()
    F_cur = np.zeros((B, 3))  # xfrc_applied[push_body, :3] of each MjData
    sub_times = np.arange(sp.n_sub) * sp.physics_dt
    nfb = sp.non_foot_bodies
    for k in range(T):
        t_now = k * sp.control_dt
        for i, d in enumerate(datas):
            saved[i] = (d.qpos.copy(), d.qvel.copy(), d.qacc_warmstart.copy(), d.time)
        F_all = _push_force(pu, (t_now + sub_times)[:, None, None], sp.physics_dt)  # (n_sub, B, 3)
        c0 = clock()
        for d in datas:
            mujoco.mj_step1(m, d)
        c1 = clock()
        terms = ctrl.terms(datas)
        ref = sp.reference(k)
        out, state = ctrl.step(terms, g, ref, state)
        tau = out["tau"]
        c2 = clock()
        body_low = np.array([d.xpos[nfb, 2].min() for d in datas]) < constants.BODY_FLOOR_HEIGHT
        # A fall as wbc_jax.sim.metrics counts it: the trunk (root body, id 1) tilted past the threshold.
        body_low |= ~(np.array([d.xmat[1, 8] for d in datas]) >= np.cos(np.radians(constants.FALL_TRUNK_TILT_DEG)))
        c2b = clock()
        for j in range(sp.n_sub):
            for i in np.flatnonzero(np.any(F_all[j] != F_cur, axis=1)).tolist():
                datas[i].xfrc_applied[pb, :3] = F_cur[i] = F_all[j, i]
            if j == 0:
                for i, d in enumerate(datas):
                    d.ctrl[acts] = tau[i]
                    mujoco.mj_step2(m, d)
            else:
                for d in datas:
                    mujoco.mj_step(m, d)
        c3 = clock()
        t_phys += (c1 - c0) + (c3 - c2b)
        t_ctrl += c2 - c1

        # Divergence: freeze at the last finite state, as the closed loop (the model does not
        # reset a diverged state itself: mjDSBL_AUTORESET; a clock that did not advance by
        # n_sub steps is treated the same way, for models without that flag).
        finite = np.ones(B, bool)
        for i, d in enumerate(datas):
            qpos, qvel, warm, time_ = saved[i]
            ok = abs(d.time - (time_ + sp.n_sub * sp.physics_dt)) < 0.5 * sp.physics_dt
            if not (ok and np.isfinite(d.qpos).all() and np.isfinite(d.qvel).all()):
                d.qpos[:], d.qvel[:], d.qacc_warmstart[:], d.time = qpos, qvel, warm, time_
                finite[i] = False

        # Metrics (wbc_jax.sim.loop.ClosedLoop._metrics), at the tick's state.
        tracker.update(
            t_now, ref["com_pos"], ref["activation"], terms.W_p_CoM, terms.W_v_CoM, terms.W_p_feet,
            terms.W_R_feet, tau, out["qp_violation"], out["qp_infeasible"], finite, body_low,
        )  # fmt: skip
        com = terms.W_p_CoM
        if record:
            rec["com"][:, k] = com
            rec["tau"][:, k] = tau
            rec["f_cmd"][:, k] = out["f"]
            rec["qp_infeasible"][:, k] = out["qp_infeasible"]
    result = {
        "t": np.arange(T) * sp.control_dt,
        "com_ref": sp.ref_com_pos[:T].copy(),
        "metrics": tracker.metrics,
        "n_envs": B,
        "n_ticks": T,
        "physics_steps": B * T * sp.n_sub,
    }
    if record:
        result.update(rec)
    loop_wall, loop_cpu = clock() - loop_start, time.process_time() - cpu_start
    if timing:
        ticks = max(B * T, 1)
        result["timing"] = {
            "loop_s": loop_wall,
            "loop_cpu_s": loop_cpu,  # process CPU time: < loop_s when the core is shared
            "physics_s": t_phys,
            "controller_s": t_ctrl,
            "other_s": loop_wall - t_phys - t_ctrl,  # state save, divergence check, metrics
            "physics_us_per_mj_step": 1e6 * t_phys / (ticks * sp.n_sub),
            "physics_us_per_env_tick": 1e6 * t_phys / ticks,
            "controller_us_per_env_tick": 1e6 * t_ctrl / ticks,
        }
    return result


def summary_columns(metrics: dict, push_end: float = 0.0) -> dict:
    """The metrics of :func:`simulate` under ``constants.METRIC_NAMES`` (numpy columns, (B,)),
    computed as :func:`wbc_jax.sim.metrics.summarize`: ``survived`` is the strict criterion of
    ``constants.SURVIVAL_CRITERION``, ``upright`` the lax one (no fall, no NaN)."""
    m = {k: np.asarray(v) for k, v in metrics.items()}
    ticks = np.maximum(m["ticks"], 1)
    upright = ~m["fell"] & ~m["nan"]
    tilt_deg = np.rad2deg(m["max_tilt"])
    survived = (
        upright
        & (m["max_slip"] <= constants.SURVIVAL_MAX_SLIP_M)
        & (tilt_deg <= constants.SURVIVAL_MAX_TILT_DEG)
        & (m["end_com_speed"] <= constants.SURVIVAL_END_COM_SPEED)
        & (m["end_support_margin"] >= 0)
    )
    cols = {
        "survived": survived,
        "upright": upright,
        "fell": m["fell"],
        "nan": m["nan"],
        "com_rmse_m": np.sqrt(m["com_sq_err_sum"] / ticks),
        "com_max_err_m": m["com_max_err"],
        "max_constraint_violation": m["max_violation"],
        "max_foot_slip_m": m["max_slip"],
        "max_foot_tilt_deg": tilt_deg,
        "max_abs_torque_nm": m["max_abs_torque"],
        "qp_infeasible_ticks": m["qp_infeasible_ticks"],
        "time_to_recover_s": np.where(upright, np.maximum(m["last_time_off"] - push_end, 0.0), np.nan),
        "min_com_height_m": m["min_com_height"],
        "end_com_speed_mps": m["end_com_speed"],
        "end_com_support_margin_m": m["end_support_margin"],
    }
    assert tuple(cols) == METRIC_NAMES
    return cols


def summarize(metrics: dict, push_end: float = 0.0) -> list[dict]:
    """Per-environment summaries (plain numbers) under ``constants.METRIC_NAMES``, as
    :func:`wbc_jax.sim.metrics.summarize` gives for one environment."""
    cols = summary_columns(metrics, push_end)
    B = len(cols["fell"])
    return [{k: v[i].item() for k, v in cols.items()} for i in range(B)]


# --------------------------------------------------------------------------------------
# One worker process per core
# --------------------------------------------------------------------------------------


def _worker_main(job: dict, conn, start_event) -> None:
    """Body of a worker (runs in the child, from this file executed by runpy)."""
    import sys
    import traceback

    try:
        t_ready = time.monotonic()
        spec = BaselineSpec(**job["spec"])
        info = {"worker": job["worker"], "jax_imported": "jax" in sys.modules,
                "startup_s": t_ready - job["t_launch"]}  # fmt: skip
        conn.send(("ready", info))
        if not start_event.wait(job["timeout"]):
            raise TimeoutError("start signal never came")
        t0 = time.monotonic()
        res = simulate(spec, job["gains"], job["push"], n_envs=job["n_envs"],
                       record=job["record"], timing=True, n_ticks=job["n_ticks"])  # fmt: skip
        t1 = time.monotonic()
        res.update(info, t_start=t0, t_end=t1, sim_wall_s=t1 - t0)
        conn.send(("ok", res))
    except BaseException:
        conn.send(("error", traceback.format_exc()))
    finally:
        conn.close()


def _collect(procs, conns, expected: str, deadline: float, timeout: float) -> list:
    """One message of kind ``expected`` from every worker before ``deadline`` (monotonic)."""
    out: list = [None] * len(procs)
    pending = set(range(len(procs)))
    while pending:
        for w in sorted(pending):
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise TimeoutError(
                    f"run_parallel: workers {sorted(pending)} did not answer ({expected!r}) "
                    f"within the {timeout} s timeout; terminated"
                )
            if conns[w].poll(min(0.02, remaining)):
                status, payload = conns[w].recv()
                if status == "error":
                    raise RuntimeError(f"run_parallel: worker {w} failed:\n{payload}")
                if status != expected:
                    raise RuntimeError(f"run_parallel: worker {w} sent {status!r}")
                out[w] = payload
                pending.discard(w)
            elif not procs[w].is_alive() and not conns[w].poll(0):
                raise RuntimeError(f"run_parallel: worker {w} died (exit code {procs[w].exitcode})")
    return out


def run_parallel(
    n_envs: int,
    n_workers: int | None = None,
    *,
    spec: BaselineSpec | None = None,
    task: str = "stand",
    duration: float | None = 1.0,
    forces: str = "qp",
    postural: str = "stable",
    gains=None,
    push=None,
    n_ticks: int | None = None,
    record: bool = False,
    timeout: float = 600.0,
) -> dict:
    """Simulate ``n_envs`` environments split over ``n_workers`` processes (default: one per core).

    Each worker simulates its share with :func:`simulate` (its environments batched in the
    NumPy controller, one BLAS thread); the workers start simulating together once all have
    started up, and ``wall_s`` is the simulation phase, from the first start to the last end.
    Workers run this file through runpy and import only numpy/mujoco/quadprog, but ``spawn``
    re-imports the parent's ``__main__`` script in each: a driver script that imports JAX at
    its top costs every worker ~3 s of start-up (``workers[i]["jax_imported"]`` says so;
    start-up is excluded from ``wall_s``).

    Args:
      spec: task spec; None: built with :func:`make_spec` from task/duration/forces/postural.
      gains, push: batched (n_envs leading axis) or shared, as in :func:`simulate`.
      timeout: seconds for the whole run; on expiry the workers are terminated and
        TimeoutError is raised (a crashed worker raises RuntimeError with its traceback).

    Returns:
      dict: wall_s, total_wall_s (with process start-up), physics_steps, steps_per_s,
      steps_per_s_per_worker, timing (worker 0: controller_us_per_env_tick,
      physics_us_per_mj_step, ...), workers (per-worker start-up, wall, jax_imported),
      metrics (concatenated, (n_envs,) each), and com (n_envs, T, 3) when ``record``.
    """
    import multiprocessing as mp
    import runpy

    t_launch_wall = time.monotonic()
    if spec is None:
        spec, _ = make_spec(task, duration=duration, forces=forces, postural=postural)
    n_workers = int(n_workers or os.cpu_count() or 1)
    if n_envs < 1 or n_workers < 1:
        raise ValueError(f"n_envs and n_workers must be >= 1, got {n_envs}, {n_workers}")
    n_workers = min(n_workers, n_envs)
    g = gains_to_numpy(gains, n_envs, spec.n)
    pu = push_to_numpy(push, n_envs)
    shares = np.array_split(np.arange(n_envs), n_workers)
    ctx = mp.get_context("spawn")
    start_event = ctx.Event()
    spec_dict = spec.to_dict()
    procs, conns = [], []
    # One BLAS thread per worker (set before the children import numpy).
    old_env = {k: os.environ.get(k) for k in _THREAD_ENV}
    try:
        os.environ.update({k: "1" for k in _THREAD_ENV})
        for w, share in enumerate(shares):
            job = {
                "worker": w, "spec": spec_dict, "n_envs": len(share),
                "gains": {k: v[share] for k, v in g.items()},
                "push": {k: v[share] for k, v in pu.items()},
                "record": record, "n_ticks": n_ticks, "timeout": timeout,
                "t_launch": time.monotonic(),
            }  # fmt: skip
            parent_conn, child_conn = ctx.Pipe(duplex=False)
            p = ctx.Process(
                target=runpy.run_path,
                args=(__file__,),
                kwargs={"run_name": _WORKER_RUN_NAME, "init_globals": {
                    "_WORKER_JOB": job, "_WORKER_CONN": child_conn, "_WORKER_START": start_event}},
                daemon=True,
            )  # fmt: skip
            p.start()
            child_conn.close()
            procs.append(p)
            conns.append(parent_conn)
    finally:
        for k, v in old_env.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    deadline = time.monotonic() + timeout
    results: list = [None] * len(procs)
    ok = False
    try:
        _collect(procs, conns, "ready", deadline, timeout)  # every worker started up...
        start_event.set()  # ...then all start simulating together
        results = _collect(procs, conns, "ok", deadline, timeout)
        ok = True
    finally:
        for p in procs:  # only the processes started here, by handle
            p.join(timeout=5.0 if ok else 0.1)
            if p.is_alive():
                p.terminate()
                p.join(timeout=5.0)
        for c in conns:
            c.close()
    total_wall = time.monotonic() - t_launch_wall
    wall = max(r["t_end"] for r in results) - min(r["t_start"] for r in results)
    steps = sum(r["physics_steps"] for r in results)
    out = {
        "n_envs": n_envs,
        "n_workers": len(procs),
        "n_ticks": results[0]["n_ticks"],
        "wall_s": wall,
        "total_wall_s": total_wall,
        "physics_steps": steps,
        "steps_per_s": steps / wall if wall > 0 else float("nan"),
        "steps_per_s_per_worker": [r["physics_steps"] / r["sim_wall_s"] for r in results],
        "timing": results[0]["timing"],
        "workers": [
            {k: r[k] for k in ("worker", "n_envs", "startup_s", "sim_wall_s", "jax_imported", "timing")}  # fmt: skip
            for r in results
        ],
        "metrics": {k: np.concatenate([r["metrics"][k] for r in results]) for k in results[0]["metrics"]},
    }
    if record:
        out["com"] = np.concatenate([r["com"] for r in results])
    return out


def benchmark(
    n_envs: int = 64,
    n_workers: int | None = None,
    horizon: float = 1.0,
    *,
    magnitude: float = 40.0,
    push_onset: float = 0.2,
    push_duration: float = 0.1,
    solver_iterations: int | None = None,
    timeout: float = 1800.0,
) -> dict:
    """The CPU baseline on the scenario of benchmarks/benchmark.py (JSON-ready dict).

    Stand task over ``horizon`` s, default gains, one ``magnitude`` N horizontal push on the
    chest per environment, azimuths spread evenly over 360 deg (sweep.build_scenarios with one
    magnitude), at ``push_onset`` for ``push_duration`` s; ``n_workers`` processes (default:
    one per core)."""
    import platform

    spec, gains = make_spec("stand", duration=horizon, solver_iterations=solver_iterations)
    azimuth = np.deg2rad(np.linspace(0.0, 360.0, n_envs, endpoint=False))
    force = magnitude * np.stack([np.cos(azimuth), np.sin(azimuth), np.zeros(n_envs)], 1)
    push = {"force": force[:, None, :], "onset": np.full((n_envs, 1), push_onset),
            "duration": np.full((n_envs, 1), push_duration)}  # fmt: skip
    r = run_parallel(n_envs, n_workers, spec=spec, gains=gains, push=push, timeout=timeout)
    cols = summary_columns(r["metrics"], push_onset + push_duration)
    t0 = r["timing"]
    return {
        "baseline": "C MuJoCo mj_step + NumPy controller (quadprog), one process per worker",
        "cpu": cpu_name(),
        "cpu_count": os.cpu_count(),
        "mujoco": mujoco.__version__,
        "numpy": np.__version__,
        "python": platform.python_version(),
        "batch": n_envs,
        "n_workers": r["n_workers"],
        "envs_per_worker": [w["n_envs"] for w in r["workers"]],
        "solver_iterations": int(spec.mj_model.opt.iterations),
        "horizon_s": horizon,
        "run_s": round(r["wall_s"], 4),
        "total_s_with_startup": round(r["total_wall_s"], 3),
        "physics_steps_per_s": r["steps_per_s"],
        "physics_steps_per_s_per_worker": r["steps_per_s_per_worker"],
        "control_ticks_per_s": r["steps_per_s"] / spec.n_sub,
        "worker0_controller_us_per_env_tick": t0["controller_us_per_env_tick"],
        "worker0_mj_step_us": t0["physics_us_per_mj_step"],
        "worker0_controller_share": t0["controller_s"] / t0["loop_s"],
        "worker_startup_s": [w["startup_s"] for w in r["workers"]],
        "workers_imported_jax": [w["jax_imported"] for w in r["workers"]],
        # Names of constants.METRIC_NAMES: the rates of its booleans, medians of the others.
        "survived_rate": float(np.mean(cols["survived"])),
        "upright_rate": float(np.mean(cols["upright"])),
        "com_max_err_m_median": float(np.median(cols["com_max_err_m"])),
        "max_abs_torque_nm_median": float(np.median(cols["max_abs_torque_nm"])),
        "qp_infeasible_ticks_total": int(np.sum(cols["qp_infeasible_ticks"])),
    }


def cpu_name() -> str:
    """The host CPU's model name (Linux /proc/cpuinfo; else platform)."""
    import platform

    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


if __name__ == _WORKER_RUN_NAME:  # a worker process of run_parallel (runpy.run_path)
    _worker_main(_WORKER_JOB, _WORKER_CONN, _WORKER_START)  # noqa: F821
