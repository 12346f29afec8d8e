"""[hierarchy] Motion tasks below the force task, solved in recursive null spaces.

The force task (momentum rate through the contact wrenches f, with the contact constraints)
has the highest priority; it fixes f. The joint torques then read (:mod:`wbc_jax.torques`)

    tau = tau_c(f) + N_Lambda tau_0,          tau_c(f) = Sigma_c f + tau_c,

and the free-floating dynamics give the accelerations as an affine function of tau_0:

    nu_dot = nu_dot_c(f) + G tau_0,   nu_dot_c = M^-1 (B tau_c(f) + J_c^T f - h),   G = M^-1 B N_Lambda.

A motion task i asks J_i nu_dot + Jdot_i nu = nu_dot*_i, i.e. A_i tau_0 = b_i with A_i = J_i G and
b_i = nu_dot*_i - Jdot_i nu - J_i nu_dot_c. Levels are solved in priority order by recursive
null-space projection (Siciliano-Slotine):

    x_0 = 0, N_0 = I;   Ahat_i = A_i N_{i-1}
    x_i = x_{i-1} + Ahat_i^# (b_i - A_i x_{i-1})            (damped: singular tasks stay bounded)
    N_i = N_{i-1} - Ahat_i^+ Ahat_i                          (projector on the common null space)

and the postural task is last: tau_0 = x_k + N_k tau_0,postural(f). Ahat_i^# = Ahat_i^T (...)^-1
lies in the range of N_{i-1}, so a lower level never changes what the levels above achieve
(strict priority) unless an upper level is itself singular. The projectors use a tiny
regularisation relative to the level's scale instead of an SVD cut-off: smooth, so jit, vmap and
grad stay finite at rank changes.

With no motion task this is exactly tau = Sigma f + tau_model, the two-level law of the seed.
"""

from __future__ import annotations

import jax.numpy as jnp

from wbc_jax.dynamics import DynamicsTerms
from wbc_jax.torques import TorqueTerms
from wbc_jax.types import Array, pytree_dataclass

SOLUTION_DAMPING = 1e-6  # (s^2 units of A_i = J_i G): singular tasks get bounded torques
PROJECTOR_REG = 1e-12  # relative to the mean eigenvalue of Ahat Ahat^T (plus the same absolute)


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
    """tau (n,) unsaturated torques; tau0 (n,) the null-space torque; nu_dot (nv,) the
    accelerations the model predicts for (tau, f); task_acc: per level J_i nu_dot + Jdot_i nu."""

    tau: Array
    tau0: Array
    nu_dot: Array
    task_acc: tuple


def _projector(A_hat: Array, reg: float) -> Array:
    """Ahat^T (Ahat Ahat^T + eps I)^-1 Ahat (n, n): the projector on the row space of Ahat."""
    m = A_hat.shape[0]
    AAt = A_hat @ A_hat.T
    eps = reg * (jnp.trace(AAt) / m + 1.0)
    return A_hat.T @ jnp.linalg.solve(AAt + eps * jnp.eye(m, dtype=A_hat.dtype), A_hat)


def solve(
    t: DynamicsTerms,
    tt: TorqueTerms,
    f: Array,
    levels: tuple[TaskLevel, ...] | list[TaskLevel],
    *,
    solution_damping: float = SOLUTION_DAMPING,
    projector_reg: float = PROJECTOR_REG,
    compensate_passive: bool = True,
) -> HierarchySolution:
    """Joint torques for contact wrenches f (12,) with the motion-task levels in priority order.

    Args:
      t: dynamics terms. tt: torque terms at the same state (:func:`wbc_jax.torques.torque_terms`).
      f: (12,) feet wrenches chosen by the force task.
      levels: motion tasks in priority order (highest first), each a :class:`TaskLevel`; the
        postural task of ``tt`` is the implicit last level.
      solution_damping: damping of each level's pseudo-inverse.
      projector_reg: relative regularisation of the null-space projectors.
      compensate_passive: as in :func:`wbc_jax.torques.torque_terms` (same bias h).

    Returns:
      :class:`HierarchySolution`.
    """
    n = tt.N_Lambda.shape[0]
    dtype = t.M.dtype
    h = t.h - t.tau_passive if compensate_passive else t.h
    tau_c = tt.Sigma_c @ f + tt.tau_c
    tau0_postural = tt.Sigma_0 @ f + tt.tau_0
    B_tau_c = jnp.zeros_like(h).at[6:].set(tau_c)
    B_N = jnp.zeros((n + 6, n), dtype).at[6:].set(tt.N_Lambda)
    sol = jnp.linalg.solve(t.M, jnp.concatenate([(B_tau_c + tt.J_c.T @ f - h)[:, None], B_N], axis=1))
    nu_dot_c, G = sol[:, 0], sol[:, 1:]

    x = jnp.zeros(n, dtype)
    N = jnp.eye(n, dtype=dtype)
    for level in levels:
        A = level.J @ G
        b = level.nu_dot_star - level.Jdot_nu - level.J @ nu_dot_c
        A_hat = A @ N
        m = A_hat.shape[0]
        A_hat_sharp = jnp.linalg.solve(
            A_hat @ A_hat.T + solution_damping * jnp.eye(m, dtype=dtype), A_hat
        ).T
        x = x + A_hat_sharp @ (b - A @ x)
        N = N - _projector(A_hat, projector_reg)
    tau0 = x + N @ tau0_postural
    nu_dot = nu_dot_c + G @ tau0
    task_acc = tuple(level.J @ nu_dot + level.Jdot_nu for level in levels)
    return HierarchySolution(tau=tau_c + tt.N_Lambda @ tau0, tau0=tau0, nu_dot=nu_dot, task_acc=task_acc)
