"""Motion tasks below the force task, solved in recursive null spaces.

The force task (momentum rate through the contact wrenches f, with the contact constraints)
has the highest priority; it fixes f. The joint torques then read (:mod:`wbc_jax.control.torques`)

    tau = tau_c(f) + N_Lambda tau_0,          tau_c(f) = Sigma_c f + tau_c,

and the free-floating dynamics give the accelerations as an affine function of tau_0:

    nu_dot = nu_dot_c(f) + G tau_0,   nu_dot_c = M^-1 (B tau_c(f) + J_c^T f - h),   G = M^-1 B N_Lambda.

Motion-task torques tau_m are kept in the exact null space of Lambda = J_c M^-1 B: they change no
contact acceleration, so MuJoCo's contact wrenches (hence the force task) stay as commanded (the
damped N_Lambda of the seed's law lets ~50 % of some contact directions through, which a hand task
turned into foot slip and a 5 mm CoM error). There N_Lambda tau_m = tau_m, and a motion task i asks
J_i nu_dot + Jdot_i nu = nu_dot*_i, i.e. A_i tau_m = b_i with A_i = J_i M^-1 B and
b_i = nu_dot*_i - Jdot_i nu - J_i nu_dot_c. Levels are solved in priority order by recursive
null-space projection (Siciliano-Slotine):

    x_0 = 0, N_0 = I - Lambda^+ Lambda;   Ahat_i = A_i N_{i-1}
    x_i = x_{i-1} + Ahat_i^# (b_i - A_i x_{i-1})            (damped: singular tasks stay bounded)
    N_i = N_{i-1} - Ahat_i^+ Ahat_i                          (projector on the common null space)

with the effort-bounded pseudo-inverse Ahat_i^# (:func:`_effort_gain`): a direction of the task that
the levels above leave a fraction rho of its gain A0_i = A_i N_0 (the contacts alone) gets
phi = rho^4 / (rho^4 + mu (1 - rho^2)^2) of its acceleration (mu = 1: 100 % at rho = 1, 95 % at 0.9,
48 % at 0.7, 3.5 % at 0.4), and the postural task keeps 1 - phi of it (N_P below: it yields only what
the level uses). The plain least squares (mu = 0) drove such directions at any cost, and the postural
task yielded them whole: a hand task below a posture task on the torso and the right arm reached the
hand through the momentum of the left arm and the legs (rho = 0.39, 0.19, 0.05: up to 10 N m per m/s^2
on the left elbow), which nothing then held; the robot fell. The first level (Ahat = A0) keeps its
plain damped pseudo-inverse.

and the postural task is last. Its torque is tau_0,postural = tau_0,model(f) + u_0: the model part
(h_s - M_sb M_b^-1 h_b - (J_s^T - M_sb M_b^-1 J_b^T) f) is what makes the damped law consistent with
the contacts, so it stays whole (the motion tasks' b_i include its accelerations); only the
feedback u_0 yields: tau_0 = tau_0,model + x_k + P_k u_0, where P_k projects on the null space of
the stacked J_i M^-1 B N_Lambda (u_0 passes through the damped N_Lambda).
Ahat_i^# = Ahat_i^T (...)^-1 lies in the range of N_{i-1}, so a lower level never changes what the
levels above achieve (strict priority) unless an upper level is itself singular. The damping and
the projectors' row floor are relative to the scale of the *unprojected* A_i (mean eigenvalue of
A_i A_i^T; the projectors are built from unit-norm rows), so a level that the levels above block
entirely (A_i N_{i-1} = rounding noise) gets
no torque from that noise; they replace an SVD cut-off: smooth, so jit, vmap and grad stay finite
at rank changes. A regularised projector leaves A_j N_i = O(eps / s^2) instead of 0, which a lower
level's pseudo-inverse amplifies by 1 / damping; squaring N_i (idempotent if exact) squares that
leak, so what remains is rounding (1e-16 / damping in float64: strict priority to ~1e-10
relative). Their defaults depend on the precision (float32 rounding is ~1e-7 relative).

With no motion task this is exactly tau = Sigma f + tau_model, the two-level law of the seed.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from wbc_jax.control.torques import TorqueTerms
from wbc_jax.core.types import Array, pytree_dataclass
from wbc_jax.robot.dynamics import DynamicsTerms

# Defaults by precision {float64: 8 bytes, float32: 4}; ``ControllerConfig`` may override them.
# Damping relative to the mean eigenvalue of A_i A_i^T.
SOLUTION_DAMPING = {8: 1e-6, 4: 1e-3}  # singular directions get bounded torques
# Projectors work on unit-norm rows (see null_space_step): directions below sqrt(reg) count as singular.
PROJECTOR_REG = {8: 1e-12, 4: 1e-5}
_TINY = {8: 1e-150, 4: 1e-18}  # keeps an all-zero level (an inactive contact) regular
ROW_FLOOR = {8: 1e-12, 4: 1e-6}  # rows with |row|^2 below this x the level scale: not normalised


@pytree_dataclass
class TaskLevel:
    """One priority level: m stacked rows (several equal-priority tasks, rows scaled by sqrt(weight)).

    Attributes:
      J: (m, nv) task Jacobian (mixed representation);  Jdot_nu: (m,);  nu_dot_star: (m,)
    """

    J: Array
    Jdot_nu: Array
    nu_dot_star: Array


@pytree_dataclass
class HierarchySolution:
    """tau (n,) unsaturated torques; tau0 (n,) the null-space torque; tau_motion (n,) its motion-task
    part (in the null space of Lambda); nu_dot (nv,) the accelerations the model predicts for
    (tau, f); task_acc: per level J_i nu_dot + Jdot_i nu."""

    tau: Array
    tau0: Array
    tau_motion: Array
    nu_dot: Array
    task_acc: tuple


def _effort_gain(G_hat: Array, G_0: Array, mu: float, eps: float) -> Array:
    """W (m, m) of the effort-bounded pseudo-inverse Ahat^T W (module docstring): with L L^T = G_0
    (m, m, the level's Gram without the levels above, damped) and M = L^-1 G_hat L^-T (G_hat the
    projected Gram; eigenvalues rho^2 in [0, 1]), W = L^-T M (M^2 + mu (I - M)^2 + eps I)^-1 L^-1,
    so that Ahat Ahat^T W = L phi(M) L^-1, phi(rho^2) = rho^4 / (rho^4 + mu (1 - rho^2)^2 + eps).
    mu = 0: the damped pseudo-inverse in the metric of G_0."""
    eye = jnp.eye(G_0.shape[0], dtype=G_0.dtype)
    L_inv = jax.scipy.linalg.solve_triangular(jnp.linalg.cholesky(G_0), eye, lower=True)
    M = L_inv @ G_hat @ L_inv.T
    core = jnp.linalg.solve(M @ M + mu * (eye - M) @ (eye - M) + eps * eye, M)  # M, M^2 commute
    return L_inv.T @ core @ L_inv


def _regularised_pinv(A_hat: Array, eps: Array) -> Array:
    """Ahat^T (Ahat Ahat^T + eps I)^-1 (n, m)."""
    m = A_hat.shape[0]
    return jnp.linalg.solve(A_hat @ A_hat.T + eps * jnp.eye(m, dtype=A_hat.dtype), A_hat).T


def solve(
    t: DynamicsTerms,
    tt: TorqueTerms,
    f: Array,
    levels: tuple[TaskLevel, ...] | list[TaskLevel],
    *,
    solution_damping: float | None = None,
    projector_reg: float | None = None,
    compensate_passive: bool = True,
    effort_damping: float = 1.0,
) -> HierarchySolution:
    """Joint torques for contact wrenches f (D,) with the motion-task levels in priority order.

    Args:
      t: dynamics terms. tt: torque terms at the same state (:func:`wbc_jax.control.torques.torque_terms`).
      f: (D,) contact wrenches chosen by the force task.
      levels: motion tasks in priority order (highest first), each a :class:`TaskLevel`; the
        postural task of ``tt`` is the implicit last level.
      solution_damping: damping of each level's pseudo-inverse, relative to the level's scale
        (None: ``SOLUTION_DAMPING`` for the dtype).
      projector_reg: relative regularisation of the null-space projectors (None: ``PROJECTOR_REG``).
      compensate_passive: as in :func:`wbc_jax.control.torques.torque_terms` (same bias h).
      effort_damping: mu >= 0 of the levels' effort-bounded pseudo-inverses (module docstring);
        0: plain hierarchical least squares.

    Returns:
      :class:`HierarchySolution`.
    """
    n = tt.N_Lambda.shape[0]
    dtype = t.M.dtype
    size = jnp.dtype(dtype).itemsize
    damping = SOLUTION_DAMPING[size] if solution_damping is None else solution_damping
    reg = PROJECTOR_REG[size] if projector_reg is None else projector_reg
    h = t.h - t.tau_passive if compensate_passive else t.h
    tau_c = tt.Sigma_c @ f + tt.tau_c
    # tau_0 = tau_0,model(f) + u_0: the model part makes the damped law contact-consistent (Nava
    # 2016) and is kept whole; only the postural feedback u_0 yields to the motion tasks.
    tau0_model = tt.Sigma_0 @ f + tt.tau_0 - tt.u0
    B_tau_c = jnp.zeros_like(h).at[6:].set(tau_c)
    B_N = jnp.zeros((n + 6, n), dtype).at[6:].set(tt.N_Lambda)
    sol = jnp.linalg.solve(t.M, jnp.concatenate([(B_tau_c + tt.J_c.T @ f - h)[:, None], B_N], axis=1))
    nu_dot_c, G = sol[:, 0], sol[:, 1:]
    nu_dot_c = nu_dot_c + G @ tau0_model

    mu = effort_damping

    def unit_rows(A_hat, scale):
        # Rows scaled to unit norm first (same null space): the rows of one level differ in scale
        # by the inertia they move (leg joints vs. arm joints: ~1e3 in A A^T), so a regularisation
        # relative to the level's mean would count the heavy rows as singular and leave them free
        # for the levels below. Rows below ROW_FLOOR x the level scale (what the levels above
        # block, rounding noise) are not amplified to unit norm.
        return jnp.sqrt(jnp.sum(A_hat * A_hat, axis=1, keepdims=True) + ROW_FLOOR[size] * scale)

    def null_space_step(N, A_hat, scale):
        A_unit = A_hat / unit_rows(A_hat, scale)
        N = N - _regularised_pinv(A_unit, jnp.asarray(reg, dtype)) @ A_unit
        return N @ N  # = N for an exact projector; squares the regularisation's leak (eps / s^2)

    def used(A_hat, A_ref, scale):
        # The part of the postural torques a level takes: its directions, each by the fraction phi
        # of its acceleration it gets (A_ref: its gain without the levels above).
        d = unit_rows(A_hat, scale)
        A_unit, R = A_hat / d, A_ref / d
        W = _effort_gain(A_unit @ A_unit.T, R @ R.T + reg * jnp.eye(A_hat.shape[0], dtype=dtype), mu, reg)
        return A_unit.T @ W @ A_unit

    # Motion-task torques stay in the exact null space of Lambda (N_S starts there): they change no
    # contact acceleration, so the contact wrenches, hence the force task, are left as they were.
    # The postural torque, filtered by the damped N_Lambda of the seed's law, yields to what the
    # levels use of their directions (N_P), each level's within the exact null space of the levels
    # above (N_Q): so no level's acceleration depends on the levels below it.
    Lam = tt.Lambda
    x = jnp.zeros(n, dtype)
    N_S = null_space_step(jnp.eye(n, dtype=dtype), Lam, jnp.sum(Lam * Lam) / Lam.shape[0] + _TINY[size])
    N_0 = N_S
    N_P = N_Q = jnp.eye(n, dtype=dtype)
    Minv_B = jnp.linalg.solve(t.M, jnp.zeros((n + 6, n), dtype).at[6:].set(jnp.eye(n, dtype=dtype)))
    for level in levels:
        A = level.J @ G  # postural torque -> task acceleration
        A_S = level.J @ Minv_B  # motion torque (in null(Lambda), where N_Lambda = I) -> acceleration
        b = level.nu_dot_star - level.Jdot_nu - level.J @ nu_dot_c
        A_hat, A_0 = A_S @ N_S, A_S @ N_0
        scale = jnp.sum(A_S * A_S) / A_S.shape[0] + _TINY[size]
        # Effort-bounded pseudo-inverse (module docstring); the first level (A_hat = A_0): plain.
        W = _effort_gain(
            A_hat @ A_hat.T, A_0 @ A_0.T + damping * scale * jnp.eye(A_hat.shape[0], dtype=dtype), mu, damping
        )
        x = x + A_hat.T @ (W @ (b - A_S @ x))
        N_S = null_space_step(N_S, A_hat, scale)
        A_Q, scale_P = A @ N_Q, jnp.sum(A * A) / A.shape[0] + _TINY[size]
        N_P = N_P - used(A_Q, A, scale_P)
        N_Q = null_space_step(N_Q, A_Q, scale_P)
    tau0 = tau0_model + x + N_P @ tt.u0
    nu_dot = nu_dot_c + G @ (tau0 - tau0_model)
    task_acc = tuple(level.J @ nu_dot + level.Jdot_nu for level in levels)
    return HierarchySolution(tau=tau_c + tt.N_Lambda @ tau0, tau0=tau0, tau_motion=x, nu_dot=nu_dot, task_acc=task_acc)
