"""The interior-point iterations behind :func:`wbc_jax.control.qp.solve_qp`.

A primal-dual interior-point method (Mehrotra predictor-corrector) on the scaled problem
``min 1/2 x'Hx + g'x  s.t.  Cx <= b``, in a ``lax.while_loop`` that stops once every problem of a
vmapped batch has converged, after ``unrolled`` steps written out before it (a converged problem's
later steps are not taken, so the result is the loop's: on a GPU each pass of a while loop waits for
its predicate on the host, where written-out steps run without that pause). Never differentiated: :mod:`wbc_jax.control.qp` differentiates the
solution implicitly. The module docstring of :mod:`wbc_jax.control.qp` gives the design and the
precision reached.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

Array = jax.Array

STEP_TO_BOUNDARY = 0.99  # fraction of the max step keeping s, lam > 0
# A warm start's slacks and multipliers are raised to at least this (scaled problem, O(1) data):
# the last solution's are ~tol on its active/inactive rows, a corner from which the steps to the
# boundary of a nearby problem would be tiny. Measured on the sinusoid's 1000 two-feet QPs
# (float32): 0.1 takes 4.0 Newton steps (6.0 cold) with the solution within 2.6e-5 of float64's
# (cold: 1.1e-3); 0.03 takes 3.4 but lands 3e-4 off; 0.3 takes 4.8.
WARM_START_FLOOR = 0.1


@dataclasses.dataclass(frozen=True)
class IPMResult:
    """Raw interior-point result in the units of the original problem."""

    x: Array  # (n,)
    lam: Array  # (m,) multipliers, > 0
    s: Array  # (m,) slacks b - C x, > 0
    converged: Array  # () bool
    finite: Array  # () bool, iterate is finite
    violation: Array  # () max(C x - b, 0) of the scaled problem (relative)
    kkt_residual: Array  # ()
    iterations: Array  # () int32
    # (3,) the final iterate's dual, primal and complementarity residuals (kkt_residual is their max);
    # recomputed after the loop, so a caller that does not read them pays nothing (dead code).
    residual_parts: Array


def result_of_outputs(x: Array, lam: Array, s: Array, flags: Array, stats: Array) -> IPMResult:
    """:class:`IPMResult` from the outputs of a solver engine called outside JAX's ops (the Warp kernels,
    :mod:`wbc_jax.control.qp_warp`; eiquadprog, :mod:`wbc_jax.control.qp_eiquadprog`), any leading batch shape:
    x (..., n), lam (..., m), s (..., m), flags (..., 3) int32 (converged, finite, iterations) and stats (..., 5)
    (violation, KKT residual, its dual, primal and complementarity parts)."""
    return IPMResult(
        x=x,
        lam=lam,
        s=s,
        converged=flags[..., 0] == 1,
        finite=flags[..., 1] == 1,
        violation=stats[..., 0],
        kkt_residual=stats[..., 1],
        iterations=flags[..., 2],
        residual_parts=stats[..., 2:],
    )


def _max_step(v: Array, dv: Array) -> Array:
    """Largest alpha in (0, 1] with ``v + alpha dv >= 0`` (v > 0 elementwise); NaN where some
    entry of dv is not finite (``0 dv`` is NaN there), so one reduction also tests the direction."""
    ratios = jnp.where(dv < 0, -v / jnp.where(dv < 0, dv, -1.0), jnp.inf)
    return jnp.minimum(1.0, jnp.min(ratios + 0.0 * dv))


def _newton_solver(
    H: Array, C: Array, C_pad: Array, s: Array, z: Array, r_d: Array, r_p: Array, n_keep: int
) -> Callable[[Array], tuple[Array, Array]]:
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

    an (n + n_keep) LU whose entries stay O(1) near the solution. Measured against
    pivot-free forms of the same system on one CPU core (BENCHMARKS.md, qpn46): the
    symmetric quasi-definite one (rows scaled by 1/D; a Cholesky factor of the (1,1)
    block, then of the Schur complement) needs more library calls than this one LU and
    cost 10 % more a QP; an unrolled Gauss-Jordan inverse, more kernels and no float32
    convergence. The LU's solve is written out so that its row permutation is gathered
    by the kernel that builds the right-hand side.

    Args:
        H: (n, n) Hessian (regularised).
        C: (m, n) constraint rows.
        C_pad: (m, n + n_keep) C with zero columns appended: ``C_pad @ d = C @ dx`` for the
            system's solution d = (dx, dz_K), without slicing dx out first.
        s: (m,) slacks, > 0.
        z: (m,) multipliers, > 0.
        r_d: (n,) dual residual.
        r_p: (m,) primal residual.
        n_keep: number of rows kept unreduced (static, <= m).

    Returns:
        ``newton(r_c) -> (dx, [ds, dz])`` (the slack and multiplier steps concatenated,
        as the iterate carries them).
    """
    n, m = H.shape[0], C.shape[0]
    ratio = z / s
    _, keep = lax.top_k(ratio, n_keep)  # (n_keep,) row indices
    # Each row's place among the kept ones (n_keep where eliminated), by one reduction rather
    # than a scatter: it gives the mask and, as a gather, the kept rows' dz.
    slot = jnp.sum(jnp.where(keep[None, :] == np.arange(m)[:, None], np.arange(n_keep) - n_keep, 0), axis=1) + n_keep
    in_k = slot < n_keep
    C_eT = jnp.where(in_k, 0.0, C.T)  # eliminated rows' C'
    C_k = C[keep]
    # Every row's z/(z+s) and s/(z+s) in one kernel, the kept ones gathered where they are used.
    denom = z + s
    K = jnp.concatenate(
        [
            jnp.concatenate([H + (C_eT * ratio) @ C, C_k.T], axis=1),
            jnp.concatenate([(z / denom)[keep][:, None] * C_k, -jnp.diag((s / denom)[keep])], axis=1),
        ],
        axis=0,
    )
    lu, _, perm = lax.linalg.lu(K)
    dz_k_of_row = n + jnp.minimum(slot, n_keep - 1)  # index into d of a kept row's dz

    def newton(r_c):
        t = (z * r_p - r_c) / s  # eliminated rows: dz_i = t_i + w_i C_i dx
        rhs = jnp.concatenate([-r_d - C_eT @ t, -(t * s / denom)[keep]])[perm, None]  # P rhs
        d = lax.linalg.triangular_solve(lu, rhs, left_side=True, lower=True, unit_diagonal=True)
        d = lax.linalg.triangular_solve(lu, d, left_side=True, lower=False)[:, 0]
        Cdx = C_pad @ d
        return d[:n], jnp.concatenate([-r_p - Cdx, jnp.where(in_k, d[dz_k_of_row], t + ratio * Cdx)])

    return newton


