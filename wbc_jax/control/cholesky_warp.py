"""The torque law's mass-matrix solve as one Warp tile kernel (``ControllerConfig.mass_solve_engine = "warp"``):
``M = L L^T`` and ``X = M^-1 B`` for each environment's M (nv x nv) and right-hand sides B (nv x c), one block of
threads per environment, the matrices in the block's shared memory (``warp.tile_cholesky`` and
``warp.tile_cholesky_solve``, MathDx on CUDA).

Why: under vmap XLA runs the JAX solve (:func:`wbc_jax.core.math.cholesky_solve`) as batched library calls on
small matrices (cuSOLVER ``potrf``, cuBLAS ``trsm``), each a full pass over the batch's matrices in the GPU's memory:
on the H100 the Cholesky and its two triangular solves were the torque law's largest part (BENCHMARKS.md, "The torque
law's 0.223 by library call"). Here each environment's M and B are read once and L and X written once.

Derivatives: the kernel is not differentiated; :func:`cholesky_solve_warp`'s JVP is the JAX solve's, value and
tangent (so a differentiated program runs the JAX solve in place of the kernel). Needs ``warp-lang`` (``pip install wbc_jax[cuda]``);
runs on CUDA and on the CPU (Warp's CPU backend, one thread per block). The block's width follows JAX's default
backend when the program is traced: a program placed on the CPU of a GPU machine would run each block's routine once
per thread (the same result, at that many times the work), so the engine is for programs on the default device.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax.control.warp_launch import one_launch_under_vmap, warp_module
from wbc_jax.core.math import cholesky_solve

Array = jax.Array

BLOCK_THREADS_CUDA = 64
"""Threads of each environment's block on CUDA: the tile routines' cooperative width."""


@functools.cache
def _kernel(r: int, c: int, float64: bool, block: int):
    """The tile kernel for K (r, r) and B (r, c), one block of ``block`` threads per problem."""
    wp = warp_module()
    real = wp.float64 if float64 else wp.float32

    @wp.kernel(enable_backward=False, module="unique")
    def cholesky_solve(
        K: wp.array3d(dtype=real),
        B: wp.array3d(dtype=real),
        L_out: wp.array3d(dtype=real),
        X_out: wp.array3d(dtype=real),
    ):
        p, _lane = wp.tid()
        L = wp.tile_cholesky(wp.tile_load(K[p], shape=(r, r)))
        X = wp.tile_cholesky_solve(L, wp.tile_load(B[p], shape=(r, c)))
        wp.tile_store(L_out[p], L)
        wp.tile_store(X_out[p], X)

    return wp.jax_kernel(cholesky_solve, num_outputs=2, block_dim=block)


def _block_threads() -> int:
    return BLOCK_THREADS_CUDA if jax.default_backend() == "gpu" else 1


def _flat(K, B):
    """The kernel over problems with any leading batch shape (flattened into one launch)."""
    lead = K.shape[:-2]
    r, c = B.shape[-2], B.shape[-1]
    size = int(np.prod(lead)) if lead else 1
    block = _block_threads()
    f = _kernel(r, c, K.dtype == jnp.float64, block)
    L, X = f(
        K.reshape(size, r, r),
        B.reshape(size, r, c),
        launch_dims=(size, block),
        output_dims={"L_out": (size, r, r), "X_out": (size, r, c)},
    )
    return L.reshape(lead + (r, r)), X.reshape(lead + (r, c))


_batched = one_launch_under_vmap(_flat)


@jax.custom_jvp
def cholesky_solve_warp(K: Array, B: Array) -> tuple[Array, Array]:
    """(L, K^-1 B) as :func:`wbc_jax.core.math.cholesky_solve`, by the Warp tile kernel: K (r, r) symmetric positive definite,
    B (r, c), float32 or float64 (both alike); under ``vmap`` one launch over the batch. Its derivatives are the JAX
    solve's (module docstring)."""
    if K.dtype != B.dtype or K.shape[-1] != K.shape[-2] or B.shape[-2] != K.shape[-1]:
        raise ValueError(
            f"cholesky_solve_warp: K (r, r) and B (r, c) of one dtype, got {K.shape} {K.dtype}, {B.shape} {B.dtype}"
        )
    return _batched(K, B)


@cholesky_solve_warp.defjvp
def _cholesky_solve_warp_jvp(primals, tangents):
    # The JAX solve's value and tangent: a differentiated program runs it in place of the kernel, not beside it.
    return jax.jvp(cholesky_solve, primals, tangents)
