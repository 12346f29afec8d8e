"""The controller tick in NumPy (:class:`NumpyController`), batched over environments, with its
contact-wrench QPs solved by quadprog (:func:`solve_qp`)."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import mujoco
import numpy as np
import quadprog

from .spec import GRAVITY, QP_FALLBACK_TOL, BaselineSpec

_NULL_DIM = 6  # the two feet's wrenches (12) less the momentum equality's rows (6)


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


def skew(v: np.ndarray) -> np.ndarray:
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
            M=np.zeros((B, nv, nv)),
            J=np.zeros((B, 2, 6, nv)),
            Jd=np.zeros((B, 2, 6, nv)),
            qpos=np.zeros((B, nq)),
            qvel=np.zeros((B, nv)),
            bias=np.zeros((B, nv)),
            passive=np.zeros((B, nv)),
            xmat=np.zeros((B, 9)),
            site_xpos=np.zeros((B, 2, 3)),
            site_xmat=np.zeros((B, 2, 9)),
            com=np.zeros((B, 3)),
            vcom=np.zeros((B, 3)),
            angmom=np.zeros((B, 3)),
        )

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
            nu=nu,
            s=buf["qpos"][:, sp.qpos_joints],
            s_dot=nu[:, 6:],
            W_R_B=R,
            M=M,
            h=h,
            tau_passive=tp,
            J_feet=J,
            Jdot_nu_feet=_mv(buf["Jd"], qvel[:, None]),
            W_p_feet=buf["site_xpos"].copy(),
            W_R_feet=buf["site_xmat"].reshape(B, 2, 3, 3).copy(),
            W_p_CoM=buf["com"].copy(),
            W_v_CoM=buf["vcom"].copy(),
            L_ang=buf["angmom"].copy(),
        )

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
            "tau": tau,
            "tau_unsat": tau_unsat,
            "f": f,
            "Ldot_star": Ldot_star,
            "Ldot_cmd": mv(A, f) + self.f_grav,
            "qp_infeasible": infeasible,
            "qp_violation": self.constraint_violation(f, t.W_R_feet, act, C_feet),
        }
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

        forces.null_space orthonormalises N_A's columns outside a sole (Cholesky); the QPs' solution
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
        N[:, 9:, :3] = -skew(W_p_feet[:, 0] - W_p_feet[:, 1])
        return np.linalg.qr(N)[0]

    @staticmethod
    def wrench_map(W_p_feet: np.ndarray, W_p_CoM: np.ndarray) -> np.ndarray:
        """A (B, 6, 12) of forces.wrench_map for W_p_feet (B, 2, 3), W_p_CoM (B, 3)."""
        B = W_p_feet.shape[0]
        A = np.zeros((B, 6, 2, 6))
        i6 = np.arange(6)
        A[:, i6, :, i6] = 1.0
        A[:, 3:, :, :3] = skew(W_p_feet - W_p_CoM[:, None]).transpose(0, 2, 1, 3)
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
