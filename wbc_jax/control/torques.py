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

import functools

import jax
import jax.numpy as jnp

from wbc_jax.core.math import batch_any, cho_solve_spd, cholesky_solve, damped_pinv
from wbc_jax.core.types import Array, pytree_dataclass
from wbc_jax.robot.dynamics import DynamicsTerms

POSTURAL_VARIANTS = ("stable", "seed")
MASS_SOLVE_ENGINES = ("jax", "warp")
"""Who factorises M and solves with it (:func:`torque_terms`): JAX (:func:`wbc_jax.core.math.cholesky_solve`) or one
Warp tile kernel per batch (:mod:`wbc_jax.control.cholesky_warp`; needs warp-lang)."""

MASS_SOLVE_CHOICES = ("auto",) + MASS_SOLVE_ENGINES
"""What ``ControllerConfig.mass_solve_engine`` takes: an engine, or ``auto`` (:func:`resolve_mass_solve_engine`)."""


def resolve_mass_solve_engine(engine: str) -> str:
    """The engine that ``engine`` names here: itself, or for ``auto`` the Warp kernel where JAX's default device is a
    GPU and warp-lang is installed (:func:`wbc_jax.control.warp_launch.gpu_default`), else JAX's solve."""
    if engine != "auto":
        return engine
    from wbc_jax.control import warp_launch

    return "warp" if warp_launch.gpu_default() else "jax"


RITZ_ENGINES = ("jax", "warp")
"""Who computes the ``stable`` projector's Ritz decomposition (:func:`spectral_projector`): JAX
(:func:`ritz_decomposition`) or one Warp kernel per batch (:mod:`wbc_jax.control.ritz_warp`; needs warp-lang)."""


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
    Lambda: Array,
    Mbar: Array,
    pinv_damping: Array | float,
    pinv_tol: float,
    Mbar_inv: Array | None = None,
    ritz_engine: str = "jax",
) -> Array:
    """P (n, n) = pinv(X, tol) X for X = N_Lambda Mbar: the projector on X's right singular
    vectors whose singular values exceed ``pinv_tol`` (absolute, as MATLAB's ``pinv(X, tol)``).

    Lambda: (D, n); Mbar: (n, n) positive definite; pinv_damping > 0 (of N_Lambda's damped
    pseudo-inverse); Mbar_inv: (n, n) Mbar^-1 where the caller has it (:func:`torque_terms` reads
    it off its solve with M), None: solved here; ritz_engine: :data:`RITZ_ENGINES` (:func:`spectral_projector`).
    With that pseudo-inverse N_Lambda = (I + Lambda^T Lambda / damping)^-1
    (Woodbury), so X^-1 = Mbar^-1 (I + Lambda^T Lambda / damping) = V S^-1 U^T and the cut
    directions are the eigenvectors of X^-1 X^-T = V S^-2 V^T with eigenvalues 1 / s^2 above
    1 / tol^2 (computed for damping X^-1, whose entries stay in float32's range for any damping).
    A symmetric eigensolver instead of X's SVD (batched on a GPU, the cheaper of the two), and in
    the form where the cut singular values are the large eigenvalues, which float32 resolves
    (X^T X would put them at 1e-11 next to rounding of 1e-8). Differentiable
    (:func:`spectral_projector`): the derivative is undefined only where a cut and a kept
    singular value coincide.

    The cut directions lie near Mbar^-1 Lambda^T's D columns, :func:`spectral_projector`'s start:
    damping X^-1 = E + F with E = damping Mbar^-1 and F = Mbar^-1 Lambda^T Lambda of rank D, so a
    cut direction u (singular value of damping X^-1 above damping / tol) lies within
    sin = tol |Mbar^-1| of F's range (3e-3 for the default robot), and at most D are cut where that is below 1.
    """
    A, threshold, start = projector_problem(Lambda, Mbar, pinv_damping, pinv_tol, Mbar_inv)
    return jnp.eye(Mbar.shape[0], dtype=Mbar.dtype) - spectral_projector(A, threshold, start, ritz_engine)


def projector_problem(Lambda, Mbar, pinv_damping, pinv_tol, Mbar_inv):
    """(A (n, n), threshold, start (n, D)): the eigenproblem of :func:`postural_projector`."""
    eye = jnp.eye(Mbar.shape[0], dtype=Mbar.dtype)
    Mbar_inv = cho_solve_spd(Mbar, eye) if Mbar_inv is None else Mbar_inv
    X_inv_scaled = Mbar_inv @ (pinv_damping * eye + Lambda.T @ Lambda)  # damping X^-1
    return X_inv_scaled @ X_inv_scaled.T, (pinv_damping / pinv_tol) ** 2, Mbar_inv @ Lambda.T


