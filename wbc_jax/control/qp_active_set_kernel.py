"""The force QP ``min 1/2 x'Hx + g'x s.t. Cx <= b`` by the dual active-set method of Goldfarb and Idnani (1983,
"A numerically stable dual method for solving strictly convex quadratic programs", Math. Programming 27), as one
Warp kernel, one thread per problem (:mod:`wbc_jax.control.qp_warp`, engine ``"warp_active_set"``).

Why a second algorithm beside the interior point: the contact problems are tiny (n = 6 or 12 unknowns, m = 38
rows) and at most n rows are active, so an exact active-set solve is a handful of rank-k updates (k <= n) where the
interior point builds and factorises an (n + n) Newton matrix over all m rows at every one of its 6-12 steps. In a
GPU thread the matrices live in local memory, and the work the thread does with them is what the kernel costs.
The method is the one quadprog and eiquadprog implement (the references of tests/test_forces.py and of TSID's
controller); this is its textbook form written anew: start from the unconstrained minimiser, add the most violated
row, take the primal-dual step along the direction that keeps the active rows' equalities, drop a row whose
multiplier reaches zero, until no row is violated. Each step recomputes the active rows' Schur complement
``S = N' H^-1 N`` (k x k) and its Cholesky factor instead of updating a factorisation: k <= 12, and nothing
accumulates rounding from one step to the next.

The problem is scaled as the interior point scales it (rows of C to unit norm or ``row_weight``, max|H| = 1, data to
O(1); :func:`wbc_jax.control.qp_ipm.interior_point`) and solved in float64 whatever the inputs' precision: the
multipliers come from differences of the Schur complement's entries. The outputs are the interior point's
(:class:`wbc_jax.control.qp_ipm.IPMResult`): x, the multipliers (0 off the active set), the slacks ``b - Cx``
(floored at the smallest positive float, so that :func:`wbc_jax.control.qp.solve_qp`'s implicit derivative sees every
row as either active or not), whether it converged (no row violated by more than ``tol`` in the scaled problem),
whether all is finite, the steps taken (each added or dropped row), the violation and the KKT residual.
"""

# Warp needs a variable that a dynamic loop changes declared by its type (x = int(0), flag = bool(True)): UP018 off.
# ruff: noqa: UP018

import functools
import math

import numpy as np

from wbc_jax.control.warp_launch import warp_module

STEP_LIMIT_PER_ROW = 3
"""The kernel's bound on added and dropped rows, per constraint row (3 m): each outer step adds a row and the
method never repeats an active set, so a problem that reaches it has cycled on rounding; it is then flagged not
converged (the caller's fallback decides)."""


DEPENDENT_ROW = 1e-10
"""A row to be added counts as dependent on the active rows (z = 0: only a partial step, dropping a row, or the
problem is infeasible) where its curvature along the primal direction, a'z = z'Hz, is below this fraction of a'H^-1 a:
the squared sine of its angle to their span in H^-1's metric. Above it the active rows' Schur complement keeps a
condition number below about 1e10, so its float64 solves keep 6 digits. Rows that float32 rounding alone makes
independent (a contact cone's opposite faces, 1e-7 apart, in a falling robot's problems) were added at 1e-12 by the
earlier bound of 1e3 eps, after which the solves were rounding and the active set grew past n rows
(tests/test_qp_active_set.py)."""


