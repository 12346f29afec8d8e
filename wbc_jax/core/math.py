"""Small gradient-safe helpers shared by the pipeline stages."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.custom_batching import custom_vmap

from wbc_jax.core.types import Array


def skew(v: Array) -> Array:
    """Skew-symmetric matrix S(v) with S(v) w = v x w. v: (..., 3) -> (..., 3, 3)."""
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    o = jnp.zeros_like(x)
    return jnp.stack([jnp.stack([o, -z, y], -1), jnp.stack([z, o, -x], -1), jnp.stack([-y, x, o], -1)], -2)


def quat_to_mat(q: Array) -> Array:
    """Rotation matrix (3, 3) of a (not necessarily unit) quaternion q = (w, x, y, z)."""
    q = q / jnp.sqrt(jnp.sum(q * q))
    w, x, y, z = q
    return jnp.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def quat_mul(a: Array, b: Array) -> Array:
    """Hamilton product of two (w, x, y, z) quaternions."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return jnp.array(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ]
    )


def safe_norm(x: Array, axis: int = -1, eps: float = 1e-12) -> Array:
    """Euclidean norm whose gradient is finite (zero) at x = 0 (double-where pattern)."""
    sq = jnp.sum(x * x, axis=axis)
    nonzero = sq > eps * eps
    return jnp.where(nonzero, jnp.sqrt(jnp.where(nonzero, sq, 1.0)), 0.0)


def damped_pinv(A: Array, damping: float) -> Array:
    """Damped pseudo-inverse A^T (A A^T + damping I)^-1 (WBC ``wbc.pinvDamped``). A: (r, c).

    A A^T + damping I is symmetric positive definite: a Cholesky solve (no pivots, half an LU's work)."""
    r = A.shape[0]
    return cho_solve_spd(A @ A.T + damping * jnp.eye(r, dtype=A.dtype), A).T


def cho_solve_spd(K: Array, B: Array) -> Array:
    """K^-1 B for a symmetric positive definite K (r, r) and B (r, ...), by Cholesky: on a CPU a
    third of the time of ``jnp.linalg.solve``'s LU for the controller's small systems (its pivots
    cost a loop of their own). Differentiable (only K's symmetric part matters)."""
    return cholesky_solve(K, B)[1]


def cholesky_solve(K: Array, B: Array) -> tuple[Array, Array]:
    """(L, K^-1 B): the lower Cholesky factor L (r, r) of the symmetric positive definite K (r, r) and the solve
    with B (r, ...) by it. Differentiable."""
    L = jnp.linalg.cholesky(K)
    return L, jax.scipy.linalg.cho_solve((L, True), B)


@custom_vmap
def batch_any(pred: Array) -> Array:
    """``pred`` () bool, reduced with ``any`` over every vmapped axis it is batched along.

    As the predicate of a ``lax.cond`` whose taken branch is also correct for the environments
    that did not need it, it keeps the cond a branch under vmap (a batched predicate turns it
    into a select that evaluates both branches for every environment): the costly branch runs
    only in the ticks where some environment of the batch needs it. Unbatched it is ``pred``.
    """
    return pred


@batch_any.def_vmap
def _batch_any_vmap(axis_size: int, in_batched: list[bool], pred: Array) -> tuple[Array, bool]:
    del axis_size
    return (jnp.any(pred, axis=0) if in_batched[0] else pred), False