def projector_certified(
    t: DynamicsTerms,
    J_c: Array,
    *,
    pinv_damping: Array | float = 1.0,
    pinv_tol: float = 1e-5,
    compensate_passive: bool = True,
) -> Array:
    """() bool: whether the ``stable`` postural projector that :func:`torque_terms` builds at this
    state (same arguments, same computations) is its Ritz start's, certified
    (:func:`spectral_projector`); False: the tick needs the whole ``eigh``, and under vmap the
    batch runs it for every environment. A diagnostic (benchmarks/profile_tick.py)."""
    D = J_c.shape[0]
    L, _, Minv = _mass_solve(t, J_c, compensate_passive, stable=True)
    Mbar = L[6:, 6:] @ L[6:, 6:].T
    problem = projector_problem(Minv[:, :D].T[:, 6:], Mbar, pinv_damping, pinv_tol, Minv[6:, D + 1 :])
    return ritz_projector(*problem)[1]


@functools.partial(jax.custom_jvp, nondiff_argnums=(3,))
def spectral_projector(
    A: Array, threshold: Array | float, start: Array | None = None, ritz_engine: str = "jax"
) -> Array:
    """(n, n) the orthogonal projector V_c V_c^T on the eigenvectors of the symmetric A (n, n)
    whose eigenvalues exceed ``threshold`` (not differentiated: the cut is a step).

    ``start`` (n, k): columns whose span is near the cut eigenvectors' (k < n). Then the cut
    directions are first taken from A's Ritz vectors on the span of A start (a QR and a k x k
    ``eigh``, on a CPU cheaper than the n x n one, the postural task's dearest op), and kept where
    they are certified to be what the whole eigenproblem gives, to its rounding: their residual
    |A V_c - V_c Theta_c| at most n eps |A| (eigh's backward error; the projector's error is that
    over the gap to the other eigenvalues, for either), and the rest of A, (I - P) A (I - P), of
    Frobenius norm below the threshold (no cut direction missed; Ritz values never exceed the
    eigenvalues they approximate, so none is cut wrongly). Elsewhere the whole eigenproblem runs.

    Its derivative (a custom JVP, from the whole eigendecomposition) involves only pairs of a cut
    and a kept eigenvalue:

    .. math::

        dP = V (F + F^T) V^T, \\quad F_{ij} = \\frac{v_i^T dA\\, v_j}{\\lambda_i - \\lambda_j}
        \\ (i \\text{ cut}, j \\text{ kept}), \\ 0 \\text{ otherwise}.

    The eigenvector derivatives of ``jnp.linalg.eigh`` divide by every eigenvalue gap, so its JVP
    is NaN wherever two eigenvalues coincide, even with a zero tangent (inf x 0): at any
    left-right symmetric posture of the robot, whose mirrored limbs give equal pairs. The
    projector's derivative is defined there, and equals eigh's elsewhere.

    ``ritz_engine``: who computes the Ritz decomposition, :data:`RITZ_ENGINES` (the certification is the same)."""
    if start is None:
        return _projector(*_cut_eigenvectors(A, threshold)[1:])
    P, certified = ritz_projector(A, threshold, start, ritz_decomposer(ritz_engine))
    # batch_any: a branch under vmap too, the whole eigenproblem only in ticks where some robot needs it.
    return jax.lax.cond(batch_any(~certified), lambda: _projector(*_cut_eigenvectors(A, threshold)[1:]), lambda: P)


def _projector(V, cut):
    return (V * cut) @ V.T


def _cut_eigenvectors(A, threshold):
    w, V = jnp.linalg.eigh(A)
    return w, V, w > threshold


def ritz_decomposition(A: Array, B: Array) -> tuple[Array, Array, Array, Array]:
    """(Q (n, k), A Q (n, k), theta (k,), W (k, k)): Q an orthonormal basis of B's (n, k) columns (Householder QR),
    and the eigenpairs of Q' A Q (ascending) for the symmetric A (n, n): A's Ritz pairs on span(B) are theta, Q W."""
    Q = jnp.linalg.qr(B)[0]
    AQ = A @ Q
    theta, W = jnp.linalg.eigh(Q.T @ AQ)
    return Q, AQ, theta, W


def ritz_decomposer(engine: str):
    """The Ritz decomposition of ``engine`` (:data:`RITZ_ENGINES`): ``jax`` :func:`ritz_decomposition`, ``warp``
    the same as one Warp kernel (:func:`wbc_jax.control.ritz_warp.ritz_decomposition_warp`)."""
    if engine == "jax":
        return ritz_decomposition
    if engine == "warp":
        from wbc_jax.control.ritz_warp import ritz_decomposition_warp

        return ritz_decomposition_warp
    raise ValueError(f"unknown ritz_engine {engine!r}; valid: {list(RITZ_ENGINES)}")