def interior_point(
    H: Array,
    g: Array,
    C: Array,
    b: Array,
    iterations: int,
    tol: float,
    weight: Array | None = None,
    start: Array | None = None,
    unrolled: int = 0,
) -> IPMResult:
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
        start: (2, m) multipliers and slacks (original units) of a nearby problem's solution to
            start from (each raised to :data:`WARM_START_FLOOR` in the scaled problem; x starts
            at the cold start's least-squares point, which does not depend on a basis the
            caller may have changed), or None; any non-finite entry: the cold start.
        unrolled: Newton steps written out before the while loop (static, at most ``iterations``;
            the loop is left out where they are all of them).

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
    if start is not None:
        z_warm = jnp.maximum(start[0] * row / (h * data), WARM_START_FLOOR)
        s_warm = jnp.maximum(start[1] / (row * data), WARM_START_FLOOR)
        warm = jnp.all(jnp.isfinite(z_warm)) & jnp.all(jnp.isfinite(s_warm))
        s0 = jnp.where(warm, s_warm, s0)
        z0 = jnp.where(warm, z_warm, z0)

    # Loop invariants: the Newton matrices' Hessian, [H; C] (H x and C x in one product) and
    # C padded for the Newton system's solution (see _newton_solver).
    H_reg = Hs + reg * eye
    HC = jnp.concatenate([Hs, Cs])
    C_pad = jnp.concatenate([Cs, jnp.zeros((m, n_keep), dtype)], axis=1)

    def residuals(x, sz):
        s, z = sz[:m], sz[m:]
        HCx = HC @ x
        Hx, Cx = HCx[:n], HCx[n:]
        Cz = Cs.T @ z
        r_d = Hx + gs + Cz
        r_p = Cx + s - bs
        # The max-norms as two reductions over stacked vectors (one kernel each on a CPU, not seven).
        max_r_d, max_Hx, max_Cz, max_x = jnp.max(jnp.abs(jnp.stack([r_d, Hx, Cz, x])), axis=1)
        max_r_p, max_Cx, max_z = jnp.max(jnp.abs(jnp.stack([r_p, Cx, z])), axis=1)
        res_d = max_r_d / (1.0 + jnp.maximum(max_Hx, max_Cz))
        res_p = max_r_p / (1.0 + max_Cx)
        # Complementarity pair by pair: an active row's slack is an error in x
        # (unit rows), an inactive row's multiplier pushes x by ~z_i/|H|. The
        # duality gap s'z relative to the objective is too weak a test: it
        # lets inactive rows keep multipliers of 1e-3 max(z) (x off by 1e-3).
        res_c = jnp.max(jnp.minimum(s / (1.0 + max_x), z / (1.0 + max_z)))
        return r_d, r_p, jnp.maximum(jnp.maximum(res_d, res_p), res_c), jnp.stack([res_d, res_p, res_c])

    # The residuals of an iterate are computed once, at the end of the step that made it, and
    # carried: the loop stops right after the step that converged (no extra Newton step whose
    # result would be thrown away) and the final residual is the carried one. The slacks and
    # multipliers travel as one vector sz = [s, z] (each update one kernel on a CPU, not two).
    def step(carry):
        x, sz, mu, r_d, r_p, res, count, k = carry
        s, z = sz[:m], sz[m:]
        done = res <= tol
        newton = _newton_solver(H_reg, Cs, C_pad, s, z, r_d, r_p, n_keep)

        # Predictor (affine scaling) step: target s_i z_i = 0.
        _, dsz_a = newton(s * z)
        a_aff = _max_step(sz, dsz_a)
        sz_aff = sz + a_aff * dsz_a
        mu_aff = (sz_aff[:m] @ sz_aff[m:]) / m
        sigma = jnp.clip(mu_aff / mu, 0.0, 1.0) ** 3
        # Corrector: centring sigma mu plus the second-order term ds_a dz_a.
        dx, dsz = newton(s * z + dsz_a[:m] * dsz_a[m:] - sigma * mu)
        alpha = STEP_TO_BOUNDARY * _max_step(sz, dsz)
        x_n, sz_n = x + alpha * dx, sz + alpha * dsz
        mu_n = (sz_n[:m] @ sz_n[m:]) / m
        # The step is taken where it is finite, with no reduction of its own: alpha is NaN where
        # (dx, ds, dz) is not (_max_step; dx's entries reach every C dx), alpha < the step to the
        # boundary keeps s, z > 0, and mu_n (the next step's mu) is finite unless s z overflows.
        take = ~done & jnp.isfinite(alpha) & jnp.isfinite(mu_n)
        x = jnp.where(take, x_n, x)
        sz = jnp.where(take, sz_n, sz)
        mu = jnp.where(take, mu_n, mu)
        r_d, r_p, res, _ = residuals(x, sz)
        return x, sz, mu, r_d, r_p, res, count + take.astype(jnp.int32), k + 1

    def running(carry):
        return ~(carry[5] <= tol) & (carry[7] < iterations)

    sz0 = jnp.concatenate([s0, z0])
    init = (x0, sz0, (s0 @ z0) / m, *residuals(x0, sz0)[:3], jnp.array(0, jnp.int32), jnp.array(0, jnp.int32))
    carry = init
    for _ in range(min(unrolled, iterations)):
        carry = step(carry)
    if unrolled < iterations:
        carry = lax.while_loop(running, step, carry)
    x, sz, _, _, _, res, count, _ = carry
    s, z = sz[:m], sz[m:]
    finite = jnp.all(jnp.isfinite(x)) & jnp.all(jnp.isfinite(z)) & jnp.all(jnp.isfinite(s))
    violation = jnp.max(jnp.maximum(Cs @ x - bs, 0.0)) / (1.0 + jnp.max(jnp.abs(x)))
    return IPMResult(
        x=data * x,
        # Undo the scalings: C'lam = h data C_s'z  and  b - C x = row data s.
        lam=(h * data) * z / row,
        s=(row * data) * s,
        converged=finite & (res <= tol),
        finite=finite,
        violation=jnp.where(finite, violation, jnp.inf),
        kkt_residual=res,
        iterations=count,
        residual_parts=residuals(x, sz)[3],
    )
