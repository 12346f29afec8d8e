"""Contact-wrench quadratic programs of the WBC balancing controller, in JAX.

Each control tick of the iCub balancing controller (robotology
whole-body-controllers, controller-spec §1.7) solves one tiny dense QP for the
feet wrenches. This module provides

* :class:`ContactParams` and :func:`foot_constraints` /
  :func:`world_constraints`: the rigid-contact constraint set ``C f <= b`` of
  ``wbc.computeRigidContactConstraints`` (linearised friction cone, torsional
  friction, unilaterality, centre of pressure in the sole rectangle);
* :func:`solve_qp`: a generic dense QP solver ``min 1/2 x'Hx + g'x  s.t.
  Cx <= b`` that runs under ``jit``/``vmap``/``lax.scan`` and is differentiable
  in reverse *and* forward mode;
* :func:`two_feet_wrenches` and :func:`one_foot_wrench`: the two contact-force
  QPs of the controller.

Wrenches are ``[force; moment]``, applied at the sole origin. ``f_L``/``f_R``
and the arguments of the QP wrappers are in world axes.

Algorithm of :func:`solve_qp` and why
-------------------------------------
A primal-dual interior-point method (Mehrotra predictor-corrector) run for a
*fixed* number of Newton steps in ``lax.scan``:

* The problems are tiny and dense (n <= 12, m <= 38); an interior point method
  reaches ~1e-10 (float64) in 10-20 steps whatever the active set, so one
  fixed iteration count serves every problem of a vmapped batch. ADMM/OSQP
  needs hundreds to thousands of iterations for 1e-6 and its speed depends on
  the penalty rho and the conditioning (WBC's f0 Hessian has a condition
  number ~1e11); an active-set method takes a data-dependent number of
  discontinuous steps, a poor fit for ``vmap``.
* Newton system: the n rows with the largest z_i/s_i (the active ones) keep
  their multiplier step as an unknown, the others are eliminated, which gives
  an (n + n) LU per step (see :func:`_newton_solver`). The usual normal
  equations (H + C' diag(z/s) C) are 30x cheaper on a CPU but lose H in the
  float32 rounding of C' diag(z/s) C near the solution: measured 1e-3 errors
  and 30-90 % convergence in float32, against 1e-5 and 100 % here.
* Once a problem has converged its iterate is frozen (``jnp.where``), so
  surplus iterations of the batch cannot degrade it; a step that would produce
  non-finite numbers is rejected likewise.
* The final iterate is strictly interior (slacks ``s > 0`` and multipliers
  ``lam > 0``), so the linearised KKT system used for the derivative is
  nonsingular even at weakly active constraints, and its solution is smooth
  ("informative" gradients, as in OptNet/qpth).
* The derivative is implicit: a ``jax.custom_jvp`` rule solves the linearised
  KKT system once, at the solution. The Newton iterations themselves run on
  ``stop_gradient`` data and are never differentiated, so the derivative cost
  is one (n+m) LU solve and does not grow with the iteration count. Because
  the rule is a JVP that is linear in the tangents, JAX transposes it for
  reverse mode: ``jax.jvp``/``jacfwd`` and ``jax.grad``/``vjp`` both work.
  Only first derivatives are exact (the rule is not itself implicit).

Libraries considered: qpax defines its derivative with ``custom_vjp`` (no
forward mode), jaxopt is unmaintained, OSQP/proxsuite/quadprog are not JAX.

Precision reached with the defaults (compared with quadprog; random problems
of sizes (6, 19), (12, 38), (6, 38) with ~5-12 active rows, and 3117 feasible
random two-feet problems), error = max|x - x*| / (1 + max|x*|), resp.
max|f - f*| / max|f*| for the feet wrenches:

* float64 (tol 1e-11): max 2e-10, median 1e-12; objective within 1e-10
  relative; 11-12 Newton steps on average, at most 19.
* float32 (tol 2e-6): max 9e-5, 99th percentile 1.2e-5, median 3e-7;
  constraint violation <= 2e-5 N on forces of ~300 N; 9 steps on average, at
  most 22.

Default: ``DEFAULT_ITERATIONS = 25`` Newton steps for either precision.
Cost: a vmapped batch of 4096 two-feet QPs takes 4.7 ms (float32) / 7.3 ms
(float64) on one H100 (jax 0.11), about 1.2 s (either dtype) on 2 idle CPU
cores.

Failure handling: if the iterate did not converge *and* the returned point
violates the constraints by more than ``fallback_tol`` (relative, after
scaling), the problem is treated as infeasible (or the solver as failed): the
result is the unconstrained minimiser ``x = -H^{-1} g`` and
``QPInfo.infeasible`` is set. With finite inputs the output is always finite.
With non-finite inputs (NaN/inf in H, g, C or b) the output ``x`` is NaN,
``converged = False`` and ``infeasible = True``: NaN is propagated on purpose so
that a broken upstream computation is not hidden behind a plausible force.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

Array = jax.Array

DEFAULT_ITERATIONS = 25
"""Default number of interior-point (Newton) steps: the contact problems
converge in 8-19 (float64, tol 1e-11) or 7-22 (float32, tol 2e-6); a converged
iterate is frozen, so surplus steps only cost time."""

_NULL_DIM = 6  # dim range(N_A): 12 foot-wrench components minus 6 momentum rows
_STEP_TO_BOUNDARY = 0.99  # fraction of the max step keeping s, lam > 0


# --------------------------------------------------------------------------------------
# Parameters and constraints
# --------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class ContactParams:
    """Static parameters of the rigid-contact constraints of one foot.

    Registered as a pytree without leaves, so it can be passed to ``jax.jit``
    functions as a normal argument (its values are part of the treedef, i.e.
    static: a change recompiles).

    Attributes:
        mu: static friction coefficient (tangential force <= mu f_z).
        n_points: points per quadrant of the linearised friction cone; the cone
            is a polygon with 4 (n_points - 1) edges.
        mu_t: torsional friction coefficient (|tau_z| <= mu_t f_z).
        fz_min: minimal normal force [N].
        foot_size: ((x_min, x_max), (y_min, y_max)) of the centre-of-pressure
            rectangle in the sole frame [m].
    """

    mu: float = 1.0 / 3.0
    n_points: int = 4
    mu_t: float = 1.0 / 75.0
    fz_min: float = 10.0
    foot_size: tuple[tuple[float, float], tuple[float, float]] = (
        (-0.07, 0.12),
        (-0.045, 0.045),
    )

    def __post_init__(self) -> None:
        for name in ("mu", "mu_t", "fz_min"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ValueError(
                    f"ContactParams.{name} must be a real number, got {value!r}"
                )
            if not math.isfinite(value) or value <= 0.0:
                raise ValueError(
                    f"ContactParams.{name} must be positive and finite, got {value!r}"
                )
            object.__setattr__(self, name, float(value))
        n = self.n_points
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 2:
            raise ValueError(
                f"ContactParams.n_points must be an integer >= 2, got {n!r}"
            )
        object.__setattr__(self, "n_points", int(n))
        try:
            (x_min, x_max), (y_min, y_max) = (
                (float(a), float(b)) for a, b in self.foot_size
            )
        except (TypeError, ValueError) as err:
            raise ValueError(
                "ContactParams.foot_size must be ((x_min, x_max), (y_min, y_max)), "
                f"got {self.foot_size!r}"
            ) from err
        if not all(math.isfinite(v) for v in (x_min, x_max, y_min, y_max)):
            raise ValueError(
                f"ContactParams.foot_size must be finite, got {self.foot_size!r}"
            )
        if not x_min < x_max:
            raise ValueError(
                f"ContactParams.foot_size needs x_min < x_max, got {self.foot_size!r}"
            )
        if not y_min < y_max:
            raise ValueError(
                f"ContactParams.foot_size needs y_min < y_max, got {self.foot_size!r}"
            )
        # A CoP rectangle that excludes the sole origin is legal (the rows stay
        # meaningful), so only the ordering is checked.
        object.__setattr__(self, "foot_size", ((x_min, x_max), (y_min, y_max)))


jax.tree_util.register_dataclass(
    ContactParams,
    data_fields=[],
    meta_fields=["mu", "n_points", "mu_t", "fz_min", "foot_size"],
)


def foot_constraints(params: ContactParams) -> tuple[np.ndarray, np.ndarray]:
    """Rigid-contact constraints ``C_foot f <= b_foot`` of a wrench in the SOLE frame.

    Same constraint set as WBC ``wbc.computeRigidContactConstraints(mu,
    numberOfPoints, mu_t, footSize, fZmin)`` and the same row order:

    * rows 0..E-1 (E = 4 (n_points - 1), 12 by default): linearised friction
      cone. Vertices ``(cos t_i, sin t_i)``, ``t_i = i d``, ``d = (pi/2) /
      (n_points - 1)``, i.e. a regular E-gon *inscribed* in the circle of
      radius ``mu f_z``. Each edge is ``n_e . (f_x, f_y) <= mu cos(d/2) f_z``
      with ``n_e`` the unit outward normal (the direction of the edge
      midpoint) and ``cos(d/2)`` the apothem. WBC writes the same half-planes
      as ``y - k x - q`` with the slope/offset of the edge line: its rows are
      ours times ``1/|n_e,y|`` (same set); unit normals are better scaled.
    * E, E+1: torsion ``tau_z - mu_t f_z <= 0``, ``-tau_z - mu_t f_z <= 0``.
    * E+2: unilateral ``-f_z <= -fz_min``.
    * E+3..E+6: CoP ``x_min f_z + tau_y <= 0``, ``-x_max f_z - tau_y <= 0``,
      ``y_min f_z - tau_x <= 0``, ``-y_max f_z + tau_x <= 0``, i.e.
      ``x_min <= -tau_y/f_z <= x_max`` and ``y_min <= tau_x/f_z <= y_max``.

    Args:
        params: the contact parameters.

    Returns:
        ``(C_foot, b_foot)``: float64 numpy arrays of shapes (E+7, 6) and
        (E+7,), (19, 6) and (19,) by default, acting on
        ``f = [f_x, f_y, f_z, tau_x, tau_y, tau_z]``.
    """
    n_edges = 4 * (params.n_points - 1)  # = 4 (n_points - 2) + 4 as in WBC
    step = 0.5 * np.pi / (params.n_points - 1)
    mid = step * (np.arange(n_edges) + 0.5)  # edge midpoints' angles
    apothem = np.cos(0.5 * step)
    cone = np.zeros((n_edges, 6))
    cone[:, 0] = np.cos(mid)
    cone[:, 1] = np.sin(mid)
    cone[:, 2] = -params.mu * apothem
    (x_min, x_max), (y_min, y_max) = params.foot_size
    #                  f_x  f_y  f_z            tau_x tau_y tau_z
    other = np.array(
        [
            [0.0, 0.0, -params.mu_t, 0.0, 0.0, 1.0],
            [0.0, 0.0, -params.mu_t, 0.0, 0.0, -1.0],
            [0.0, 0.0, -1.0, 0.0, 0.0, 0.0],
            [0.0, 0.0, x_min, 0.0, 1.0, 0.0],
            [0.0, 0.0, -x_max, 0.0, -1.0, 0.0],
            [0.0, 0.0, y_min, -1.0, 0.0, 0.0],
            [0.0, 0.0, -y_max, 1.0, 0.0, 0.0],
        ]
    )
    C_foot = np.concatenate([cone, other], axis=0)
    b_foot = np.zeros(n_edges + 7)
    b_foot[n_edges + 2] = -params.fz_min
    return C_foot, b_foot


def world_constraints(
    C_foot: np.ndarray | Array, b_foot: np.ndarray | Array, W_R_sole: Array
) -> tuple[Array, Array]:
    """Foot constraints for a wrench expressed in world axes.

    A world-axes wrench ``f`` (still applied at the sole origin) is
    ``blkdiag(W_R_sole', W_R_sole') f`` in the sole frame, hence
    ``C = C_foot blkdiag(W_R_sole', W_R_sole')``.

    Args:
        C_foot: (m, 6) sole-frame constraint matrix of :func:`foot_constraints`.
        b_foot: (m,) sole-frame bounds.
        W_R_sole: (3, 3) rotation from the sole frame to the world frame.

    Returns:
        ``(C, b)`` of shapes (m, 6) and (m,), in the dtype of ``W_R_sole``.
    """
    dtype = _float_dtype(W_R_sole)
    R = jnp.asarray(W_R_sole, dtype)
    C_foot = jnp.asarray(C_foot, dtype)
    # C_foot[:, :3] R' acts on the world force, C_foot[:, 3:] R' on the moment.
    C = jnp.concatenate([C_foot[:, :3] @ R.T, C_foot[:, 3:] @ R.T], axis=1)
    return C, jnp.asarray(b_foot, dtype)


# --------------------------------------------------------------------------------------
# Generic dense QP
# --------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class QPInfo:
    """Solver diagnostics (a pytree of arrays; under ``vmap`` each has a batch axis).

    Attributes:
        converged: () bool, the interior-point iterate met ``tol``.
        infeasible: () bool, the solver fell back to ``x = -H^{-1} g`` (QP
            infeasible, solver failure, or non-finite input).
        max_violation: () ``max(C x - b, 0)`` of the returned x, units of b.
        kkt_residual: () dimensionless KKT residual of the final iterate,
            ``max(primal, dual, complementarity)`` residuals of the scaled
            problem, each relative to the size of its terms (compare with tol).
        iterations: () int32, Newton steps taken before the iterate froze.
    """

    converged: Array
    infeasible: Array
    max_violation: Array
    kkt_residual: Array
    iterations: Array


jax.tree_util.register_dataclass(
    QPInfo,
    data_fields=[
        "converged",
        "infeasible",
        "max_violation",
        "kkt_residual",
        "iterations",
    ],
    meta_fields=[],
)


def default_tolerances(dtype: Any) -> tuple[float, float]:
    """Default ``(tol, fallback_tol)`` of :func:`solve_qp` for a float dtype.

    ``tol`` bounds the relative KKT residual at which the iterate freezes; in
    float32 it sits just above what rounding in the residuals lets us reach.
    ``fallback_tol`` is the relative constraint violation above which a
    non-converged result is declared infeasible.
    """
    if jnp.finfo(dtype).bits >= 64:
        return 1e-11, 1e-6
    return 2e-6, 1e-3


def solve_qp(
    H: Array,
    g: Array,
    C: Array,
    b: Array,
    *,
    iterations: int = DEFAULT_ITERATIONS,
    tol: float | None = None,
    fallback_tol: float | None = None,
) -> tuple[Array, QPInfo]:
    """Solve a small dense convex QP with inequality constraints.

    The QP (H symmetric positive definite; callers add a small ridge)::

        minimise_x   1/2 x' H x + g' x
        subject to   C x <= b

    Interior point with ``iterations`` fixed Newton steps (see the module
    docstring); differentiable w.r.t. all of H, g, C and b in forward and
    reverse mode (implicit derivative of the KKT conditions at the returned
    point; only the symmetric part of H matters). Use ``jax.vmap`` for batches.

    Args:
        H: (n, n) Hessian, symmetric positive (semi)definite.
        g: (n,) linear term.
        C: (m, n) constraint matrix, m >= 1.
        b: (m,) constraint bounds.
        iterations: number of Newton steps (static).
        tol: relative KKT tolerance (static); default from
            :func:`default_tolerances`.
        fallback_tol: relative violation above which a non-converged result
            falls back to ``-H^{-1} g`` (static); default likewise.

    Returns:
        ``(x, info)``: x (n,) in the promoted float dtype of the inputs, and a
        :class:`QPInfo`.
    """
    dtype = _float_dtype(H, g, C, b)
    H, g, C, b = (jnp.asarray(a, dtype) for a in (H, g, C, b))
    n = g.shape[0]
    if H.shape != (n, n) or C.ndim != 2 or C.shape[1] != n or b.shape != (C.shape[0],):
        raise ValueError(
            f"solve_qp: inconsistent shapes H{H.shape} g{g.shape} C{C.shape} b{b.shape}"
            " (expected H (n, n), g (n,), C (m, n), b (m,))"
        )
    if C.shape[0] == 0:
        raise ValueError("solve_qp: needs at least one constraint row (m >= 1)")
    if int(iterations) < 1:
        raise ValueError(f"solve_qp: iterations must be >= 1, got {iterations}")
    d_tol, d_fallback = default_tolerances(dtype)
    tol = d_tol if tol is None else float(tol)
    fallback_tol = d_fallback if fallback_tol is None else float(fallback_tol)

    # Only the symmetric part of H enters the objective; symmetrising also makes
    # the derivative w.r.t. H that of the symmetric problem.
    H = 0.5 * (H + H.T)
    Hp, gp, Cp, bp = (lax.stop_gradient(a) for a in (H, g, C, b))
    ipm = _interior_point(Hp, gp, Cp, bp, int(iterations), tol)

    finite_input = jnp.all(
        jnp.array([jnp.all(jnp.isfinite(a)) for a in (Hp, gp, Cp, bp)])
    )
    fallback = (~ipm.converged & (ipm.violation > fallback_tol)) | ~ipm.finite
    fallback = fallback | ~finite_input
    ridge = _fallback_ridge(Hp)
    x_unc = _unconstrained_minimiser(Hp, gp, ridge)

    x_p = jnp.where(fallback, x_unc, ipm.x)
    x_p = jnp.where(finite_input, x_p, jnp.nan)
    # At the fallback point no constraint is treated as active: lam = 0, s = 1
    # turns the derivative rule into that of -H^{-1} g.
    lam_p = jnp.where(fallback, 0.0, ipm.lam)
    s_p = jnp.where(fallback, 1.0, ipm.s)
    x = _implicit_solution(H, g, C, b, x_p, lam_p, s_p, ridge)

    info = QPInfo(
        converged=ipm.converged & ~fallback,
        infeasible=fallback,
        max_violation=jnp.max(jnp.maximum(Cp @ x_p - bp, 0.0)),
        kkt_residual=ipm.kkt_residual,
        iterations=ipm.iterations,
    )
    return x, info


@dataclasses.dataclass(frozen=True)
class _IPMResult:
    """Raw interior-point result in the units of the original problem."""

    x: Array  # (n,)
    lam: Array  # (m,) multipliers, > 0
    s: Array  # (m,) slacks b - C x, > 0
    converged: Array  # () bool
    finite: Array  # () bool, iterate is finite
    violation: Array  # () max(C x - b, 0) of the scaled problem (relative)
    kkt_residual: Array  # ()
    iterations: Array  # () int32


def _float_dtype(*arrays: Any) -> Any:
    """Promoted dtype of the inputs, or the default float dtype for ints."""
    dtype = jnp.result_type(*arrays)
    if not jnp.issubdtype(dtype, jnp.floating):
        dtype = jnp.result_type(float)
    return dtype


def _fallback_ridge(H: Array) -> Array:
    """Tiny ridge n eps max|diag H| that keeps a PSD H numerically invertible."""
    eps = jnp.finfo(H.dtype).eps
    return H.shape[0] * eps * jnp.max(jnp.abs(jnp.diagonal(H)))


def _unconstrained_minimiser(H: Array, g: Array, ridge: Array) -> Array:
    """``x = -(H + ridge I)^{-1} g``; zeros if H is not even PSD (keeps x finite).

    Args:
        H: (n, n) symmetric Hessian.
        g: (n,) linear term.
        ridge: () nonnegative diagonal shift.

    Returns:
        (n,) unconstrained minimiser.
    """
    K = H + ridge * jnp.eye(H.shape[0], dtype=H.dtype)
    L = jnp.linalg.cholesky(K)
    x = -jax.scipy.linalg.cho_solve((L, True), g)
    return jnp.where(jnp.all(jnp.isfinite(x)), x, jnp.zeros_like(x))


def _max_step(v: Array, dv: Array) -> Array:
    """Largest alpha in (0, 1] with ``v + alpha dv >= 0`` (v > 0 elementwise)."""
    ratios = jnp.where(dv < 0, -v / jnp.where(dv < 0, dv, -1.0), jnp.inf)
    return jnp.minimum(1.0, jnp.min(ratios))


def _newton_solver(
    H: Array, C: Array, s: Array, z: Array, r_d: Array, r_p: Array, n_keep: int
) -> Callable[[Array], tuple[Array, Array, Array]]:
    """Factorise the interior-point Newton system; return its solve function.

    The primal-dual Newton system (W = Z/S, r_c the complementarity target)::

        H dx + C' dz = -r_d
        Z ds + S dz = -r_c,    ds = -r_p - C dx

    Eliminating every dz gives the normal equations (H + C'WC) dx = ..., but
    z_i/s_i -> inf on active rows, and in float32 H is lost in the rounding
    of C'WC (measured: 1e-3 errors, 30-90% convergence). Keeping every dz
    (an (n+m) augmented system, rows scaled by 1/(z_i+s_i)) is accurate but
    costs an (n+m)^3 LU per step (4x slower on a GPU for n=6, m=38).
    Compromise: keep the ``n_keep`` rows with the largest z_i/s_i (the active
    ones) unreduced and eliminate the others, whose W_i (below those of the
    kept rows) stay moderate as long as at most ``n_keep`` rows are active::

        [H + C_E' W_E C_E   C_K'       ] [dx  ]   [-r_d - C_E' S^-1 (Z r_p - r_c)_E]
        [z_K C_K/(z+s)_K    -s_K/(z+s)_K] [dz_K] = [(r_c - Z r_p)_K / (z+s)_K      ]

    an (n + n_keep) LU whose entries stay O(1) near the solution.

    Args:
        H: (n, n) Hessian (regularised).
        C: (m, n) constraint rows.
        s: (m,) slacks, > 0.
        z: (m,) multipliers, > 0.
        r_d: (n,) dual residual.
        r_p: (m,) primal residual.
        n_keep: number of rows kept unreduced (static, <= m).

    Returns:
        ``newton(r_c) -> (dx, ds, dz)``.
    """
    n = H.shape[0]
    ratio = z / s
    _, keep = lax.top_k(ratio, n_keep)  # (n_keep,) row indices
    in_k = jnp.zeros(ratio.shape, bool).at[keep].set(True)
    w_e = jnp.where(in_k, 0.0, ratio)  # eliminated rows' weights
    C_k = C[keep]
    denom_k = z[keep] + s[keep]
    K = jnp.concatenate(
        [
            jnp.concatenate([H + (C.T * w_e) @ C, C_k.T], axis=1),
            jnp.concatenate(
                [(z[keep] / denom_k)[:, None] * C_k, -jnp.diag(s[keep] / denom_k)],
                axis=1,
            ),
        ],
        axis=0,
    )
    lu = jax.scipy.linalg.lu_factor(K)

    def newton(r_c):
        t = (z * r_p - r_c) / s  # eliminated rows: dz_i = t_i + w_i C_i dx
        rhs = jnp.concatenate(
            [-r_d - C.T @ jnp.where(in_k, 0.0, t), -(t * s)[keep] / denom_k]
        )
        d = jax.scipy.linalg.lu_solve(lu, rhs)
        dx = d[:n]
        ds = -r_p - C @ dx
        dz = jnp.where(in_k, 0.0, t + ratio * (C @ dx)).at[keep].set(d[n:])
        return dx, ds, dz

    return newton


def _interior_point(
    H: Array, g: Array, C: Array, b: Array, iterations: int, tol: float
) -> _IPMResult:
    """Mehrotra predictor-corrector interior point for ``min 1/2 x'Hx + g'x, Cx <= b``.

    Works on a scaled copy of the problem (unit constraint rows, unit max|H|,
    O(1) data), in the slack form::

        minimise 1/2 x'Hx + g'x   s.t.  C x + s = b,  s >= 0,   multipliers z >= 0
        KKT:  r_d = H x + g + C'z = 0,  r_p = C x + s - b = 0,  s_i z_i = 0

    Each step solves the Newton system of these conditions twice (predictor,
    corrector) with one factorisation, see :func:`_newton_solver`.

    Not differentiated (callers pass ``stop_gradient`` data).

    Args:
        H: (n, n) symmetric Hessian.
        g: (n,) linear term.
        C: (m, n) constraint matrix.
        b: (m,) bounds.
        iterations: number of Newton steps.
        tol: relative KKT tolerance at which the iterate freezes.

    Returns:
        The raw result, unscaled back to the original units.
    """
    n, m = g.shape[0], b.shape[0]
    dtype = H.dtype
    eye = jnp.eye(n, dtype=dtype)
    eps = jnp.finfo(dtype).eps

    # Scaling: rows of C to unit norm, max|H| = 1, then data (g, b) to O(1).
    # Keeps the Newton matrices and the tolerances independent of units (N vs
    # N m, torques of 1e2 vs Hessians of 1e4).
    row = jnp.linalg.norm(C, axis=1)
    row = jnp.where(row > 0, row, 1.0)
    Cs = C / row[:, None]
    h = jnp.max(jnp.abs(H))
    h = jnp.where(h > 0, h, 1.0)
    Hs = H / h
    bs = b / row
    gs = g / h
    data = jnp.maximum(jnp.max(jnp.abs(bs)), jnp.max(jnp.abs(gs)))
    data = jnp.where(data > 0, data, 1.0)
    bs = bs / data
    gs = gs / data
    # Newton-matrix ridge: an inexact-Newton safeguard for a singular H (the
    # residuals are exact, so it does not bias the fixed point).
    reg = 10.0 * eps
    # Rows kept unreduced in the Newton system: at a nondegenerate solution at
    # most n rows are active, so n suffice.
    n_keep = min(n, m)

    # Starting point (CVXOPT's heuristic): least squares x of the KKT system
    # with S = Z = I, then s and z shifted into s, z >= 1.
    #   min 1/2 x'Hx + g'x + 1/2 |b - Cx|^2  ->  (H + C'C) x = -g + C'b
    K0 = Hs + Cs.T @ Cs + reg * eye
    x0 = jax.scipy.linalg.cho_solve((jnp.linalg.cholesky(K0), True), -gs + Cs.T @ bs)
    s0 = bs - Cs @ x0
    z0 = -s0
    s0 = s0 + jnp.maximum(0.0, 1.0 - jnp.min(s0))
    z0 = z0 + jnp.maximum(0.0, 1.0 - jnp.min(z0))

    def residuals(x, s, z):
        Hx = Hs @ x
        Cz = Cs.T @ z
        Cx = Cs @ x
        r_d = Hx + gs + Cz
        r_p = Cx + s - bs
        res_d = jnp.max(jnp.abs(r_d)) / (
            1.0 + jnp.maximum(jnp.max(jnp.abs(Hx)), jnp.max(jnp.abs(Cz)))
        )
        res_p = jnp.max(jnp.abs(r_p)) / (1.0 + jnp.max(jnp.abs(Cx)))
        # Complementarity pair by pair: an active row's slack is an error in x
        # (unit rows), an inactive row's multiplier pushes x by ~z_i/|H|. The
        # duality gap s'z relative to the objective is too weak a test: it
        # lets inactive rows keep multipliers of 1e-3 max(z) (x off by 1e-3).
        res_c = jnp.max(
            jnp.minimum(
                s / (1.0 + jnp.max(jnp.abs(x))), z / (1.0 + jnp.max(jnp.abs(z)))
            )
        )
        return r_d, r_p, jnp.maximum(jnp.maximum(res_d, res_p), res_c)

    def step(carry, _):
        x, s, z, done, count = carry
        r_d, r_p, res = residuals(x, s, z)
        done = done | (res <= tol)
        mu = (s @ z) / m
        newton = _newton_solver(Hs + reg * eye, Cs, s, z, r_d, r_p, n_keep)

        # Predictor (affine scaling) step: target s_i z_i = 0.
        dx_a, ds_a, dz_a = newton(s * z)
        a_aff = jnp.minimum(_max_step(s, ds_a), _max_step(z, dz_a))
        mu_aff = ((s + a_aff * ds_a) @ (z + a_aff * dz_a)) / m
        sigma = jnp.clip(mu_aff / mu, 0.0, 1.0) ** 3
        # Corrector: centring sigma mu plus the second-order term ds_a dz_a.
        dx, ds, dz = newton(s * z + ds_a * dz_a - sigma * mu)
        alpha = _STEP_TO_BOUNDARY * jnp.minimum(_max_step(s, ds), _max_step(z, dz))
        x_n, s_n, z_n = x + alpha * dx, s + alpha * ds, z + alpha * dz
        ok = (
            jnp.all(jnp.isfinite(x_n))
            & jnp.all(s_n > 0)
            & jnp.all(z_n > 0)
            & jnp.all(jnp.isfinite(s_n * z_n))
        )
        take = ~done & ok
        x = jnp.where(take, x_n, x)
        s = jnp.where(take, s_n, s)
        z = jnp.where(take, z_n, z)
        return (x, s, z, done, count + take.astype(jnp.int32)), None

    init = (x0, s0, z0, jnp.array(False), jnp.array(0, jnp.int32))
    (x, s, z, _, count), _ = lax.scan(step, init, None, length=iterations)
    _, _, res = residuals(x, s, z)
    finite = (
        jnp.all(jnp.isfinite(x)) & jnp.all(jnp.isfinite(z)) & jnp.all(jnp.isfinite(s))
    )
    violation = jnp.max(jnp.maximum(Cs @ x - bs, 0.0)) / (1.0 + jnp.max(jnp.abs(x)))
    return _IPMResult(
        x=data * x,
        # Undo the scalings: C'lam = h data C_s'z  and  b - C x = row data s.
        lam=(h * data) * z / row,
        s=(row * data) * s,
        converged=finite & (res <= tol),
        finite=finite,
        violation=jnp.where(finite, violation, jnp.inf),
        kkt_residual=res,
        iterations=count,
    )


@jax.custom_jvp
def _implicit_solution(
    H: Array, g: Array, C: Array, b: Array, x: Array, lam: Array, s: Array, ridge: Array
) -> Array:
    """Returns ``x``; its JVP is the implicit derivative of the QP's KKT point.

    ``x, lam, s`` are the (stop-gradient) primal solution, multipliers and
    slacks; ``ridge`` a tiny diagonal shift for PSD H. Their tangents are
    ignored.
    """
    del H, g, C, b, lam, s, ridge
    return x


@_implicit_solution.defjvp
def _implicit_solution_jvp(primals, tangents):
    """Linearised KKT conditions at the interior-point solution.

    With s = b - C x and s_i lam_i held at its (tiny) final value::

        H dx + C' dlam = -(dH x + dg + dC' lam)
        lam_i C_i dx - s_i dlam_i = lam_i (db_i - dC_i x)

    Row i of the second block is divided by lam_i + s_i, which makes it
    ~``C_i dx = db_i - dC_i x`` for an active constraint and ~``dlam_i = 0``
    for an inactive one: the (n+m) system is well conditioned under strict
    complementarity and smooth otherwise. Solved with LU (``jnp.linalg.solve``
    is transposable in its right-hand side, so reverse mode works).
    """
    H, g, C, b, x, lam, s, ridge = primals
    dH, dg, dC, db = tangents[:4]
    n = g.shape[0]
    weight = lam + s
    a = lam / weight
    c = s / weight
    top = jnp.concatenate([H + ridge * jnp.eye(n, dtype=H.dtype), C.T], axis=1)
    bottom = jnp.concatenate([a[:, None] * C, -jnp.diag(c)], axis=1)
    M = jnp.concatenate([top, bottom], axis=0)
    rhs = jnp.concatenate([-(dH @ x + dg + dC.T @ lam), a * (db - dC @ x)])
    # Row then column equilibration (Hessian and constraint scales differ).
    r_scale = 1.0 / jnp.maximum(jnp.max(jnp.abs(M), axis=1), jnp.finfo(H.dtype).tiny)
    M = M * r_scale[:, None]
    c_scale = 1.0 / jnp.maximum(jnp.max(jnp.abs(M), axis=0), jnp.finfo(H.dtype).tiny)
    sol = c_scale * jnp.linalg.solve(M * c_scale[None, :], rhs * r_scale)
    return x, sol[:n]


# --------------------------------------------------------------------------------------
# The two contact-force QPs of the WBC controller
# --------------------------------------------------------------------------------------


def _block_diag2(A: Array, B: Array) -> Array:
    """``blkdiag(A, B)`` for two 2-D arrays."""
    top = jnp.concatenate([A, jnp.zeros((A.shape[0], B.shape[1]), A.dtype)], axis=1)
    bottom = jnp.concatenate([jnp.zeros((B.shape[0], A.shape[1]), B.dtype), B], axis=1)
    return jnp.concatenate([top, bottom], axis=0)


def range_basis(N_A: Array, dim: int = _NULL_DIM) -> Array:
    """(12, dim) basis Z of range(N_A), differentiable through N_A.

    ``Q`` = the top-``dim`` left singular vectors of ``stop_gradient(N_A)`` (an
    orthonormal basis of the range), then ``Z = N_A Q``. For a projector
    ``N_A Q = Q``, so Z is orthonormal at the evaluation point, while its
    derivative ``dN_A Q`` carries the rotation of the range. Differentiating an
    SVD/eigh basis directly would divide by the gaps between the repeated
    eigenvalues 1 of the projector (NaN); ``Z`` itself is never differentiated
    as a basis because the QP's solution ``Z y`` does not depend on the choice
    of basis of the same range.

    Args:
        N_A: (k, k) projector (symmetric or oblique) of rank ``dim``.
        dim: rank of N_A.

    Returns:
        (k, dim) array Z with ``range(Z) = range(N_A)``.
    """
    U, _, _ = jnp.linalg.svd(lax.stop_gradient(N_A), full_matrices=False)
    return N_A @ U[:, :dim]


def two_feet_wrenches(
    Sigma: Array,
    tau_model: Array,
    f1: Array,
    N_A: Array,
    W_R_left: Array,
    W_R_right: Array,
    params: ContactParams,
    *,
    iterations: int = DEFAULT_ITERATIONS,
    hessian_reg: float = 1e-7,
    tol: float | None = None,
) -> tuple[Array, QPInfo]:
    """Feet wrenches of the two-feet balancing QP (controller-spec §1.7).

    WBC writes the QP in f0 in R^12::

        minimise_f0  1/2 |tau_model + Sigma (f1 + N_A f0)|^2 (+ eps/2 |f0|^2)
        subject to   C_2 (f1 + N_A f0) <= b_2
        H = (Sigma N_A)'(Sigma N_A) + eps I,   g = (Sigma N_A)'(tau_model + Sigma f1)

    whose Hessian is singular but for eps (N_A has rank 6). Here f0 = Z y with
    Z a 12 x 6 basis of range(N_A) (:func:`range_basis`), which gives the same
    f = f1 + N_A f0 with a well-conditioned 6 x 6 QP::

        minimise_y   1/2 y' (Sigma Z)'(Sigma Z) y + (eps/2) |y|^2
                       + y' (Sigma Z)'(tau_model + Sigma f1)
        subject to   (C_2 Z) y <= b_2 - C_2 f1
        C_2 = blkdiag(C_left, C_right) (world-axes foot constraints), (38, 12)

    Args:
        Sigma: (n, 12) map from the feet wrenches to the joint torques.
        tau_model: (n,) joint torques without the contact wrenches.
        f1: (12,) particular wrench solution (realises the momentum rate).
        N_A: (12, 12) rank-6 projector onto the null space of the momentum map.
        W_R_left: (3, 3) world rotation of the left sole.
        W_R_right: (3, 3) world rotation of the right sole.
        params: contact parameters (the same for both feet).
        iterations: interior-point Newton steps.
        hessian_reg: eps above, absolute (WBC's value).
        tol: relative KKT tolerance, see :func:`solve_qp`.

    Returns:
        ``(f, info)``: f (12,) = ``[f_L (force, moment); f_R]`` in world axes at
        the sole origins, ``f = f1 + N_A f0``; on infeasibility f is the
        unconstrained minimiser over ``f1 + range(N_A)`` and ``info.infeasible``
        is set.
    """
    dtype = _float_dtype(Sigma, tau_model, f1, N_A, W_R_left, W_R_right)
    Sigma, tau_model, f1, N_A, W_R_left, W_R_right = (
        jnp.asarray(a, dtype) for a in (Sigma, tau_model, f1, N_A, W_R_left, W_R_right)
    )
    C_foot, b_foot = foot_constraints(params)
    C_L, b_L = world_constraints(C_foot, b_foot, W_R_left)
    C_R, b_R = world_constraints(C_foot, b_foot, W_R_right)
    C2 = _block_diag2(C_L, C_R)
    b2 = jnp.concatenate([b_L, b_R])

    Z = range_basis(N_A)
    SZ = Sigma @ Z
    H = SZ.T @ SZ + hessian_reg * jnp.eye(_NULL_DIM, dtype=dtype)
    g = SZ.T @ (tau_model + Sigma @ f1)
    y, info = solve_qp(H, g, C2 @ Z, b2 - C2 @ f1, iterations=iterations, tol=tol)
    return f1 + Z @ y, info


def one_foot_wrench(
    A_k: Array,
    wrench_des: Array,
    W_R_sole: Array,
    params: ContactParams,
    *,
    iterations: int = DEFAULT_ITERATIONS,
    hessian_reg: float = 1e-7,
    tol: float | None = None,
) -> tuple[Array, QPInfo]:
    """Wrench of the single foot in contact (controller-spec §1.7)::

        minimise_f   1/2 |A_k f - wrench_des|^2 + (eps/2) |f|^2
        subject to   C_k f <= b_k   (world-axes constraints of that foot)
        H = A_k'A_k + eps I,   g = -A_k' wrench_des

    Args:
        A_k: (6, 6) map from the foot wrench to the centroidal wrench.
        wrench_des: (6,) desired centroidal wrench.
        W_R_sole: (3, 3) world rotation of the sole in contact.
        params: contact parameters.
        iterations: interior-point Newton steps.
        hessian_reg: eps above, absolute (WBC's value).
        tol: relative KKT tolerance, see :func:`solve_qp`.

    Returns:
        ``(f_k, info)``: f_k (6,) world-axes wrench at the sole origin.
    """
    dtype = _float_dtype(A_k, wrench_des, W_R_sole)
    A_k, wrench_des, W_R_sole = (
        jnp.asarray(a, dtype) for a in (A_k, wrench_des, W_R_sole)
    )
    C, b = world_constraints(*foot_constraints(params), W_R_sole)
    H = A_k.T @ A_k + hessian_reg * jnp.eye(6, dtype=dtype)
    g = -A_k.T @ wrench_des
    return solve_qp(H, g, C, b, iterations=iterations, tol=tol)
