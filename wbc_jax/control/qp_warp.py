"""The force QP's Warp engines, each one kernel with one thread per problem: the interior point of
:func:`wbc_jax.control.qp_ipm.interior_point` (:func:`interior_point_warp`, engine ``"warp"``) and the dual active-set
method (:func:`active_set_warp`, engine ``"warp_active_set"``; :mod:`wbc_jax.control.qp_active_set_kernel`).

The interior point:

The same iterations, step for step (scaling, start, Mehrotra predictor-corrector, the Newton system with the
``n`` rows of largest ``z/s`` kept unreduced and its LU with partial pivoting, the residuals and the stopping
test), so the same solution within the tolerance. XLA runs a vmapped step as some twenty library kernels
(batched LU, triangular solves, ``top_k``) each a full pass over the batch, and every problem of the batch waits
for the slowest's Newton steps; here each problem's small matrices stay in its thread and it stops when it has
converged (results/gpu_h100/s58, BENCHMARKS.md). Never differentiated: :func:`wbc_jax.control.qp.solve_qp`
differentiates the solution implicitly, for either engine. Needs ``warp-lang`` (``pip install wbc_jax[cuda]``);
runs on CUDA and on the CPU (Warp's CPU backend).
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_batching import custom_vmap

from wbc_jax.control.qp_active_set_kernel import active_set_kernel
from wbc_jax.control.qp_ipm import IPMResult, result_of_outputs
from wbc_jax.control.qp_warp_kernel import ipm_kernel

Array = jax.Array


def _flat_ipm(H, g, C, b, weight, start, *, iterations, tol, weighted, warm, method="interior_point"):
    """The kernel over problems with any leading batch shape (flattened into one launch); ``method``
    ``"active_set"``: the dual active-set kernel (no ``iterations``, no ``start``)."""
    lead = g.shape[:-1]
    n, m = g.shape[-1], b.shape[-1]
    size = int(np.prod(lead)) if lead else 1
    dtype = H.dtype
    H2, g2, C2, b2 = (a.reshape((size,) + a.shape[len(lead) :]) for a in (H, g, C, b))
    w2 = weight.reshape(size, m) if weighted else jnp.ones((1, 1), dtype)
    if method == "active_set":
        f = active_set_kernel(n, m, float(tol), dtype == jnp.float64, weighted)
        inputs = (H2, g2, C2, b2, w2)
    else:
        f = ipm_kernel(n, m, int(iterations), float(tol), dtype == jnp.float64, weighted, warm)
        inputs = (H2, g2, C2, b2, w2, start.reshape(size, 2, m) if warm else jnp.zeros((1, 1, 1), dtype))
    x, lam, s, flags, stats = f(
        *inputs,
        launch_dims=(size,),
        output_dims={
            "x_out": (size, n),
            "lam_out": (size, m),
            "s_out": (size, m),
            "flags_out": (size, 3),
            "stats_out": (size, 5),
        },
    )
    return (
        x.reshape(lead + (n,)),
        lam.reshape(lead + (m,)),
        s.reshape(lead + (m,)),
        flags.reshape(lead + (3,)),
        stats.reshape(lead + (5,)),
    )


@functools.cache
def _batched(iterations: int, tol: float, weighted: bool, warm: bool, method: str = "interior_point"):
    """The kernel call as a function that vmap batches by widening its leading batch shape (one launch per
    call, whatever the vmaps around it)."""
    settings = dict(iterations=iterations, tol=tol, weighted=weighted, warm=warm, method=method)

    @custom_vmap
    def call(H, g, C, b, weight, start):
        return _flat_ipm(H, g, C, b, weight, start, **settings)

    @call.def_vmap
    def _(axis_size, in_batched, H, g, C, b, weight, start):
        args = [
            a if batched else jnp.broadcast_to(a, (axis_size,) + a.shape)
            for a, batched in zip((H, g, C, b, weight, start), in_batched)
        ]
        out = call(*args)
        return out, (True,) * len(out)

    return call


def interior_point_warp(
    H: Array,
    g: Array,
    C: Array,
    b: Array,
    iterations: int,
    tol: float,
    weight: Array | None = None,
    start: Array | None = None,
) -> IPMResult:
    """:func:`wbc_jax.control.qp_ipm.interior_point` (same arguments but ``unrolled``, same result) as one Warp
    kernel: H (n, n), g (n,), C (m, n), b (m,), weight (m,) or None, start (2, m) or None; under ``vmap`` one
    launch over the batch. float32 or float64. Not differentiated (callers pass ``stop_gradient`` data)."""
    dtype = H.dtype
    weighted, warm = weight is not None, start is not None
    w = weight if weighted else jnp.zeros((), dtype)
    s0 = start if warm else jnp.zeros((), dtype)
    x, lam, s, flags, stats = _batched(int(iterations), float(tol), weighted, warm)(H, g, C, b, w, s0)
    return result_of_outputs(x, lam, s, flags, stats)


def active_set_warp(H: Array, g: Array, C: Array, b: Array, tol: float, weight: Array | None = None) -> IPMResult:
    """The QP ``min 1/2 x'Hx + g'x s.t. Cx <= b`` by the dual active-set method, one Warp kernel
    (:mod:`wbc_jax.control.qp_active_set_kernel`): H (n, n) positive definite, g (n,), C (m, n), b (m,), weight (m,)
    or None (the scaled rows' norms, as :func:`wbc_jax.control.qp_ipm.interior_point`'s); under ``vmap`` one launch
    over the batch. ``tol``: the largest violation of a row, in the scaled problem, that counts as none. Returns the
    interior point's :class:`wbc_jax.control.qp_ipm.IPMResult`: ``iterations`` the rows added and dropped,
    ``lam`` zero and ``s`` positive off the active set. float32 or float64 data, solved in float64. Not
    differentiated (callers pass ``stop_gradient`` data)."""
    dtype = H.dtype
    weighted = weight is not None
    w = weight if weighted else jnp.zeros((), dtype)
    x, lam, s, flags, stats = _batched(0, float(tol), weighted, False, "active_set")(
        H, g, C, b, w, jnp.zeros((), dtype)
    )
    return result_of_outputs(x, lam, s, flags, stats)
