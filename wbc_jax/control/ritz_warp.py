"""The postural projector's Ritz decomposition as one Warp kernel (``ControllerConfig.ritz_engine = "warp"``): for
each environment's symmetric A (n x n) and B = A S (n x k, k <= n), an orthonormal basis Q of B's columns
(Householder QR, Q formed from the reflectors as LAPACK's ``geqrf`` + ``orgqr``), A Q, and the eigenpairs of the
k x k Rayleigh quotient Q' A Q (cyclic Jacobi, eigenvalues ascending as ``eigh``'s), one thread per environment,
computed in float64 whatever the inputs' precision. :func:`wbc_jax.control.torques.ritz_projector` certifies the
result as it certifies the JAX decomposition's.

Why: under vmap XLA runs the JAX decomposition as batched library kernels, each a full pass over the batch's
matrices in the GPU's memory; on the H100 the QR's forming of Q (``householder_product``) and the small ``eigh``
were the projector's largest parts (BENCHMARKS.md, "Where the rest went"). Here each environment's A and B are read
once and Q, A Q and the eigenpairs written once; the matrices live in the thread's local memory.

Derivatives: none are needed: the projector's derivative comes from the whole eigendecomposition
(:func:`wbc_jax.control.torques.spectral_projector`'s JVP), and the Ritz decomposition only decides its value.
Needs ``warp-lang`` (``pip install wbc_jax[cuda]``); runs on CUDA and on the CPU (Warp's CPU backend).
"""

# Warp needs a variable that a dynamic loop changes declared by its type (x = int(0)): UP018 off.
# ruff: noqa: UP018

import functools

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax.control.warp_launch import one_launch_under_vmap, warp_module

Array = jax.Array

JACOBI_SWEEPS = 30
"""The Jacobi iteration's bound on sweeps over the k (k - 1) / 2 rotations; it stops earlier where the off-diagonal
part's Frobenius norm falls below float64's eps of the whole (quadratic convergence: 6-8 sweeps at k = 12)."""


