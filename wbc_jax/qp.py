"""[contact forces] A small dense QP solver in JAX: ``min 1/2 x'Hx + g'x  s.t.  Cx <= b``.

Each control tick of the iCub balancing controller (robotology whole-body-controllers,
the seed paper) solves tiny dense QPs for the contact wrenches (:mod:`wbc_jax.forces`
builds them). :func:`solve_qp` runs under ``jit``/``vmap``/``lax.scan`` and is differentiable
in reverse *and* forward mode.

Algorithm of :func:`solve_qp` and why
-------------------------------------
A primal-dual interior-point method (Mehrotra predictor-corrector) run for at
most ``iterations`` Newton steps in a ``lax.while_loop`` that stops once the
iterate has converged (under ``vmap``: once every problem of the batch has):

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
  surplus iterations of a batch cannot degrade it; a step that would produce
  non-finite numbers is rejected likewise. The loop is never differentiated
  (below), so a ``while_loop`` serves reverse mode as well as a ``scan``.
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

Default: at most ``DEFAULT_ITERATIONS = 25`` Newton steps for either precision
(BENCHMARKS.md has the cost).

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
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
from jax import lax

Array = jax.Array


DEFAULT_ITERATIONS = 25
"""Default (maximum) number of interior-point (Newton) steps: the contact problems
converge in 8-19 (float64, tol 1e-11) or 7-22 (float32, tol 2e-6); the loop stops once
the iterate has converged."""

_STEP_TO_BOUNDARY = 0.99  # fraction of the max step keeping s, lam > 0

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
    row_weight: Any = None,
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
        row_weight: (m,) positive weights of the rows in the scaled problem, or None
            (all 1). Row i is scaled to norm ``row_weight[i]`` instead of 1, so its
            residual and violation count ``row_weight[i]`` times more in the
            tolerances: rows whose natural scale is smaller than the problem's (a
            hand's 1 N next to feet of 300 N) are met as tightly, relative to it.

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
    weight = None if row_weight is None else lax.stop_gradient(jnp.asarray(row_weight, dtype))
    if weight is not None and weight.shape != b.shape:
        raise ValueError(f"solve_qp: row_weight must have shape {b.shape}, got {weight.shape}")
    ipm = _interior_point(Hp, gp, Cp, bp, int(iterations), tol, weight)

    finite_input = jnp.all(jnp.array([jnp.all(jnp.isfinite(a)) for a in (Hp, gp, Cp, bp)]))
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
        rhs = jnp.concatenate([-r_d - C.T @ jnp.where(in_k, 0.0, t), -(t * s)[keep] / denom_k])
        d = jax.scipy.linalg.lu_solve(lu, rhs)
        dx = d[:n]
        ds = -r_p - C @ dx
        dz = jnp.where(in_k, 0.0, t + ratio * (C @ dx)).at[keep].set(d[n:])
        return dx, ds, dz

    return newton


def _interior_point(
    H: Array, g: Array, C: Array, b: Array, iterations: int, tol: float, weight: Array | None = None
) -> _IPMResult:
    """Mehrotra predictor-corrector interior point for ``min 1/2 x'Hx + g'x, Cx <= b``.

    Works on a scaled copy of the problem (constraint rows of norm ``weight``,
    default 1, unit max|H|, O(1) data), in the slack form::

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
        weight: (m,) row weights (:func:`solve_qp`'s ``row_weight``) or None.

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
    if weight is not None:  # row i scaled to norm weight_i
        row = row / weight
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
        res_d = jnp.max(jnp.abs(r_d)) / (1.0 + jnp.maximum(jnp.max(jnp.abs(Hx)), jnp.max(jnp.abs(Cz))))
        res_p = jnp.max(jnp.abs(r_p)) / (1.0 + jnp.max(jnp.abs(Cx)))
        # Complementarity pair by pair: an active row's slack is an error in x
        # (unit rows), an inactive row's multiplier pushes x by ~z_i/|H|. The
        # duality gap s'z relative to the objective is too weak a test: it
        # lets inactive rows keep multipliers of 1e-3 max(z) (x off by 1e-3).
        res_c = jnp.max(jnp.minimum(s / (1.0 + jnp.max(jnp.abs(x))), z / (1.0 + jnp.max(jnp.abs(z)))))
        return r_d, r_p, jnp.maximum(jnp.maximum(res_d, res_p), res_c)

    def step(carry):
        x, s, z, done, count, k = carry
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
        ok = jnp.all(jnp.isfinite(x_n)) & jnp.all(s_n > 0) & jnp.all(z_n > 0) & jnp.all(jnp.isfinite(s_n * z_n))
        take = ~done & ok
        x = jnp.where(take, x_n, x)
        s = jnp.where(take, s_n, s)
        z = jnp.where(take, z_n, z)
        return x, s, z, done, count + take.astype(jnp.int32), k + 1

    def running(carry):
        return ~carry[3] & (carry[5] < iterations)

    init = (x0, s0, z0, jnp.array(False), jnp.array(0, jnp.int32), jnp.array(0, jnp.int32))
    x, s, z, _, count, _ = lax.while_loop(running, step, init)
    _, _, res = residuals(x, s, z)
    finite = jnp.all(jnp.isfinite(x)) & jnp.all(jnp.isfinite(z)) & jnp.all(jnp.isfinite(s))
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
def _implicit_solution(H: Array, g: Array, C: Array, b: Array, x: Array, lam: Array, s: Array, ridge: Array) -> Array:
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
