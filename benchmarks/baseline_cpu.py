"""[CPU baseline] C MuJoCo stepping + the balancing controller in NumPy, one process per core.

This is the baseline a user would write without JAX/MJX, for the benchmark: the controller of
:mod:`wbc_jax.controller` reproduced equation for equation in NumPy (batched over the
environments of a worker with stacked ``np.linalg`` calls), the dynamics terms read from C
MuJoCo, the contact-wrench QPs solved with ``quadprog`` (Goldfarb-Idnani, C), physics with
``mujoco.mj_step`` at 1 kHz, the controller at 100 Hz with zero-order hold, pushes through
``xfrc_applied`` on the CoM of the push body: the closed loop of :class:`wbc_jax.rollout.Rollout`.

Dynamics terms from C MuJoCo (mixed representation, controller joint order, as
:func:`wbc_jax.dynamics.terms`; ``T = blkdiag(I3, W_R_B, I_n)``):

* ``M = T^-T M_mj T^-1`` with ``M_mj`` from ``mj_fullM``; ``h = T^-T qfrc_bias``,
  ``tau_passive = T^-T qfrc_passive``;
* sole Jacobians ``J = J_mj T^-1`` from ``mj_jacSite``; ``Jdot nu = Jdot_mj qvel`` from
  ``mj_jacDot`` (exact: d/dt(T^-1) nu = 0, see :mod:`wbc_jax.dynamics`);
* CoM, CoM velocity and the centroidal angular momentum from ``subtree_com``,
  ``mj_subtreeVel`` -> ``subtree_linvel``/``subtree_angmom`` of the base body;
* J_G,ang (Nava 2016) at the postural reference: computed once, from C MuJoCo Jacobians
  (:func:`centroidal_jacobian_ref`), or taken from ``constants_at_reference``
  (:func:`spec_from_setup`).

The loop uses the split step of C MuJoCo: ``mj_step1`` (position- and velocity-dependent
computations at the current state, which the controller reads) -> controller -> ``ctrl`` ->
``mj_step2``; with the Euler integrator this is exactly ``mj_step``, so the controller costs no
extra ``mj_forward``. The other 9 physics steps of a tick are plain ``mj_step``.

QPs: the formulations of :func:`wbc_jax.contact_qp.two_feet_wrenches`,
:func:`~wbc_jax.contact_qp.one_foot_wrench` and, when the two-feet QP is infeasible, the soft
two-feet momentum QP of :mod:`wbc_jax.controller` (same H, g, C, b; for the two-feet QP the
orthonormal basis Z of range(N_A) comes from a QR factorisation instead of an SVD, which changes
y = Z' (f - f1) by a rotation but not f). quadprog solves ``min 1/2 x'Gx - a'x, C'x >= b``, so
it is called with ``(H, -g, -C', -b)``; when it reports infeasibility the result is
``-(H + ridge I)^-1 g`` and the tick is flagged, as in the JAX code. A QP whose blending weight
is exactly 0 (one foot or two feet), or the soft QP while the two-feet QP is feasible, is not
solved: the JAX code computes it and then discards it (multiplied by 0 / ``where``), so the
outputs are the same. The postural projector pinv(X, tol) X = V diag(sigma > tol) V' is built
from ``eigh(X'X)`` instead of the SVD of X (same V and sigma^2, cheaper).

Workers: ``run_parallel`` starts ``n_workers`` processes with the ``spawn`` context; each runs
*this file* through ``runpy.run_path`` (not ``import wbc_jax...``, whose package ``__init__``
imports JAX/MJX, ~3 s and ~200 MB per worker), so a worker imports only numpy, mujoco and
quadprog. (As always with ``spawn``, the parent's ``__main__`` script is re-imported in the
children: keep heavy imports of a driver script under ``if __name__ == "__main__"``.)
The parent builds a picklable, JAX-free job (model, indices, references at the ticks,
constants) with :func:`make_spec` (the library's schedule/config classes, no JAX evaluation) or
:func:`spec_from_setup` (from the pieces of ``balance.setup``).
"""

from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Sequence
from typing import Any

import mujoco
import numpy as np
import quadprog

