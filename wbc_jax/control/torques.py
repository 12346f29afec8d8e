"""Joint torques from the free-floating dynamics and the contact constraints.

Substituting nu_dot from M nu_dot + h - J_c^T f = B tau into J_c nu_dot + Jdot_c nu = 0:

    Lambda tau = J_c M^-1 (h - J_c^T f) - Jdot_c nu,          Lambda = J_c M^-1 B   (D, n)
    tau = Lambda^+ (J_c M^-1 (h - J_c^T f) - Jdot_c nu) + N_Lambda tau_0,   N_Lambda = I - Lambda^+ Lambda
    tau_0 = h_s - M_sb M_b^-1 h_b - (J_s^T - M_sb M_b^-1 J_b^T) f + u_0         (postural task)

which is affine in the contact wrenches f (D,): tau = Sigma f + tau_model, with

    Sigma     = -(Lambda^+ J_c M^-1 J_c^T + N_Lambda (J_s^T - M_sb M_b^-1 J_b^T))   (n, D)
    tau_model = Lambda^+ (J_c M^-1 h - Jdot_c nu) + N_Lambda (h_s - M_sb M_b^-1 h_b + u_0)

Lambda^+ is the damped pseudo-inverse Lambda^T (Lambda Lambda^T + lambda I)^-1 (WBC
``Reg.pinvDamp`` = 1 in simulation). Rows of J_c are scaled by each contact's activation
(codyco ``torqueBalancing``), so contacts appear and vanish continuously.

Postural u_0, two variants:
* ``seed``  (seed paper, codyco C++):  u_0 = -K_imp (s - s_d) - K_d s_dot (diagonal gains);
* ``stable`` (Nava et al. 2016, WBC): u_0 = -K_P N_Lambda Mbar s~ - K_D N_Lambda Mbar s_dot with
  K_P = diag(k_p) pinv(N_Lambda Mbar) + 0.1 I and K_D = diag(k_d) pinv(N_Lambda Mbar).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from wbc_jax.core.math import damped_pinv
from wbc_jax.core.types import Array, pytree_dataclass
from wbc_jax.robot.dynamics import DynamicsTerms

POSTURAL_VARIANTS = ("stable", "seed")


@pytree_dataclass
class TorqueTerms:
    """Terms of the affine torque law tau = Sigma f + tau_model (n joints, D = contact wrench rows).

    Attributes:
      J_c:        (D, nv)  contact Jacobians, rows scaled by the activations
      Jdot_nu_c:  (D,)     their Jdot nu
      Lambda:     (D, n)   J_c M^-1 B
      Lambda_pinv:(n, D)   damped pseudo-inverse
      N_Lambda:   (n, n)   I - Lambda^+ Lambda
      Mbar:       (n, n)   joint-space inertia with the base eliminated
      Sigma:      (n, D)   d tau / d f
      tau_model:  (n,)     torques for f = 0 (postural task included)
      u0:         (n,)     postural term
      Sigma_c, tau_c: (n, D), (n,)  contact part Lambda^+ (J_c M^-1 (h - J_c^T f) - Jdot_c nu)
      Sigma_0, tau_0: (n, D), (n,)  postural tau_0 = Sigma_0 f + tau_0 (before N_Lambda), so
        Sigma = Sigma_c + N_Lambda Sigma_0 and tau_model = tau_c + N_Lambda tau_0; the motion-task
        hierarchy (:mod:`wbc_jax.control.hierarchy`) replaces tau_0 by its prioritised solution.
    """

    J_c: Array
    Jdot_nu_c: Array
    Lambda: Array
    Lambda_pinv: Array
    N_Lambda: Array
    Mbar: Array
    Sigma: Array
    tau_model: Array
    u0: Array
    Sigma_c: Array
    tau_c: Array
    Sigma_0: Array
    tau_0: Array


def postural_projector(
    Lambda: Array, Mbar: Array, pinv_damping: Array | float, pinv_tol: float, Mbar_factor: Array | None = None
) -> Array:
    """P (n, n) = pinv(X, tol) X for X = N_Lambda Mbar: the projector on X's right singular
    vectors whose singular values exceed ``pinv_tol`` (absolute, as MATLAB's ``pinv(X, tol)``).

    Lambda: (D, n); Mbar: (n, n) positive definite; pinv_damping > 0 (of N_Lambda's damped
    pseudo-inverse); Mbar_factor: (n, n) Mbar's lower Cholesky factor where the caller has it
    (:func:`torque_terms` reads it off M's), None: factorised here. With that pseudo-inverse N_Lambda = (I + Lambda^T Lambda / damping)^-1
    (Woodbury), so X^-1 = Mbar^-1 (I + Lambda^T Lambda / damping) = V S^-1 U^T and the cut
    directions are the eigenvectors of X^-1 X^-T = V S^-2 V^T with eigenvalues 1 / s^2 above
    1 / tol^2 (computed for damping X^-1, whose entries stay in float32's range for any damping).
    A symmetric eigensolver instead of X's SVD (batched on a GPU, the cheaper of the two), and in
    the form where the cut singular values are the large eigenvalues, which float32 resolves
    (X^T X would put them at 1e-11 next to rounding of 1e-8). Differentiable
    (:func:`spectral_projector`): the derivative is undefined only where a cut and a kept
    singular value coincide.
    """
    n = Mbar.shape[0]
    eye = jnp.eye(n, dtype=Mbar.dtype)
    L = jnp.linalg.cholesky(Mbar) if Mbar_factor is None else Mbar_factor
    X_inv_scaled = jax.scipy.linalg.cho_solve((L, True), pinv_damping * eye + Lambda.T @ Lambda)  # damping X^-1
    return eye - spectral_projector(X_inv_scaled @ X_inv_scaled.T, (pinv_damping / pinv_tol) ** 2)


@jax.custom_jvp
def spectral_projector(A: Array, threshold: Array | float) -> Array:
    """(n, n) the orthogonal projector V_c V_c^T on the eigenvectors of the symmetric A (n, n)
    whose eigenvalues exceed ``threshold`` (not differentiated: the cut is a step).

    Its derivative (a custom JVP) involves only pairs of a cut and a kept eigenvalue:

    .. math::

        dP = V (F + F^T) V^T, \\quad F_{ij} = \\frac{v_i^T dA\\, v_j}{\\lambda_i - \\lambda_j}
        \\ (i \\text{ cut}, j \\text{ kept}), \\ 0 \\text{ otherwise}.

    The eigenvector derivatives of ``jnp.linalg.eigh`` divide by every eigenvalue gap, so its JVP
    is NaN wherever two eigenvalues coincide, even with a zero tangent (inf x 0): at any
    left-right symmetric posture of the robot, whose mirrored limbs give equal pairs. The
    projector's derivative is defined there, and equals eigh's elsewhere."""
    _, V, cut = _cut_eigenvectors(A, threshold)
    return (V * cut) @ V.T


def _cut_eigenvectors(A, threshold):
    w, V = jnp.linalg.eigh(A)
    return w, V, w > threshold


@spectral_projector.defjvp
def _spectral_projector_jvp(primals, tangents):
    A, threshold = primals
    dA = tangents[0]
    w, V, cut = _cut_eigenvectors(A, threshold)
    across = cut[:, None] & ~cut[None, :]  # (i cut, j kept)
    gap = jnp.where(across, w[:, None] - w[None, :], 1.0)
    F = jnp.where(across, (V.T @ dA @ V) / gap, 0.0)
    return (V * cut) @ V.T, V @ (F + F.T) @ V.T


def postural_torque(
    variant: str,
    *,
    kp: Array,
    kd: Array,
    s_err: Array,
    s_dot: Array,
    N_Lambda: Array,
    Mbar: Array,
    Lambda: Array,
    pinv_damping: Array | float,
    pinv_tol: float = 1e-5,
    kp_reg: float = 0.1,
    freeze_projector: bool = False,
    Mbar_factor: Array | None = None,
) -> Array:
    """u_0 (n,) of the postural task (module docstring). kp, kd, s_err, s_dot: (n,); Mbar_factor:
    as :func:`postural_projector`'s.

    For ``stable``, diag(k) pinv(X) X v is evaluated as diag(k) P v with P = pinv(X) X
    (:func:`postural_projector`) for X = N_Lambda Mbar; P is formed from Lambda (D, n) and
    ``pinv_damping``, so N_Lambda must be I - damped_pinv(Lambda, pinv_damping) Lambda (no default
    damping: a mismatch would give a projector of another X). Holding P constant in derivatives
    (``freeze_projector``, kept for comparison) made reverse-mode gradients differ from central
    differences by up to 9 % (results/tuning/grad_check_sources.json); differentiated, they agree to 1e-6.
    """
    if variant == "seed":
        return -kp * s_err - kd * s_dot
    if variant == "stable":
        X = N_Lambda @ Mbar
        P = postural_projector(Lambda, Mbar, pinv_damping, pinv_tol, Mbar_factor)
        P = jax.lax.stop_gradient(P) if freeze_projector else P
        return -kp * (P @ s_err) - kp_reg * (X @ s_err) - kd * (P @ s_dot)
    raise ValueError(f"unknown postural variant {variant!r}; valid: {list(POSTURAL_VARIANTS)}")


def torque_terms(
    t: DynamicsTerms,
    J_c: Array,
    Jdot_nu_c: Array,
    *,
    postural: str,
    kp_postural: Array,
    kd_postural: Array,
    s_des: Array,
    pinv_damping: float = 1.0,
    pinv_tol: float = 1e-5,
    kp_postural_reg: float = 0.1,
    compensate_passive: bool = True,
    freeze_projector: bool = False,
) -> TorqueTerms:
    """Build the affine torque law at one state.

    Args:
      t: dynamics terms (mixed representation).
      J_c: (D, nv) contact Jacobians, rows scaled by the contacts' activations
        (:func:`wbc_jax.robot.contacts.row_activation`); Jdot_nu_c: (D,) their Jdot nu, scaled alike.
      postural: ``"stable"`` or ``"seed"``.
      kp_postural, kd_postural: (n,) postural gains.
      s_des: (n,) postural reference.
      pinv_damping: lambda of the damped pseudo-inverse of Lambda.
      pinv_tol: absolute singular-value tolerance of pinv(N_Lambda Mbar).
      kp_postural_reg: the 0.1 I added to K_P (WBC ``Reg.KP_postural``).
      compensate_passive: include the model's joint damping in the bias h.
      freeze_projector: hold the postural projector constant in derivatives (:func:`postural_torque`).

    Returns:
      :class:`TorqueTerms`.
    """
    n, D = t.s.shape[0], J_c.shape[0]
    M = t.M
    h = t.h - t.tau_passive if compensate_passive else t.h
    # One Cholesky factorisation of M serves every solve of the tick: M = L L^T with
    # L = [[L_b, 0], [L_sb, L_s]] gives M_sb M_b^-1 = L_sb L_b^-1 and the base-eliminated inertia
    # Mbar = M_s - M_sb M_b^-1 M_bs = L_s L_s^T, whose factor the postural projector solves with.
    L = jnp.linalg.cholesky(M)
    Minv = jax.scipy.linalg.cho_solve((L, True), jnp.concatenate([J_c.T, h[:, None]], axis=1))
    Minv_JcT, Minv_h = Minv[:, :D], Minv[:, D]  # (nv, D), (nv,)
    Lambda = Minv_JcT.T[:, 6:]  # M symmetric
    Lambda_pinv = damped_pinv(Lambda, pinv_damping)
    N_Lambda = jnp.eye(n, dtype=M.dtype) - Lambda_pinv @ Lambda

    L_b, L_sb, L_s = L[:6, :6], L[6:, :6], L[6:, 6:]
    Lb_inv = jax.scipy.linalg.solve_triangular(L_b, jnp.concatenate([h[:6, None], J_c[:, :6].T], axis=1), lower=True)
    Msb_Mb_inv_hb, Msb_Mb_inv_JbT = L_sb @ Lb_inv[:, 0], L_sb @ Lb_inv[:, 1:]
    Mbar = L_s @ L_s.T
    u0 = postural_torque(
        postural,
        kp=kp_postural,
        kd=kd_postural,
        s_err=t.s - s_des,
        s_dot=t.s_dot,
        N_Lambda=N_Lambda,
        Mbar=Mbar,
        Lambda=Lambda,
        pinv_damping=pinv_damping,
        pinv_tol=pinv_tol,
        kp_reg=kp_postural_reg,
        freeze_projector=freeze_projector,
        Mbar_factor=L_s,
    )
    Sigma_c = -Lambda_pinv @ (J_c @ Minv_JcT)
    tau_c = Lambda_pinv @ (J_c @ Minv_h - Jdot_nu_c)
    Sigma_0 = -(J_c[:, 6:].T - Msb_Mb_inv_JbT)
    tau_0 = h[6:] - Msb_Mb_inv_hb + u0
    Sigma = Sigma_c + N_Lambda @ Sigma_0
    tau_model = tau_c + N_Lambda @ tau_0
    return TorqueTerms(
        J_c=J_c,
        Jdot_nu_c=Jdot_nu_c,
        Lambda=Lambda,
        Lambda_pinv=Lambda_pinv,
        N_Lambda=N_Lambda,
        Mbar=Mbar,
        Sigma=Sigma,
        tau_model=tau_model,
        u0=u0,
        Sigma_c=Sigma_c,
        tau_c=tau_c,
        Sigma_0=Sigma_0,
        tau_0=tau_0,
    )
