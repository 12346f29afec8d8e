"""The Warp kernel of :mod:`wbc_jax.control.qp_warp`: :func:`wbc_jax.control.qp_ipm.interior_point` transcribed,
one thread per problem (its scaling, start, Mehrotra predictor-corrector, the Newton system with the ``n`` rows of
largest ``z/s`` kept unreduced and its LU with partial pivoting, residuals and stopping test), as a JAX call
(``warp.jax_kernel``). Built per problem size and static setting, once per process (Warp caches the compiled code
on disk).
"""

# Warp needs a variable that a dynamic loop changes declared by its type (x = int(0), flag = bool(True)): UP018 off.
# ruff: noqa: UP018

import functools
import math

import numpy as np

from wbc_jax.control.qp_ipm import STEP_TO_BOUNDARY, WARM_START_FLOOR
from wbc_jax.control.warp_launch import warp_module


@functools.cache
def ipm_kernel(n: int, m: int, iterations: int, tol: float, float64: bool, weighted: bool, warm: bool):
    """The Warp kernel of problems with n unknowns and m rows (one thread each), for these static settings."""
    wp = warp_module()
    real = wp.float64 if float64 else wp.float32
    eps = float(np.finfo(np.float64 if float64 else np.float32).eps)
    nk = min(n, m)  # rows kept unreduced in the Newton system (qp_ipm._newton_solver)
    r = n + nk
    vec_n = wp.types.vector(length=n, dtype=real)
    vec_m = wp.types.vector(length=m, dtype=real)
    vec_r = wp.types.vector(length=r, dtype=real)
    mat_nn = wp.types.matrix(shape=(n, n), dtype=real)
    mat_mn = wp.types.matrix(shape=(m, n), dtype=real)
    mat_rr = wp.types.matrix(shape=(r, r), dtype=real)
    ivec_m = wp.types.vector(length=m, dtype=wp.int32)
    ivec_k = wp.types.vector(length=nk, dtype=wp.int32)
    ivec_r = wp.types.vector(length=r, dtype=wp.int32)
    zero, one = real(0.0), real(1.0)
    nan = real(math.nan)
    reg = real(10.0 * eps)
    tol_ = real(tol)
    floor = real(WARM_START_FLOOR)
    to_boundary = real(STEP_TO_BOUNDARY)
    m_real = real(float(m))

    @wp.func
    def nanmax(a: real, b: real):
        # jnp.max's NaN: a NaN anywhere makes the maximum NaN
        if wp.isnan(a) or wp.isnan(b):
            return nan
        return wp.max(a, b)

    @wp.func
    def max_step(v: vec_m, w: vec_m, dv: vec_m, dw: vec_m):
        # qp_ipm._max_step over the stacked [s, z]: NaN where some entry of the direction is not finite
        a = real(1.0)
        bad = bool(False)
        for i in range(m):
            if not wp.isfinite(dv[i]) or not wp.isfinite(dw[i]):
                bad = bool(True)
            if dv[i] < zero:
                a = wp.min(a, -v[i] / dv[i])
            if dw[i] < zero:
                a = wp.min(a, -w[i] / dw[i])
        if bad:
            return nan
        return a

    @wp.func
    def residuals(Hs: mat_nn, Cs: mat_mn, gs: vec_n, bs: vec_m, x: vec_n, s: vec_m, z: vec_m):
        # qp_ipm.interior_point.residuals: (r_d, r_p, res, (res_d, res_p, res_c))
        r_d = vec_n()
        max_r_d = real(0.0)
        max_Hx = real(0.0)
        max_Cz = real(0.0)
        max_x = real(0.0)
        for i in range(n):
            hx = real(0.0)
            for j in range(n):
                hx += Hs[i, j] * x[j]
            cz = real(0.0)
            for k in range(m):
                cz += Cs[k, i] * z[k]
            r_d[i] = hx + gs[i] + cz
            max_r_d = nanmax(max_r_d, wp.abs(r_d[i]))
            max_Hx = nanmax(max_Hx, wp.abs(hx))
            max_Cz = nanmax(max_Cz, wp.abs(cz))
            max_x = nanmax(max_x, wp.abs(x[i]))
        r_p = vec_m()
        max_r_p = real(0.0)
        max_Cx = real(0.0)
        max_z = real(0.0)
        for k in range(m):
            cx = real(0.0)
            for j in range(n):
                cx += Cs[k, j] * x[j]
            r_p[k] = cx + s[k] - bs[k]
            max_r_p = nanmax(max_r_p, wp.abs(r_p[k]))
            max_Cx = nanmax(max_Cx, wp.abs(cx))
            max_z = nanmax(max_z, wp.abs(z[k]))
        res_d = max_r_d / (one + nanmax(max_Hx, max_Cz))
        res_p = max_r_p / (one + max_Cx)
        res_c = real(-math.inf)
        for k in range(m):
            res_c = nanmax(res_c, wp.min(s[k] / (one + max_x), z[k] / (one + max_z)))
            if wp.isnan(s[k]) or wp.isnan(z[k]):
                res_c = nan
        res = nanmax(nanmax(res_d, res_p), res_c)
        return r_d, r_p, res, wp.vec3d(wp.float64(res_d), wp.float64(res_p), wp.float64(res_c))

    @wp.func
    def newton_solve(
        lu: mat_rr,
        perm: ivec_r,
        Cs: mat_mn,
        keep: ivec_k,
        slot: ivec_m,
        ratio: vec_m,
        s: vec_m,
        z: vec_m,
        r_d: vec_n,
        r_p: vec_m,
        r_c: vec_m,
    ):
        # qp_ipm._newton_solver.newton: (dx, ds, dz) for the complementarity target r_c
        t = vec_m()
        for k in range(m):
            t[k] = (z[k] * r_p[k] - r_c[k]) / s[k]
        rhs = vec_r()
        for i in range(n):
            acc = -r_d[i]
            for k in range(m):
                if slot[k] >= nk:  # eliminated row
                    acc -= Cs[k, i] * t[k]
            rhs[i] = acc
        for q in range(nk):
            k = keep[q]
            rhs[n + q] = -(t[k] * s[k] / (z[k] + s[k]))
        # P rhs, then L (unit diagonal) and U
        d = vec_r()
        for i in range(r):
            d[i] = rhs[perm[i]]
        for i in range(r):
            acc = d[i]
            for j in range(i):
                acc -= lu[i, j] * d[j]
            d[i] = acc
        for ii in range(r):
            i = r - 1 - ii
            acc = d[i]
            for j in range(i + 1, r):
                acc -= lu[i, j] * d[j]
            d[i] = acc / lu[i, i]
        dx = vec_n()
        for i in range(n):
            dx[i] = d[i]
        ds = vec_m()
        dz = vec_m()
        for k in range(m):
            cdx = real(0.0)
            for j in range(n):
                cdx += Cs[k, j] * d[j]
            ds[k] = -r_p[k] - cdx
            if slot[k] < nk:
                dz[k] = d[n + slot[k]]
            else:
                dz[k] = t[k] + ratio[k] * cdx
        return dx, ds, dz

    # max_unroll 1: Warp's default unrolls every loop of up to 16 passes, and the nested loops over n then make a
    # source that took the H100 run 174 s to build, against about 50 s without (BENCHMARKS.md). CUDA still unrolls.
    @wp.kernel(enable_backward=False, module="unique", module_options={"max_unroll": 1})
    def ipm(
        H: wp.array3d(dtype=real),
        g: wp.array2d(dtype=real),
        C: wp.array3d(dtype=real),
        b: wp.array2d(dtype=real),
        weight: wp.array2d(dtype=real),
        start: wp.array3d(dtype=real),
        x_out: wp.array2d(dtype=real),
        lam_out: wp.array2d(dtype=real),
        s_out: wp.array2d(dtype=real),
        flags_out: wp.array2d(dtype=wp.int32),  # converged, finite, iterations
        stats_out: wp.array2d(dtype=real),  # violation, kkt_residual, res_d, res_p, res_c
    ):
        p = wp.tid()
        # Scaling (qp_ipm.interior_point): rows of C to unit norm (or weight), max|H| = 1, data to O(1).
        row = vec_m()
        Cs = mat_mn()
        bs = vec_m()
        for k in range(m):
            nrm = real(0.0)
            for j in range(n):
                nrm += C[p, k, j] * C[p, k, j]
            nrm = wp.sqrt(nrm)
            if not (nrm > zero):
                nrm = real(1.0)
            if wp.static(weighted):
                nrm = nrm / weight[p, k]
            row[k] = nrm
            for j in range(n):
                Cs[k, j] = C[p, k, j] / nrm
            bs[k] = b[p, k] / nrm
        h = real(0.0)
        for i in range(n):
            for j in range(n):
                h = nanmax(h, wp.abs(H[p, i, j]))
        if not (h > zero):
            h = real(1.0)
        Hs = mat_nn()
        gs = vec_n()
        data = real(0.0)
        for i in range(n):
            for j in range(n):
                Hs[i, j] = H[p, i, j] / h
            gs[i] = g[p, i] / h
            data = nanmax(data, wp.abs(gs[i]))
        for k in range(m):
            data = nanmax(data, wp.abs(bs[k]))
        if not (data > zero):
            data = real(1.0)
        for i in range(n):
            gs[i] = gs[i] / data
        for k in range(m):
            bs[k] = bs[k] / data

        # Start (CVXOPT's heuristic): (Hs + Cs'Cs + reg I) x0 = -gs + Cs'bs by Cholesky.
        K0 = mat_nn()
        rhs0 = vec_n()
        for i in range(n):
            for j in range(n):
                acc = Hs[i, j]
                for k in range(m):
                    acc += Cs[k, i] * Cs[k, j]
                K0[i, j] = acc
            K0[i, i] = K0[i, i] + reg
            acc = -gs[i]
            for k in range(m):
                acc += Cs[k, i] * bs[k]
            rhs0[i] = acc
        L0 = mat_nn()
        for j in range(n):
            acc = K0[j, j]
            for q in range(j):
                acc -= L0[j, q] * L0[j, q]
            L0[j, j] = wp.sqrt(acc)
            for i in range(j + 1, n):
                acc = K0[i, j]
                for q in range(j):
                    acc -= L0[i, q] * L0[j, q]
                L0[i, j] = acc / L0[j, j]
        y0 = vec_n()
        for i in range(n):
            acc = rhs0[i]
            for q in range(i):
                acc -= L0[i, q] * y0[q]
            y0[i] = acc / L0[i, i]
        x = vec_n()
        for ii in range(n):
            i = n - 1 - ii
            acc = y0[i]
            for q in range(i + 1, n):
                acc -= L0[q, i] * x[q]
            x[i] = acc / L0[i, i]
        s = vec_m()
        z = vec_m()
        min_s = real(math.inf)
        max_s = real(-math.inf)
        for k in range(m):
            cx = real(0.0)
            for j in range(n):
                cx += Cs[k, j] * x[j]
            s[k] = bs[k] - cx
            min_s = wp.min(min_s, s[k])
            max_s = wp.max(max_s, s[k])
        min_z = -max_s  # z0 = -s0 before the shifts
        shift_s = wp.max(zero, one - min_s)
        shift_z = wp.max(zero, one - min_z)
        for k in range(m):
            z[k] = -s[k] + shift_z
            s[k] = s[k] + shift_s
        if wp.static(warm):
            finite_warm = bool(True)
            zw = vec_m()
            sw = vec_m()
            for k in range(m):
                zw[k] = wp.max(start[p, 0, k] * row[k] / (h * data), floor)
                sw[k] = wp.max(start[p, 1, k] / (row[k] * data), floor)
                if not wp.isfinite(start[p, 0, k]) or not wp.isfinite(start[p, 1, k]):
                    finite_warm = bool(False)
            if finite_warm:
                s = sw
                z = zw

        Hreg = mat_nn()
        for i in range(n):
            for j in range(n):
                Hreg[i, j] = Hs[i, j]
            Hreg[i, i] = Hs[i, i] + reg
        mu = real(0.0)
        for k in range(m):
            mu += s[k] * z[k]
        mu = mu / m_real
        r_d, r_p, res, parts = residuals(Hs, Cs, gs, bs, x, s, z)
        count = int(0)
        it = int(0)
        while not (res <= tol_) and it < iterations:
            # The Newton system (qp_ipm._newton_solver): the nk rows of largest z/s kept (lax.top_k's order:
            # descending, the lower index first among equals), the others eliminated.
            ratio = vec_m()
            for k in range(m):
                ratio[k] = z[k] / s[k]
            keep = ivec_k()
            slot = ivec_m()
            for k in range(m):
                slot[k] = nk
            for q in range(nk):
                best = int(-1)
                for k in range(m):
                    if slot[k] == nk:
                        if best < 0:
                            best = k
                        elif ratio[k] > ratio[best]:
                            best = k
                keep[q] = best
                slot[best] = q
            K = mat_rr()
            for i in range(n):
                for j in range(n):
                    acc = Hreg[i, j]
                    for k in range(m):
                        if slot[k] >= nk:
                            acc += Cs[k, i] * ratio[k] * Cs[k, j]
                    K[i, j] = acc
                for q in range(nk):
                    K[i, n + q] = Cs[keep[q], i]
            for q in range(nk):
                k = keep[q]
                zk = z[k] / (z[k] + s[k])
                for j in range(n):
                    K[n + q, j] = zk * Cs[k, j]
                K[n + q, n + q] = -(s[k] / (z[k] + s[k]))
            # LU with partial pivoting (lax.linalg.lu): the row of largest |entry| in each column, the first
            # among equals; perm[i] = the original row now at i.
            perm = ivec_r()
            for i in range(r):
                perm[i] = i
            for j in range(r):
                piv = int(j)
                big = wp.abs(K[j, j])
                for i in range(j + 1, r):
                    if wp.abs(K[i, j]) > big:
                        big = wp.abs(K[i, j])
                        piv = i
                if piv != j:
                    for q in range(r):
                        tmp = K[j, q]
                        K[j, q] = K[piv, q]
                        K[piv, q] = tmp
                    tp = perm[j]
                    perm[j] = perm[piv]
                    perm[piv] = tp
                for i in range(j + 1, r):
                    K[i, j] = K[i, j] / K[j, j]
                    for q in range(j + 1, r):
                        K[i, q] = K[i, q] - K[i, j] * K[j, q]

            # Predictor (affine scaling): target s z = 0.
            r_c = vec_m()
            for k in range(m):
                r_c[k] = s[k] * z[k]
            dx_a, ds_a, dz_a = newton_solve(K, perm, Cs, keep, slot, ratio, s, z, r_d, r_p, r_c)
            a_aff = max_step(s, z, ds_a, dz_a)
            mu_aff = real(0.0)
            for k in range(m):
                mu_aff += (s[k] + a_aff * ds_a[k]) * (z[k] + a_aff * dz_a[k])
            mu_aff = mu_aff / m_real
            sigma = wp.clamp(mu_aff / mu, zero, one)
            if wp.isnan(mu_aff / mu):
                sigma = nan
            sigma = sigma * sigma * sigma
            # Corrector: centring sigma mu plus the second-order term ds_a dz_a.
            for k in range(m):
                r_c[k] = s[k] * z[k] + ds_a[k] * dz_a[k] - sigma * mu
            dx, ds, dz = newton_solve(K, perm, Cs, keep, slot, ratio, s, z, r_d, r_p, r_c)
            alpha = to_boundary * max_step(s, z, ds, dz)
            mu_n = real(0.0)
            for k in range(m):
                mu_n += (s[k] + alpha * ds[k]) * (z[k] + alpha * dz[k])
            mu_n = mu_n / m_real
            if wp.isfinite(alpha) and wp.isfinite(mu_n):
                for i in range(n):
                    x[i] = x[i] + alpha * dx[i]
                for k in range(m):
                    s[k] = s[k] + alpha * ds[k]
                    z[k] = z[k] + alpha * dz[k]
                mu = mu_n
                count += 1
            r_d, r_p, res, parts = residuals(Hs, Cs, gs, bs, x, s, z)
            it += 1

        finite = bool(True)
        max_x = real(0.0)
        for i in range(n):
            if not wp.isfinite(x[i]):
                finite = bool(False)
            max_x = nanmax(max_x, wp.abs(x[i]))
        for k in range(m):
            if not wp.isfinite(s[k]) or not wp.isfinite(z[k]):
                finite = bool(False)
        violation = real(0.0)
        for k in range(m):
            cx = real(0.0)
            for j in range(n):
                cx += Cs[k, j] * x[j]
            violation = nanmax(violation, wp.max(cx - bs[k], zero))
        violation = violation / (one + max_x)
        if not finite:
            violation = real(math.inf)
        for i in range(n):
            x_out[p, i] = data * x[i]
        for k in range(m):
            lam_out[p, k] = (h * data) * z[k] / row[k]
            s_out[p, k] = (row[k] * data) * s[k]
        converged = int(0)
        if finite and res <= tol_:
            converged = 1
        flags_out[p, 0] = converged
        flags_out[p, 1] = 0
        if finite:
            flags_out[p, 1] = 1
        flags_out[p, 2] = count
        stats_out[p, 0] = violation
        stats_out[p, 1] = res
        stats_out[p, 2] = real(parts[0])
        stats_out[p, 3] = real(parts[1])
        stats_out[p, 4] = real(parts[2])

    return wp.jax_kernel(ipm, num_outputs=5)