GRAVITY = 9.81  # m/s^2, as wbc_jax.momentum
GAIN_FIELDS = ("kp_com", "kd_com", "ki_com", "kp_ang", "ki_ang", "kp_postural", "kd_postural")
FORCE_MODES = ("qp", "analytic")
POSTURAL_VARIANTS = ("stable", "seed")
RECOVERY_THRESHOLD = 0.01  # m, as wbc_jax.rollout
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
      mj_model: C MuJoCo model (solver overrides of the rollout's SimConfig applied).
      nq, nv, n: sizes; qpos_joints, dof_joints, actuators (n,), dof_perm (nv,): as RobotIndex.
      base_body: floating-base body; foot_sites, foot_bodies (2,); mass (kg).
      push_body: body the pushes act on; non_foot_bodies: bodies that must stay off the floor.
      forces, postural, pinv_damping, pinv_tol, kp_postural_reg, hessian_reg, torque_limit:
        as ControllerConfig; torque_weight_soft: controller.TORQUE_WEIGHT_SOFT (the soft
        two-feet QP). C_foot (m, 6), b_foot (m,), fz_min: contact constraints.
      centroidal_jacobian_ref: (2, 3, n) J_G,ang at the reference (left, right stance).
      control_dt, physics_dt, n_sub, n_ticks, fall_com_height: as the Rollout/SimConfig.
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
    torque_limit: float
    torque_weight_soft: float
    C_foot: np.ndarray
    b_foot: np.ndarray
    fz_min: float
    centroidal_jacobian_ref: np.ndarray
    control_dt: float
    physics_dt: float
    n_sub: int
    n_ticks: int
    fall_com_height: float
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
            raise ValueError(
                f"unknown postural variant {self.postural!r}; valid: {list(POSTURAL_VARIANTS)}"
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


def _min_jerk(u: np.ndarray):
    """mj(u), mj'(u), mj''(u) for u clipped to [0, 1] (numpy copy of references.min_jerk)."""
    inside = (u > 0) & (u < 1)
    u = np.clip(u, 0.0, 1.0)
    p = u**3 * (10 - 15 * u + 6 * u**2)
    v = np.where(inside, 30 * u**2 * (1 - u) ** 2, 0.0)
    a = np.where(inside, 60 * u * (1 - u) * (1 - 2 * u), 0.0)
    return p, v, a


def _segments(t: np.ndarray, x0: np.ndarray, starts, durations, deltas):
    """Sum of minimum-jerk segments at the times t (T,): pos, vel, acc, each (T, d)."""
    starts, durations = np.asarray(starts, float), np.asarray(durations, float)
    x0 = np.asarray(x0, float)
    T = t.shape[0]
    if len(starts) == 0:
        zero = np.zeros((T,) + x0.shape)
        return np.broadcast_to(x0, (T,) + x0.shape).copy(), zero, zero.copy()
    deltas = np.asarray(deltas, float)
    p, v, a = _min_jerk((t[:, None] - starts) / durations)
    return x0 + p @ deltas, (v / durations) @ deltas, (a / durations**2) @ deltas


def schedule_table(schedule, times: np.ndarray) -> dict:
    """Evaluate a :class:`wbc_jax.references.Schedule` at the times (T,) in NumPy (float64).

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


def spec_from_setup(robot, rollout, consts, schedule=None, qpos0=None) -> BaselineSpec:
    """Build the spec from the pieces of :func:`wbc_jax.balance.setup` (same task, same settings).

    Args:
      robot: :class:`wbc_jax.model.Robot`. rollout: the :class:`wbc_jax.rollout.Rollout`.
      consts: :class:`wbc_jax.controller.ControllerConstants` (J_G,ang at the reference).
      schedule: defaults to ``rollout.schedule``. qpos0: initial qpos (default: home keyframe).
    """
    from wbc_jax import contact_qp
    from wbc_jax import controller as ctrl_lib

    schedule = rollout.schedule if schedule is None else schedule
    idx, config, cfg = robot.index, rollout.config, rollout.cfg
    m = robot.mj_model
    if cfg.solver_iterations is not None or cfg.ls_iterations is not None:
        import copy

        m = copy.copy(m)
        if cfg.solver_iterations is not None:
            m.opt.iterations = int(cfg.solver_iterations)
        if cfg.ls_iterations is not None:
            m.opt.ls_iterations = int(cfg.ls_iterations)
    integrators = mujoco.mjtIntegrator
    if m.opt.integrator not in (
        integrators.mjINT_EULER, integrators.mjINT_IMPLICIT, integrators.mjINT_IMPLICITFAST
    ):
        # mj_step1 + mj_step2 equals mj_step for these only (RK4 would fall back to Euler).
        raise ValueError("the CPU baseline needs the Euler or an implicit integrator (mj_step1/2)")
    C_foot, b_foot = contact_qp.foot_constraints(config.contact)
    times = np.arange(rollout.n_ticks) * cfg.control_dt
    ref = schedule_table(schedule, times)
    qpos0 = robot.home_qpos() if qpos0 is None else np.asarray(qpos0, float)
    return BaselineSpec(
        mj_model=m, nq=idx.nq, nv=idx.nv, n=idx.n,
        qpos_joints=np.asarray(idx.qpos_joints), dof_joints=np.asarray(idx.dof_joints),
        actuators=np.asarray(idx.actuators), dof_perm=np.asarray(idx.dof_perm),
        base_body=int(idx.base_body), foot_sites=np.asarray(idx.foot_sites),
        foot_bodies=np.asarray(idx.foot_bodies), mass=float(idx.mass),
        push_body=int(rollout.push_body), non_foot_bodies=np.asarray(rollout.non_foot_bodies),
        forces=config.forces, postural=config.postural, pinv_damping=float(config.pinv_damping),
        pinv_tol=float(config.pinv_tol), kp_postural_reg=float(config.kp_postural_reg),
        hessian_reg=float(config.hessian_reg), torque_limit=float(config.torque_limit),
        torque_weight_soft=float(ctrl_lib.TORQUE_WEIGHT_SOFT),
        C_foot=C_foot, b_foot=b_foot, fz_min=float(config.contact.fz_min),
        centroidal_jacobian_ref=np.asarray(consts.centroidal_jacobian_ref, float),
        control_dt=float(cfg.control_dt), physics_dt=float(rollout.physics_dt),
        n_sub=int(rollout.n_sub), n_ticks=int(rollout.n_ticks),
        fall_com_height=float(cfg.fall_com_height), qpos0=np.asarray(qpos0, float),
        ref_com_pos=ref["com_pos"], ref_com_vel=ref["com_vel"], ref_com_acc=ref["com_acc"],
        ref_s_des=ref["s_des"], ref_activation=ref["activation"],
    )  # fmt: skip


def make_spec(
    robot=None,
    task: str = "stand",
    *,
    duration: float | None = None,
    forces: str = "qp",
    postural: str = "stable",
    sim: dict | None = None,
    controller: dict | None = None,
    qpos0: np.ndarray | None = None,
):
    """Build the spec of a task as :func:`wbc_jax.balance.setup` does, without evaluating JAX.

    balance.setup evaluates ``dynamics.terms`` eagerly at the initial state (over a minute on a
    busy 2-core CPU); here the initial CoM, posture and sole come from C MuJoCo and J_G,ang
    from :func:`centroidal_jacobian_ref` (equal to ``constants_at_reference`` to ~1e-12,
    tests/test_baseline_cpu.py). The schedule, settings and indices are the library's own
    (references.make_schedule, ControllerConfig, SimConfig, Rollout).

    Returns ``(spec, gains)``: gains = the default gains as a dict of float64 numpy arrays."""
    from wbc_jax import controller as ctrl_lib
    from wbc_jax import model, references
    from wbc_jax import rollout as rollout_lib

    robot = model.load_robot("icub") if robot is None else robot
    idx = robot.index
    ccfg = ctrl_lib.ControllerConfig(forces=forces, postural=postural, **(controller or {}))
    qpos0 = robot.home_qpos() if qpos0 is None else np.asarray(qpos0, float)
    m = robot.mj_model
    d = mujoco.MjData(m)
    d.qpos[:] = qpos0
    mujoco.mj_forward(m, d)
    schedule = references.make_schedule(
        task, com0=d.subtree_com[idx.base_body].copy(), s0=qpos0[idx.qpos_joints],
        left_sole=d.site_xpos[idx.foot_sites[0]].copy(), joints=idx.joints, duration=duration,
    )  # fmt: skip
    cfg = rollout_lib.SimConfig(duration=schedule.duration, **(sim or {}))
    rollout = rollout_lib.make_rollout(robot, schedule, ccfg, cfg)
    J_G = centroidal_jacobian_ref(m, d, idx.dof_perm, idx.foot_sites, idx.base_body,
                                  ccfg.base_vel_damping)  # fmt: skip
    consts = ctrl_lib.ControllerConstants(centroidal_jacobian_ref=J_G)
    spec = spec_from_setup(robot, rollout, consts, schedule, qpos0)
    return spec, {k: v[0] for k, v in gains_to_numpy(None, 1, idx.n).items()}


def centroidal_jacobian_ref(
    m: mujoco.MjModel, d: mujoco.MjData, dof_perm, foot_sites, base_body: int,
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
    """Gains (controller.Gains, a dict, or None: WBC defaults) -> dict of (n_envs, dim) float64."""
    if gains is None:
        kp_com = np.array([50.0, 50.0, 10.0])
        from_wbc = (
            [10, 30, 20] + [10, 10, 10, 8] * 2 + [30, 30, 20, 20, 100, 100]
            + [30, 50, 30, 60, 100, 100]
        )  # fmt: skip  # controller.WBC_KP_POSTURAL
        kp_post = np.array(from_wbc, float)
        gains = {
            "kp_com": kp_com, "kd_com": 2 * np.sqrt(kp_com) / 20, "ki_com": np.zeros(3),
            "kp_ang": np.ones(3), "ki_ang": np.full(3, 0.25), "kp_postural": kp_post,
            "kd_postural": 2 * np.sqrt(kp_post) / 20,
        }  # fmt: skip
    out = {}
    for name in GAIN_FIELDS:
        value = gains[name] if isinstance(gains, dict) else getattr(gains, name)
        value = np.asarray(value, float)
        size = n if name.endswith("postural") else 3
        if value.shape[-1:] != (size,) or value.ndim > 2:
            raise ValueError(
                f"gain {name} must have shape ({size},) or (n_envs, {size}), got {value.shape}"
            )
        if not np.all(np.isfinite(value)) or np.any(value < 0):
            raise ValueError(f"gain {name} must be finite and non-negative")
        out[name] = np.ascontiguousarray(np.broadcast_to(value, (n_envs, size)))
    return out


def push_to_numpy(push, n_envs: int) -> dict:
    """Push (rollout.Push, dict with force/onset/duration, or None) -> force (B, P, 3), onset
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
        raise ValueError(
            f"push shapes: force {force.shape}, onset {onset.shape}, duration {dur.shape}"
        )
    P = force.shape[1]
    return {
        "force": np.ascontiguousarray(np.broadcast_to(force, (n_envs, P, 3))),
        "onset": np.ascontiguousarray(np.broadcast_to(onset, (n_envs, P))),
        "duration": np.ascontiguousarray(np.broadcast_to(dur, (n_envs, P))),
    }


def _push_force(push: dict, t) -> np.ndarray:
    """Total push force (..., B, 3) at the time(s) t (as rollout.push_force); t: scalar or
    (..., 1, 1) to broadcast against onset (B, P)."""
    on = (t >= push["onset"]) & (t < push["onset"] + push["duration"])
    return np.sum(push["force"] * on[..., None], axis=-2)


# --------------------------------------------------------------------------------------
# The controller in NumPy
# --------------------------------------------------------------------------------------


@dataclasses.dataclass
class Terms:
    """Batched dynamics terms (B environments), mixed representation, controller joint order;
    the same quantities as :class:`wbc_jax.dynamics.DynamicsTerms` (those the controller uses).

    nu (B, nv), s/s_dot (B, n), W_R_B (B, 3, 3), M (B, nv, nv), h/tau_passive (B, nv),
    J_feet (B, 2, 6, nv), Jdot_nu_feet (B, 2, 6), W_p_feet (B, 2, 3), W_R_feet (B, 2, 3, 3),
    W_p_CoM/W_v_CoM/L_ang (B, 3).
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
    (ridge = n eps max|diag H|, as contact_qp) and ``infeasible = True``.

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
    """The controller tick of :func:`wbc_jax.controller.step` in NumPy, batched over environments.

    Usage per tick: the MjData must hold the position- and velocity-dependent quantities of
    their current state (``mj_forward``, or ``mj_step1`` in a loop), then
    ``out, state = ctrl(datas, gains, spec.reference(k), state)``.
    """

    def __init__(self, spec: BaselineSpec):
        self.spec = spec
        self.m = spec.mj_model
        s = spec
        self.f_grav = np.array([0.0, 0.0, -s.mass * GRAVITY, 0.0, 0.0, 0.0])
        self._fz_row = len(s.b_foot) - 5  # the unilateral row (contact_qp.foot_constraints)
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

        # Torque law (torques.torque_terms), compensate_passive=True.
        M = t.M
        h = t.h - t.tau_passive
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
        Sigma = -(
            Lambda_pinv @ (J_c @ Minv_JcT) + N_Lambda @ (_T(J_c[:, :, 6:]) - M_sb @ Mb_inv_JbT)
        )
        mv = _mv
        tau_model = mv(Lambda_pinv, mv(J_c, Minv_h) - Jdot_nu_c) + mv(
            N_Lambda, h[:, 6:] - mv(M_sb, Mb_inv_hb) + u0
        )

        # Force distribution: A = [A_L, A_R], f1 = A^+ wrench_des, N_A = I - A^+ A.
        A = self.wrench_map(t.W_p_feet, t.W_p_CoM)
        A_pinv = _T(_solve(A @ _T(A), A))
        f1 = mv(A_pinv, wrench_des)
        N_A = self._eye12 - A_pinv @ A
        A_stance = A[:, :, 6 * stance : 6 * stance + 6]
        C_feet = _world_constraints(sp.C_foot, t.W_R_feet)  # (B, 2, m, 6)
        w_two = float(np.min(act))
        eps = sp.hessian_reg
        infeasible = np.zeros(B, bool)
        f_two = np.zeros((B, 12))
        f_one = np.zeros((B, 6))
        if w_two > 0:
            Z = self.null_basis(t.W_p_feet)
            SZ = Sigma @ Z
            H = _T(SZ) @ SZ + eps * np.eye(_NULL_DIM)
            gq = mv(_T(SZ), tau_model + mv(Sigma, f1))
            if sp.forces == "qp":
                m_ = len(sp.b_foot)
                C2 = np.zeros((B, 2 * m_, 12))
                C2[:, :m_, :6], C2[:, m_:, 6:] = C_feet[:, 0], C_feet[:, 1]
                b2 = np.concatenate([sp.b_foot, sp.b_foot])
                Cq = C2 @ Z
                bq = b2 - mv(C2, f1)
                y = np.empty((B, _NULL_DIM))
                bad_two = np.zeros(B, bool)
                for i in range(B):
                    y[i], bad_two[i] = solve_qp(H[i], gq[i], Cq[i], bq[i])
                f_two = f1 + mv(Z, y)
                # WBC's QP infeasible (A f = L_dot* - f_grav not realisable): the soft two-feet
                # momentum QP of controller._two_feet_momentum_qp, over f (12,).
                for i in np.flatnonzero(bad_two):
                    c = sp.torque_weight_soft
                    Hs = A[i].T @ A[i] + c * Sigma[i].T @ Sigma[i] + eps * self._eye12
                    gs = -A[i].T @ wrench_des[i] + c * Sigma[i].T @ tau_model[i]
                    f_two[i], bad_two[i] = solve_qp(Hs, gs, C2[i], b2)
                infeasible |= bad_two
            else:
                y = -_solve(H, gq[:, :, None])[:, :, 0]
                f_two = f1 + mv(Z, y)
        if w_two < 1:
            if sp.forces == "qp":
                H1 = _T(A_stance) @ A_stance + eps * np.eye(6)
                g1 = -mv(_T(A_stance), wrench_des)
                C1 = C_feet[:, stance]
                for i in range(B):
                    f_one[i], bad = solve_qp(H1[i], g1[i], C1[i], sp.b_foot)
                    infeasible[i] |= bad
            else:
                f_one = _solve(A_stance, wrench_des[:, :, None])[:, :, 0]
        f_one_padded = np.zeros((B, 12))
        f_one_padded[:, 6 * stance : 6 * stance + 6] = f_one
        f = w_two * f_two + (1.0 - w_two) * f_one_padded

        tau_unsat = tau_model + mv(Sigma, f)
        tau = np.clip(tau_unsat, -sp.torque_limit, sp.torque_limit)
        out = {
            "tau": tau, "tau_unsat": tau_unsat, "f": f, "Ldot_star": Ldot_star,
            "Ldot_cmd": mv(A, f) + self.f_grav, "qp_infeasible": infeasible,
            "qp_violation": self.constraint_violation(f, t.W_R_feet, act, C_feet),
        }  # fmt: skip
        return out, new_state

    @staticmethod
    def null_basis(W_p_feet: np.ndarray) -> np.ndarray:
        """Orthonormal basis Z (B, 12, 6) of null(A) = range(N_A).

        contact_qp.range_basis takes the top singular vectors of N_A; the QPs' solution
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
        """A (B, 6, 12) of momentum.wrench_map for W_p_feet (B, 2, 3), W_p_CoM (B, 3)."""
        B = W_p_feet.shape[0]
        A = np.zeros((B, 6, 2, 6))
        i6 = np.arange(6)
        A[:, i6, :, i6] = 1.0
        A[:, 3:, :, :3] = _skew(W_p_feet - W_p_CoM[:, None]).transpose(0, 2, 1, 3)
        return A.reshape(B, 6, 12)

    def constraint_violation(self, f, W_R_feet, act, C_feet=None) -> np.ndarray:
        """controller.constraint_violation, batched: (B,). f (B, 12), W_R_feet (B, 2, 3, 3),
        act (2,); C_feet (B, 2, m, 6): the world-axes constraints, if already computed."""
        sp = self.spec
        if C_feet is None:
            C_feet = _world_constraints(sp.C_foot, W_R_feet)
        b = np.stack([sp.b_foot, sp.b_foot])
        b[:, self._fz_row] *= act
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
    """Closed-loop simulation of a batch of environments with C MuJoCo (as rollout.Rollout).

    Args:
      spec: the task (:func:`make_spec` / :func:`spec_from_setup`).
      gains: per-environment gains, (B, dim) or (dim,) arrays (dict or controller.Gains);
        None: the WBC defaults.
      push: pushes on ``spec.push_body``: force (B, P, 3) or (P, 3), onset/duration (B, P)
        or (P,) (dict or rollout.Push); None: no push.
      n_envs: batch size (default: from the batched gains/push, else 1).
      record: keep per-tick trajectories (CoM, torques, wrenches).
      timing: measure the time spent in physics and in the controller (perf_counter).
      n_ticks: simulate fewer ticks than the spec's horizon.

    Returns:
      dict with ``t`` (T,), ``com_ref`` (T, 3), ``metrics`` (dict of (B,) arrays, the fields of
      rollout.Metrics), with ``record``: ``com`` (B, T, 3), ``tau`` (B, T, n), ``f_cmd``
      (B, T, 12), ``qp_infeasible`` (B, T); with ``timing``: ``timing`` (dict: wall and CPU
      seconds of the loop, seconds in physics (mj_step1/mj_step2/mj_step) and in the controller
      (terms + tick), microseconds per mj_step and per environment-tick; perf_counter).
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

    # Metrics as rollout.Rollout.init / _tick.
    for d in datas:
        mujoco.mj_forward(m, d)
    t0 = ctrl.terms(datas)
    anchors = t0.W_p_feet.copy()
    com0_height = t0.W_p_CoM[:, 2].copy()
    met = {
        "com_sq_err_sum": np.zeros(B), "com_max_err": np.zeros(B), "max_abs_torque": np.zeros(B),
        "max_violation": np.zeros(B), "max_slip": np.zeros(B),
        "qp_infeasible_ticks": np.zeros(B, np.int64), "fell": np.zeros(B, bool),
        "nan": np.zeros(B, bool), "last_time_off": np.zeros(B),
        "min_com_height": com0_height.copy(), "ticks": np.zeros(B, np.int64),
    }  # fmt: skip
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
    for k in range(T):
        t_now = k * sp.control_dt
        for i, d in enumerate(datas):
            saved[i] = (d.qpos.copy(), d.qvel.copy(), d.qacc_warmstart.copy(), d.time)
        F_all = _push_force(pu, (t_now + sub_times)[:, None, None])  # (n_sub, B, 3)
        c0 = clock()
        for d in datas:
            mujoco.mj_step1(m, d)
        c1 = clock()
        terms = ctrl.terms(datas)
        ref = sp.reference(k)
        out, state = ctrl.step(terms, g, ref, state)
        tau = out["tau"]
        c2 = clock()
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
        t_phys += (c1 - c0) + (c3 - c2)
        t_ctrl += c2 - c1

        # Divergence: freeze at the last finite state, as the rollout. C MuJoCo resets a state
        # with NaN/huge qpos, qvel or qacc to qpos0 itself (mj_check*, with a warning), which
        # shows as a clock that did not advance by n_sub steps: treated the same way.
        finite = np.ones(B, bool)
        for i, d in enumerate(datas):
            qpos, qvel, warm, time_ = saved[i]
            ok = abs(d.time - (time_ + sp.n_sub * sp.physics_dt)) < 0.5 * sp.physics_dt
            if not (ok and np.isfinite(d.qpos).all() and np.isfinite(d.qvel).all()):
                d.qpos[:], d.qvel[:], d.qacc_warmstart[:], d.time = qpos, qvel, warm, time_
                finite[i] = False

        # Metrics (rollout.Rollout._tick), at the tick's state.
        com = terms.W_p_CoM
        com_err = np.linalg.norm(com - ref["com_pos"], axis=1)
        fully_active = ref["activation"] >= 1.0
        anchors = np.where(fully_active[None, :, None], anchors, terms.W_p_feet)
        slip_k = np.linalg.norm((terms.W_p_feet - anchors)[:, :, :2], axis=2)
        slip = np.max(np.where(fully_active[None], slip_k, 0.0), axis=1)
        nfb = sp.non_foot_bodies
        body_low = np.array([d.xpos[nfb, 2].min() for d in datas]) < 0.05
        met["fell"] |= (com[:, 2] < sp.fall_com_height * com0_height) | body_low
        met["com_sq_err_sum"] += com_err**2
        met["com_max_err"] = np.maximum(met["com_max_err"], com_err)
        met["max_abs_torque"] = np.maximum(met["max_abs_torque"], np.max(np.abs(tau), axis=1))
        met["max_violation"] = np.maximum(met["max_violation"], out["qp_violation"])
        met["max_slip"] = np.maximum(met["max_slip"], slip)
        met["qp_infeasible_ticks"] += out["qp_infeasible"]
        met["nan"] |= ~finite | ~np.all(np.isfinite(tau), axis=1)
        met["last_time_off"] = np.where(com_err > RECOVERY_THRESHOLD, t_now, met["last_time_off"])
        met["min_com_height"] = np.minimum(met["min_com_height"], com[:, 2])
        met["ticks"] += 1
        if record:
            rec["com"][:, k] = com
            rec["tau"][:, k] = tau
            rec["f_cmd"][:, k] = out["f"]
            rec["qp_infeasible"][:, k] = out["qp_infeasible"]
    result = {
        "t": np.arange(T) * sp.control_dt,
        "com_ref": sp.ref_com_pos[:T].copy(),
        "metrics": met,
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


def summarize(metrics: dict, push_end: float = 0.0) -> list[dict]:
    """Per-environment summaries with the fields of :func:`wbc_jax.rollout.summarize`."""
    B = len(metrics["ticks"])
    out = []
    for i in range(B):
        ticks = max(int(metrics["ticks"][i]), 1)
        out.append({
            "fell": bool(metrics["fell"][i]),
            "nan": bool(metrics["nan"][i]),
            "com_rmse_m": float(np.sqrt(metrics["com_sq_err_sum"][i] / ticks)),
            "com_max_err_m": float(metrics["com_max_err"][i]),
            "max_constraint_violation": float(metrics["max_violation"][i]),
            "max_foot_slip_m": float(metrics["max_slip"][i]),
            "max_abs_torque_nm": float(metrics["max_abs_torque"][i]),
            "qp_infeasible_ticks": int(metrics["qp_infeasible_ticks"][i]),
            "time_to_recover_s": float(max(0.0, float(metrics["last_time_off"][i]) - push_end)),
            "min_com_height_m": float(metrics["min_com_height"][i]),
        })  # fmt: skip
    return out


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
    except BaseException:  # noqa: BLE001 - report everything to the parent
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
        spec, _ = make_spec(task=task, duration=duration, forces=forces, postural=postural)
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
            {k: r[k] for k in ("worker", "n_envs", "startup_s", "sim_wall_s", "jax_imported",
                               "timing")}  # fmt: skip
            for r in results
        ],
        "metrics": {
            k: np.concatenate([r["metrics"][k] for r in results]) for k in results[0]["metrics"]
        },
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
    """The CPU baseline on the scenario of experiments/benchmark.py (JSON-ready dict).

    Stand task over ``horizon`` s, default gains, one ``magnitude`` N horizontal push on the
    chest per environment, azimuths spread evenly over 360 deg (sweep.build_scenarios with one
    magnitude), at ``push_onset`` for ``push_duration`` s; ``n_workers`` processes (default:
    one per core)."""
    import platform

    sim = {"record": False}
    if solver_iterations is not None:
        sim["solver_iterations"] = int(solver_iterations)
    spec, gains = make_spec(task="stand", duration=horizon, sim=sim)
    azimuth = np.deg2rad(np.linspace(0.0, 360.0, n_envs, endpoint=False))
    force = magnitude * np.stack([np.cos(azimuth), np.sin(azimuth), np.zeros(n_envs)], 1)
    push = {"force": force[:, None, :], "onset": np.full((n_envs, 1), push_onset),
            "duration": np.full((n_envs, 1), push_duration)}  # fmt: skip
    r = run_parallel(n_envs, n_workers, spec=spec, gains=gains, push=push, timeout=timeout)
    met = r["metrics"]
    t0 = r["timing"]
    return {
        "baseline": "C MuJoCo mj_step + NumPy controller (quadprog), one process per worker",
        "cpu": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "mujoco": mujoco.__version__,
        "numpy": np.__version__,
        "batch": n_envs,
        "n_workers": r["n_workers"],
        "envs_per_worker": [w["n_envs"] for w in r["workers"]],
        "solver_iterations": int(spec.mj_model.opt.iterations),
        "horizon_s": horizon,
        "run_s": round(r["wall_s"], 4),
        "total_s_with_startup": round(r["total_wall_s"], 3),
        "physics_steps_per_s": r["steps_per_s"],
        "control_ticks_per_s": r["steps_per_s"] / spec.n_sub,
        "physics_steps_per_s_per_worker": r["steps_per_s_per_worker"],
        "worker0_controller_us_per_env_tick": t0["controller_us_per_env_tick"],
        "worker0_mj_step_us": t0["physics_us_per_mj_step"],
        "worker0_controller_share": t0["controller_s"] / t0["loop_s"],
        "worker_startup_s": [w["startup_s"] for w in r["workers"]],
        "workers_imported_jax": [w["jax_imported"] for w in r["workers"]],
        "survival": float(np.mean(~met["fell"] & ~met["nan"])),
        "com_max_dev_m_median": float(np.median(met["com_max_err"])),
    }


if __name__ == _WORKER_RUN_NAME:  # a worker process of run_parallel (runpy.run_path)
    _worker_main(_WORKER_JOB, _WORKER_CONN, _WORKER_START)  # noqa: F821