@functools.cache
def _kernel(n: int, k: int, out_float64: bool):
    """The Warp kernel for A (n, n) and B (n, k), one thread per problem."""
    wp = warp_module()
    real = wp.float64
    io = wp.float64 if out_float64 else wp.float32
    mat_nn = wp.types.matrix(shape=(n, n), dtype=real)
    mat_nk = wp.types.matrix(shape=(n, k), dtype=real)
    mat_kk = wp.types.matrix(shape=(k, k), dtype=real)
    vec_k = wp.types.vector(length=k, dtype=real)
    eps2 = real(np.finfo(np.float64).eps ** 2)

    @wp.kernel(enable_backward=False, module="unique", module_options={"max_unroll": 1})
    def ritz(
        A_in: wp.array3d(dtype=io),
        B_in: wp.array3d(dtype=io),
        Q_out: wp.array3d(dtype=io),
        AQ_out: wp.array3d(dtype=io),
        theta_out: wp.array2d(dtype=io),
        W_out: wp.array3d(dtype=io),
    ):
        p = wp.tid()
        A = mat_nn()
        for i in range(n):
            for j in range(n):
                A[i, j] = real(A_in[p, i, j])
        # Householder QR of B: the reflectors' vectors below and on the diagonal of H, H_j = I - tau_j v_j v_j'.
        H = mat_nk()
        for i in range(n):
            for j in range(k):
                H[i, j] = real(B_in[p, i, j])
        tau = vec_k()
        for j in range(k):
            norm2 = real(0.0)
            for i in range(j, n):
                norm2 += H[i, j] * H[i, j]
            alpha = wp.sqrt(norm2)
            if H[j, j] > real(0.0):
                alpha = -alpha
            vj = H[j, j] - alpha
            vnorm2 = norm2 - H[j, j] * H[j, j] + vj * vj
            t = real(0.0)
            if vnorm2 > real(0.0):  # else B's column j is zero below row j: no reflection
                t = real(2.0) / vnorm2
                H[j, j] = vj
                for c in range(j + 1, k):
                    s = real(0.0)
                    for i in range(j, n):
                        s += H[i, j] * H[i, c]
                    for i in range(j, n):
                        H[i, c] = H[i, c] - t * s * H[i, j]
            tau[j] = t
        # Q = H_0 ... H_{k-1} [I; 0] in H, in place of the reflectors (LAPACK's orgqr): from the last reflector to the
        # first, H_j applied to the columns already formed, then column j = H_j e_j (rows above j zero).
        for jj in range(k):
            j = k - 1 - jj
            for c in range(j + 1, k):
                s = real(0.0)
                for i in range(j, n):
                    s += H[i, j] * H[i, c]
                for i in range(j, n):
                    H[i, c] = H[i, c] - tau[j] * s * H[i, j]
            vj = H[j, j]
            for i in range(j + 1, n):
                H[i, j] = -tau[j] * vj * H[i, j]
            H[j, j] = real(1.0) - tau[j] * vj * vj
            for i in range(j):
                H[i, j] = real(0.0)
        AQ = mat_nk()
        for i in range(n):
            for c in range(k):
                s = real(0.0)
                for q in range(n):
                    s += A[i, q] * H[q, c]
                AQ[i, c] = s
        T = mat_kk()
        for a in range(k):
            for c in range(a, k):
                s = real(0.0)
                for i in range(n):
                    s += H[i, a] * AQ[i, c] + H[i, c] * AQ[i, a]
                T[a, c] = real(0.5) * s
                T[c, a] = real(0.5) * s
        # Cyclic Jacobi: T <- J' T J per pair (a, c), V <- V J (Golub and Van Loan, "Matrix Computations", 8.5).
        V = mat_kk()
        for a in range(k):
            V[a, a] = real(1.0)
        sweep = int(0)
        done = bool(False)
        while not done and sweep < JACOBI_SWEEPS:
            off = real(0.0)
            total = real(0.0)
            for a in range(k):
                for c in range(k):
                    total += T[a, c] * T[a, c]
                    if c != a:
                        off += T[a, c] * T[a, c]
            if off <= eps2 * total:
                done = bool(True)
            else:
                for a in range(k - 1):
                    for c in range(a + 1, k):
                        apq = T[a, c]
                        if apq != real(0.0):
                            th = (T[c, c] - T[a, a]) / (real(2.0) * apq)
                            t = real(0.0)
                            if wp.abs(th) > real(1.0e150):
                                t = real(0.5) / th
                            else:
                                t = wp.sign(th) / (wp.abs(th) + wp.sqrt(th * th + real(1.0)))
                                if th == real(0.0):
                                    t = real(1.0)
                            cs = real(1.0) / wp.sqrt(t * t + real(1.0))
                            sn = t * cs
                            for r in range(k):
                                tp = T[r, a]
                                tq = T[r, c]
                                T[r, a] = cs * tp - sn * tq
                                T[r, c] = sn * tp + cs * tq
                            for r in range(k):
                                tp = T[a, r]
                                tq = T[c, r]
                                T[a, r] = cs * tp - sn * tq
                                T[c, r] = sn * tp + cs * tq
                            for r in range(k):
                                vp = V[r, a]
                                vq = V[r, c]
                                V[r, a] = cs * vp - sn * vq
                                V[r, c] = sn * vp + cs * vq
                sweep += 1
        # Eigenvalues ascending (eigh's order), their vectors with them.
        w = vec_k()
        for a in range(k):
            w[a] = T[a, a]
        for a in range(k):
            best = a
            for c in range(a + 1, k):
                if w[c] < w[best]:
                    best = c
            if best != a:
                tmp = w[a]
                w[a] = w[best]
                w[best] = tmp
                for r in range(k):
                    tv = V[r, a]
                    V[r, a] = V[r, best]
                    V[r, best] = tv
        for i in range(n):
            for c in range(k):
                Q_out[p, i, c] = io(H[i, c])
                AQ_out[p, i, c] = io(AQ[i, c])
        for a in range(k):
            theta_out[p, a] = io(w[a])
            for c in range(k):
                W_out[p, a, c] = io(V[a, c])

    return wp.jax_kernel(ritz, num_outputs=4)


def _flat(A, B):
    """The kernel over problems with any leading batch shape (flattened into one launch)."""
    lead = A.shape[:-2]
    n, k = B.shape[-2], B.shape[-1]
    size = int(np.prod(lead)) if lead else 1
    f = _kernel(n, k, A.dtype == jnp.float64)
    Q, AQ, theta, W = f(
        A.reshape(size, n, n),
        B.reshape(size, n, k),
        launch_dims=size,
        output_dims={"Q_out": (size, n, k), "AQ_out": (size, n, k), "theta_out": (size, k), "W_out": (size, k, k)},
    )
    return Q.reshape(lead + (n, k)), AQ.reshape(lead + (n, k)), theta.reshape(lead + (k,)), W.reshape(lead + (k, k))


_batched = one_launch_under_vmap(_flat)


def ritz_decomposition_warp(A: Array, B: Array) -> tuple[Array, Array, Array, Array]:
    """(Q (n, k), A Q (n, k), theta (k,), W (k, k)) as :func:`wbc_jax.control.torques.ritz_decomposition`, by the
    Warp kernel: A (n, n) symmetric, B (n, k) with k <= n, float32 or float64 (both alike; computed in float64);
    under ``vmap`` one launch over the batch. Not differentiated (module docstring): the inputs' tangents are
    dropped."""
    if A.dtype != B.dtype or A.shape[-1] != A.shape[-2] or B.shape[-2] != A.shape[-1] or B.shape[-1] > B.shape[-2]:
        raise ValueError(
            f"ritz_decomposition_warp: A (n, n) and B (n, k <= n) of one dtype, got {A.shape} {A.dtype}, "
            f"{B.shape} {B.dtype}"
        )
    return _batched(jax.lax.stop_gradient(A), jax.lax.stop_gradient(B))