def ritz_projector(A, threshold, start, decompose=ritz_decomposition):
    """The projector on A's Ritz vectors (on the span of A start) above ``threshold`` and whether
    it is certified (:func:`spectral_projector`). ``decompose``: (A, B) -> (Q, A Q, theta, W) as
    :func:`ritz_decomposition` (benchmarks/projector_cost.py measures other bases through it)."""
    n = A.shape[0]
    Q, AQ, ritz, W = decompose(A, A @ start)
    cut = ritz > threshold
    V = Q @ W
    P = _projector(V, cut)
    residual = (AQ @ W - V * ritz) * cut  # A V_c - V_c Theta_c
    rest = A - P @ A - A @ P + P @ A @ P  # (I - P) A (I - P)
    eps = jnp.finfo(A.dtype).eps
    norm = jnp.sqrt(jnp.sum(A * A))
    certified = (jnp.sqrt(jnp.sum(residual * residual)) <= n * eps * norm) & (
        jnp.sqrt(jnp.sum(rest * rest)) < threshold
    )
    return P, certified


@spectral_projector.defjvp
def _spectral_projector_jvp(ritz_engine, primals, tangents):
    A, threshold, start = primals
    dA = tangents[0]
    w, V, cut = _cut_eigenvectors(A, threshold)
    across = cut[:, None] & ~cut[None, :]  # (i cut, j kept)
    gap = jnp.where(across, w[:, None] - w[None, :], 1.0)
    F = jnp.where(across, (V.T @ dA @ V) / gap, 0.0)
    P = _projector(V, cut) if start is None else spectral_projector(A, threshold, start, ritz_engine)
    return P, V @ (F + F.T) @ V.T


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
    Mbar_inv: Array | None = None,
    ritz_engine: str = "jax",
) -> Array:
    """u_0 (n,) of the postural task (module docstring). kp, kd, s_err, s_dot: (n,); Mbar_inv, ritz_engine:
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
        P = postural_projector(Lambda, Mbar, pinv_damping, pinv_tol, Mbar_inv, ritz_engine)
        P = jax.lax.stop_gradient(P) if freeze_projector else P
        return -kp * (P @ s_err) - kp_reg * (N_Lambda @ (Mbar @ s_err)) - kd * (P @ s_dot)
    raise ValueError(f"unknown postural variant {variant!r}; valid: {list(POSTURAL_VARIANTS)}")


def _mass_solve(t: DynamicsTerms, J_c: Array, compensate_passive: bool, stable: bool, engine: str = "jax"):
    """(L, h, Minv): M = L L^T, the bias h, M^-1 (J_c^T, h[, the joint columns of I]).

    One Cholesky factorisation of M and one solve with stacked right-hand sides serve the tick:
    M^-1 (J_c^T, h) and, for the projector (``stable``), M^-1's joint columns, whose joint block is
    Mbar^-1 (the base-eliminated inertia Mbar = M_s - M_sb M_b^-1 M_bs = L_s L_s^T). ``engine``:
    :data:`MASS_SOLVE_ENGINES`."""
    n, M = t.s.shape[0], t.M
    h = t.h - t.tau_passive if compensate_passive else t.h
    columns = [J_c.T, h[:, None]]
    if stable:
        columns.append(jnp.eye(n + 6, n, -6, dtype=M.dtype))
    B = jnp.concatenate(columns, axis=1)
    if engine == "warp":
        from wbc_jax.control import cholesky_warp  # Warp only where asked for

        L, Minv = cholesky_warp.cholesky_solve_warp(M, B)
    elif engine == "jax":
        L, Minv = cholesky_solve(M, B)
    else:
        raise ValueError(f"unknown mass_solve_engine {engine!r}; valid: {list(MASS_SOLVE_ENGINES)}")
    return L, h, Minv


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
    mass_solve_engine: str = "jax",
    ritz_engine: str = "jax",
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
      mass_solve_engine: who factorises M and solves with it, :data:`MASS_SOLVE_ENGINES`.
      ritz_engine: who computes the postural projector's Ritz decomposition, :data:`RITZ_ENGINES`.

    Returns:
      :class:`TorqueTerms`.
    """
    n, D = t.s.shape[0], J_c.shape[0]
    M = t.M
    stable = postural == "stable"
    L, h, Minv = _mass_solve(t, J_c, compensate_passive, stable, mass_solve_engine)
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
        Mbar_inv=Minv[6:, D + 1 :] if stable else None,
        ritz_engine=ritz_engine,
    )
    Sigma_c = -Lambda_pinv @ (J_c @ Minv_JcT)
    tau_c = Lambda_pinv @ (J_c @ Minv_h - Jdot_nu_c)
    # The joint rows of M x = r give r_s - M_sb M_b^-1 r_b = Mbar x_s: with x = M^-1 (J_c^T, h), at hand.
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
