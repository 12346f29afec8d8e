"""A small dense QP solver in JAX: ``min 1/2 x'Hx + g'x  s.t.  Cx <= b``.

Each control tick of the humanoid balancing controller (robotology whole-body-controllers,
the seed paper) solves tiny dense QPs for the contact wrenches (:mod:`wbc_jax.control.forces`
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
* Warm start (``start``): a control loop solves a nearby problem every tick, so it can
  pass the last tick's multipliers and slacks (``QPInfo.start``; the controller's
  ``qp_warm_start``, off by default: ControllerConfig says why), raised to a floor
  (:data:`wbc_jax.control.qp_ipm.WARM_START_FLOOR`) so that the steps to the boundary stay
  long; x starts at the cold start's point (it does not depend on the basis of null(A),
  which the caller may change from one tick to the next). Measured in closed loop
  (float32): 6.0 -> 4.0 Newton steps a tick in the 20 s sinusoid, 6.2 -> 4.4 in the
  acceptance push (at most 12 -> 8); the solution is the cold start's within the tolerance.
  A warm-started solve stops at its own, tighter float32 tolerance
  (:data:`WARM_START_TOL_FLOAT32`), which costs no step of the batch's slowest problem.
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
from typing import Any

import jax
import jax.numpy as jnp
from jax import lax

from wbc_jax.control.qp_ipm import interior_point
from wbc_jax.core.math import batch_any

Array = jax.Array


QP_ENGINES = ("jax", "warp", "warp_active_set", "eiquadprog")
"""Engines of :func:`solve_qp` (its ``engine``): the interior point in JAX or as one Warp kernel, or the dual
active-set method as one Warp kernel (:mod:`wbc_jax.control.qp_active_set_kernel`) or by eiquadprog on the CPU
(:mod:`wbc_jax.control.qp_eiquadprog`)."""

WARP_ENGINES = ("warp", "warp_active_set")
"""The engines that need warp-lang."""

ACTIVE_SET_ENGINES = ("warp_active_set", "eiquadprog")
"""The engines of the dual active-set method: the exact solution, no warm start (``start``)."""

ENGINE_CHOICES = ("auto",) + QP_ENGINES
"""What the controller's ``qp_engine`` setting takes: an engine, or ``auto`` (:func:`resolve_engine`)."""


def resolve_engine(engine: str, warm_start: bool = False, unrolled_steps: int = 0) -> str:
    """The engine that ``engine`` names here: itself, or for ``auto``, where no warm start or unrolled steps are asked
    for (the active-set method takes neither), the dual active-set method: as one Warp kernel where JAX's default
    device is a GPU and warp-lang is installed (:func:`wbc_jax.control.warp_launch.gpu_default`; the loop's fastest
    engine there), by eiquadprog where it is the CPU and the engine builds
    (:func:`wbc_jax.control.qp_eiquadprog.available`; about half the interior point's controller tick there; both
    BENCHMARKS.md, issue 46); else the interior point in JAX."""
    if engine != "auto":
        return engine
    if warm_start or unrolled_steps:
        return "jax"
    from wbc_jax.control import warp_launch

    if warp_launch.gpu_default():
        return "warp_active_set"
    if jax.default_backend() != "cpu":
        return "jax"
    from wbc_jax.control import qp_eiquadprog

    return "eiquadprog" if qp_eiquadprog.available() is None else "jax"


DEFAULT_ITERATIONS = 25
"""Default (maximum) number of interior-point (Newton) steps: the contact problems
converge in 8-19 (float64, tol 1e-11) or 7-22 (float32, tol 2e-6); the loop stops once
the iterate has converged."""