@functools.cache
def active_set_kernel(n: int, m: int, tol: float, out_float64: bool, weighted: bool):
    """The Warp kernel of problems with n unknowns and m rows (one thread each); outputs in float64 or float32."""
    wp = warp_module()
    real = wp.float64  # the solve's precision, whatever the inputs'
    io = wp.float64 if out_float64 else wp.float32
    vec_n = wp.types.vector(length=n, dtype=real)
    vec_m = wp.types.vector(length=m, dtype=real)
    mat_nn = wp.types.matrix(shape=(n, n), dtype=real)
    ivec_n = wp.types.vector(length=n, dtype=wp.int32)
    zero, one = real(0.0), real(1.0)
    inf = real(math.inf)
    nan_io = io(math.nan)
    tol_ = real(tol)
    tiny = real(np.finfo(np.float32).tiny)
    dependent = real(DEPENDENT_ROW)
    limit = STEP_LIMIT_PER_ROW * m

    @wp.func
    def row_dot(C: wp.array3d(dtype=io), p: int, k: int, inv_row: real, v: vec_n):
        acc = real(0.0)
        for j in range(n):
            acc += real(C[p, k, j]) * v[j]
        return acc * inv_row

    @wp.func
    def hinv_row(C: wp.array3d(dtype=io), p: int, k: int, inv_row: real, Hinv: mat_nn):
        # H^-1 a_k for the scaled row a_k = C_k / row_k (the <= form: the direction that raises C_k x)
        v = vec_n()
        for i in range(n):
            acc = real(0.0)
            for j in range(n):
                acc += Hinv[i, j] * real(C[p, k, j])
            v[i] = acc * inv_row
        return v

    @wp.kernel(enable_backward=False, module="unique", module_options={"max_unroll": 1})
    def active_set(
        H: wp.array3d(dtype=io),
        g: wp.array2d(dtype=io),
        C: wp.array3d(dtype=io),
        b: wp.array2d(dtype=io),
        weight: wp.array2d(dtype=io),
        x_out: wp.array2d(dtype=io),
        lam_out: wp.array2d(dtype=io),
        s_out: wp.array2d(dtype=io),
        flags_out: wp.array2d(dtype=wp.int32),  # converged, finite, steps
        stats_out: wp.array2d(dtype=io),  # violation, kkt_residual, res_d, res_p, res_c
    ):
        p = wp.tid()
        finite = bool(True)
        # Scaling (qp_ipm.interior_point's): rows of C to unit norm (or weight), max|H| = 1, data to O(1).
        inv_row = vec_m()
        bs = vec_m()
        for k in range(m):
            nrm = real(0.0)
            for j in range(n):
                ckj = real(C[p, k, j])
                nrm += ckj * ckj
                if not wp.isfinite(ckj):
                    finite = bool(False)
            nrm = wp.sqrt(nrm)
            if not (nrm > zero):
                nrm = real(1.0)
            if wp.static(weighted):
                nrm = nrm / real(weight[p, k])
            inv_row[k] = one / nrm
            bs[k] = real(b[p, k]) * inv_row[k]
            if not wp.isfinite(bs[k]):
                finite = bool(False)
        h = real(0.0)
        for i in range(n):
            for j in range(n):
                h = wp.max(h, wp.abs(real(H[p, i, j])))
                if not wp.isfinite(real(H[p, i, j])):
                    finite = bool(False)
        if not (h > zero) or not wp.isfinite(h):
            h = real(1.0)
        gs = vec_n()
        data = real(0.0)
        for i in range(n):
            gs[i] = real(g[p, i]) / h
            data = wp.max(data, wp.abs(gs[i]))
            if not wp.isfinite(gs[i]):
                finite = bool(False)
        for k in range(m):
            data = wp.max(data, wp.abs(bs[k]))
        if not (data > zero) or not wp.isfinite(data):
            data = real(1.0)
        for i in range(n):
            gs[i] = gs[i] / data
        for k in range(m):
            bs[k] = bs[k] / data

        # H_s = L L' (Cholesky of the symmetric part), H_s^-1 = L^-T L^-1.
        L = mat_nn()
        for j in range(n):
            acc = real(0.5) * (real(H[p, j, j]) + real(H[p, j, j])) / h
            for q in range(j):
                acc -= L[j, q] * L[j, q]
            if not (acc > zero):
                finite = bool(False)
                acc = real(1.0)
            L[j, j] = wp.sqrt(acc)
            for i in range(j + 1, n):
                acc = real(0.5) * (real(H[p, i, j]) + real(H[p, j, i])) / h
                for q in range(j):
                    acc -= L[i, q] * L[j, q]
                L[i, j] = acc / L[j, j]
        Linv = mat_nn()
        for col in range(n):
            for i in range(col, n):
                acc = real(0.0)
                if i == col:
                    acc = real(1.0)
                for q in range(col, i):
                    acc -= L[i, q] * Linv[q, col]
                Linv[i, col] = acc / L[i, i]
        Hinv = mat_nn()
        for i in range(n):
            for j in range(n):
                acc = real(0.0)
                for q in range(wp.max(i, j), n):
                    acc += Linv[q, i] * Linv[q, j]
                Hinv[i, j] = acc

        # The unconstrained minimiser; then rows are added (most violated first) until none is violated.
        x = vec_n()
        for i in range(n):
            acc = real(0.0)
            for j in range(n):
                acc -= Hinv[i, j] * gs[j]
            x[i] = acc
        act = ivec_n()  # the active rows
        u = vec_n()  # their multipliers (>= 0)
        k_act = int(0)
        steps = int(0)
        converged = bool(False)
        infeasible = bool(False)
        while finite and not converged and not infeasible and steps < limit:
            worst = real(0.0)
            q_new = int(-1)
            for k in range(m):
                viol = row_dot(C, p, k, inv_row[k], x) - bs[k]  # > 0: violated
                if viol > worst:
                    worst = viol
                    q_new = k
            if not (worst > tol_):
                converged = bool(True)
            else:
                u_new = real(0.0)
                added = bool(False)
                while not added and not infeasible and steps < limit:
                    # Directions: z in x (keeps the active rows' equalities, raises row q_new), r in u.
                    v = hinv_row(C, p, q_new, inv_row[q_new], Hinv)
                    HN = mat_nn()  # columns: H^-1 a_j of the active rows
                    for a in range(k_act):
                        ha = hinv_row(C, p, act[a], inv_row[act[a]], Hinv)
                        for i in range(n):
                            HN[i, a] = ha[i]
                    S = mat_nn()  # Cholesky factor of N' H^-1 N (k_act x k_act), in place
                    for a in range(k_act):
                        for c2 in range(a + 1):
                            acc = real(0.0)
                            for i in range(n):
                                acc += real(C[p, act[a], i]) * HN[i, c2]
                            acc = acc * inv_row[act[a]]
                            for q in range(c2):
                                acc -= S[a, q] * S[c2, q]
                            if a == c2:
                                S[a, a] = wp.sqrt(wp.max(acc, tiny))
                            else:
                                S[a, c2] = acc / S[c2, c2]
                    r = vec_n()
                    for a in range(k_act):  # forward: S y = N' v
                        acc = real(0.0)
                        for i in range(n):
                            acc += real(C[p, act[a], i]) * v[i]
                        acc = acc * inv_row[act[a]]
                        for q in range(a):
                            acc -= S[a, q] * r[q]
                        r[a] = acc / S[a, a]
                    for aa in range(k_act):  # backward: S' r = y
                        a = k_act - 1 - aa
                        acc = r[a]
                        for q in range(a + 1, k_act):
                            acc -= S[q, a] * r[q]
                        r[a] = acc / S[a, a]
                    z = vec_n()
                    for i in range(n):
                        acc = v[i]
                        for a in range(k_act):
                            acc -= HN[i, a] * r[a]
                        z[i] = acc
                    curvature = row_dot(C, p, q_new, inv_row[q_new], z)  # a_new' z
                    scale = row_dot(C, p, q_new, inv_row[q_new], v)  # a_new' H^-1 a_new
                    # Step lengths: t_full makes row q_new active; t_drop is where an active multiplier reaches 0.
                    t_full = inf
                    if k_act < n and curvature > dependent * scale:  # n active rows: z = 0, only a partial step
                        t_full = (row_dot(C, p, q_new, inv_row[q_new], x) - bs[q_new]) / curvature
                    t_drop = inf
                    drop = int(-1)
                    for a in range(k_act):
                        if r[a] > zero:
                            ta = u[a] / r[a]
                            if ta < t_drop:
                                t_drop = ta
                                drop = a
                    t = wp.min(t_full, t_drop)
                    if not (t < inf):
                        infeasible = bool(True)  # no step lowers the violation: the rows cannot all hold
                    else:
                        if t_full < inf:
                            for i in range(n):
                                x[i] = x[i] - t * z[i]
                        for a in range(k_act):
                            u[a] = u[a] - t * r[a]
                        u_new = u_new + t
                        steps += 1
                        if t_full <= t_drop:
                            act[k_act] = q_new
                            u[k_act] = u_new
                            k_act += 1
                            added = bool(True)
                        else:  # the blocking row leaves the active set (its multiplier is 0)
                            for a in range(drop, k_act - 1):
                                act[a] = act[a + 1]
                                u[a] = u[a + 1]
                            k_act -= 1

        # Multipliers, slacks and the KKT residual of the scaled problem (qp_ipm's residuals' definitions).
        lam = vec_m()
        for a in range(k_act):
            lam[act[a]] = wp.max(u[a], zero)
        max_x = real(0.0)
        for i in range(n):
            max_x = wp.max(max_x, wp.abs(x[i]))
            if not wp.isfinite(x[i]):
                finite = bool(False)
        max_r_d = real(0.0)
        max_Hx = real(0.0)
        max_Cz = real(0.0)
        for i in range(n):
            hx = real(0.0)
            for j in range(n):
                hx += real(0.5) * (real(H[p, i, j]) + real(H[p, j, i])) / h * x[j]
            cz = real(0.0)
            for a in range(k_act):
                cz += real(C[p, act[a], i]) * inv_row[act[a]] * lam[act[a]]
            max_r_d = wp.max(max_r_d, wp.abs(hx + gs[i] + cz))
            max_Hx = wp.max(max_Hx, wp.abs(hx))
            max_Cz = wp.max(max_Cz, wp.abs(cz))
        violation = real(0.0)
        max_Cx = real(0.0)
        res_c = real(0.0)
        max_lam = real(0.0)
        for k in range(m):
            max_lam = wp.max(max_lam, lam[k])
        s = vec_m()
        for k in range(m):
            cx = row_dot(C, p, k, inv_row[k], x)
            max_Cx = wp.max(max_Cx, wp.abs(cx))
            violation = wp.max(violation, cx - bs[k])
            s[k] = bs[k] - cx
            res_c = wp.max(res_c, wp.min(wp.max(s[k], zero) / (one + max_x), lam[k] / (one + max_lam)))
        res_d = max_r_d / (one + wp.max(max_Hx, max_Cz))
        res_p = violation / (one + max_Cx)
        res = wp.max(wp.max(res_d, res_p), res_c)
        if not finite:
            violation = inf
        for i in range(n):
            x_out[p, i] = io(data * x[i])
            if not finite:
                x_out[p, i] = nan_io
        for k in range(m):
            lam_out[p, k] = io(h * data * lam[k] * inv_row[k])
            s_out[p, k] = io(wp.max(data * s[k] / inv_row[k], tiny))
        flags_out[p, 0] = 0
        if finite and converged:
            flags_out[p, 0] = 1
        flags_out[p, 1] = 0
        if finite:
            flags_out[p, 1] = 1
        flags_out[p, 2] = steps
        stats_out[p, 0] = io(violation / (one + max_x))
        stats_out[p, 1] = io(res)
        stats_out[p, 2] = io(res_d)
        stats_out[p, 3] = io(res_p)
        stats_out[p, 4] = io(res_c)

    return wp.jax_kernel(active_set, num_outputs=5)