WARM_START_TOL_FLOAT32 = 5e-7
"""float32 ``tol`` of a warm-started solve. Measured on the one-foot acceptance scenario, whose
figures amplify the QP's solution error (BENCHMARKS.md, qpmax46): warm-started at 2e-6 its end CoM
speed moves 8.9 % from the cold start's, at 5e-7 0.03 %; cold, 2e-6 -> 5e-7 moves it 0.25 %. On the
benchmark loop's states after a push the batch's slowest warm-started QP takes 10 Newton steps at
either tolerance (14 cold at 2e-6)."""


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
        start: (2, m) the multipliers and slacks of the solution, the ``start`` of a next solve
            of a nearby problem (NaN where the solver fell back: that solve starts cold).
    """

    converged: Array
    infeasible: Array
    max_violation: Array
    kkt_residual: Array
    iterations: Array
    start: Array


jax.tree_util.register_dataclass(
    QPInfo,
    data_fields=[
        "converged",
        "infeasible",
        "max_violation",
        "kkt_residual",
        "iterations",
        "start",
    ],
    meta_fields=[],
)


def default_tolerances(dtype: Any, warm_start: bool = False) -> tuple[float, float]:
    """Default ``(tol, fallback_tol)`` of :func:`solve_qp` for a float dtype.

    ``tol`` bounds the relative KKT residual at which the iterate freezes; in
    float32 it sits just above what rounding in the residuals lets us reach.
    ``fallback_tol`` is the relative constraint violation above which a
    non-converged result is declared infeasible.

    ``warm_start``: the tolerance of a solve from a nearby problem's solution (``start``), in
    float32 :data:`WARM_START_TOL_FLOAT32`. A warm start and a cold one stop at different points
    of the band that ``tol`` allows, and the difference accumulates over a closed loop's ticks.
    """
    if jnp.finfo(dtype).bits >= 64:
        return 1e-11, 1e-6
    return (WARM_START_TOL_FLOAT32 if warm_start else 2e-6), 1e-3


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
    start: Array | None = None,
    unrolled: int = 0,
    engine: str = "jax",
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
            :func:`default_tolerances` (tighter with ``start`` in float32).
        fallback_tol: relative violation above which a non-converged result
            falls back to ``-H^{-1} g`` (static); default likewise.
        row_weight: (m,) positive weights of the rows in the scaled problem, or None
            (all 1). Row i is scaled to norm ``row_weight[i]`` instead of 1, so its
            residual and violation count ``row_weight[i]`` times more in the
            tolerances: rows whose natural scale is smaller than the problem's (a
            hand's 1 N next to feet of 300 N) are met as tightly, relative to it.
        start: (2, m) ``info.start`` of a previous solve of a nearby problem (the last control
            tick's) to warm-start the interior point from, or None (cold start). The solution
            is the same within ``tol``; it takes fewer Newton steps.
        unrolled: Newton steps written out before the interior point's while loop (static, 0 to
            ``iterations``): the same solution; on a GPU no pause for the loop's predicate in them.
        engine: the solver (static): ``"jax"`` (the interior point,
            :func:`wbc_jax.control.qp_ipm.interior_point`), ``"warp"`` (the same as one Warp kernel, one thread
            per problem, :func:`wbc_jax.control.qp_warp.interior_point_warp`) or ``"warp_active_set"`` (the dual
            active-set method as one Warp kernel, :func:`wbc_jax.control.qp_warp.active_set_warp`: the exact
            solution, to float64 rounding, whatever ``tol``; no ``start``) or ``"eiquadprog"`` (the same method by
            eiquadprog in C++, in CPU programs: :func:`wbc_jax.control.qp_eiquadprog.active_set_eiquadprog`). The
            Warp engines need warp-lang; every engine but ``"jax"`` takes ``unrolled`` 0. The derivative and the
            fallback stay JAX's.

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
    if isinstance(unrolled, bool) or not isinstance(unrolled, int) or not 0 <= unrolled <= int(iterations):
        raise ValueError(f"solve_qp: unrolled must be an integer from 0 to iterations ({iterations}), got {unrolled!r}")
    if engine not in QP_ENGINES:
        raise ValueError(f"solve_qp: unknown engine {engine!r}; valid: {list(QP_ENGINES)}")
    if engine != "jax" and unrolled != 0:
        solver = "the Warp kernel" if engine in WARP_ENGINES else "eiquadprog"
        raise ValueError(
            f"solve_qp: engine {engine!r} takes unrolled 0 ({solver} has no while loop to unroll), got {unrolled!r}"
        )
    if engine in ACTIVE_SET_ENGINES and start is not None:
        raise ValueError(
            f"solve_qp: engine {engine!r} takes no start (the active-set method starts from the "
            "unconstrained minimiser); warm starts: engines ['jax', 'warp']"
        )
    d_tol, d_fallback = default_tolerances(dtype, warm_start=start is not None)
    tol = d_tol if tol is None else float(tol)
    fallback_tol = d_fallback if fallback_tol is None else float(fallback_tol)

    # Only the symmetric part of H enters the objective; symmetrising also makes
    # the derivative w.r.t. H that of the symmetric problem.
    H = 0.5 * (H + H.T)
    Hp, gp, Cp, bp = (lax.stop_gradient(a) for a in (H, g, C, b))
    weight = None if row_weight is None else lax.stop_gradient(jnp.asarray(row_weight, dtype))
    if weight is not None and weight.shape != b.shape:
        raise ValueError(f"solve_qp: row_weight must have shape {b.shape}, got {weight.shape}")
    if start is not None:
        start = lax.stop_gradient(jnp.asarray(start, dtype))
        if start.shape != (2, b.shape[0]):
            raise ValueError(
                f"solve_qp: start must have shape (2, {b.shape[0]}) (multipliers, slacks), got {start.shape}"
            )
    if engine in WARP_ENGINES:
        from wbc_jax.control import qp_warp  # Warp only where asked for

        if engine == "warp":
            ipm = qp_warp.interior_point_warp(Hp, gp, Cp, bp, int(iterations), tol, weight, start)
        else:
            ipm = qp_warp.active_set_warp(Hp, gp, Cp, bp, tol, weight)
    elif engine == "eiquadprog":
        from wbc_jax.control import qp_eiquadprog  # its library is built at first use

        ipm = qp_eiquadprog.active_set_eiquadprog(Hp, gp, Cp, bp, tol, weight)
    else:
        ipm = interior_point(Hp, gp, Cp, bp, int(iterations), tol, weight, start, unrolled)

    finite_input = jnp.all(jnp.array([jnp.all(jnp.isfinite(a)) for a in (Hp, gp, Cp, bp)]))
    fallback = (~ipm.converged & (ipm.violation > fallback_tol)) | ~ipm.finite
    fallback = fallback | ~finite_input
    ridge = _fallback_ridge(Hp)
    # The unconstrained minimiser only in calls where some problem of a batch falls back.
    x_p = lax.cond(
        batch_any(fallback), lambda: jnp.where(fallback, _unconstrained_minimiser(Hp, gp, ridge), ipm.x), lambda: ipm.x
    )
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
        start=jnp.where(fallback, jnp.nan, jnp.stack([ipm.lam, ipm.s])),
    )
    return x, info


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
