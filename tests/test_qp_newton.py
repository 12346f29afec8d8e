"""The interior point's Newton step (wbc_jax.control.qp_ipm) against a dense float64 solve.

:func:`qp_ipm._newton_solver` keeps the rows with the largest z/s unreduced, eliminates the
others and maps the solution back to (dx, ds, dz) through a gather of the kept rows' places;
here its directions are checked against NumPy's solve of the full (n + 2m) Newton system at
random interior points whose active rows lie anywhere among the m rows.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from wbc_jax.control import qp_ipm

jax.config.update("jax_enable_x64", True)


def interior_point_state(rng: np.random.Generator, n: int, m: int) -> dict:
    """A scaled problem (unit rows, max|H| = 1) and an iterate near a solution with n - 1 active
    rows (s ~ 1e-5, z ~ 1), inactive ones (s ~ 1, z ~ 1e-5) and the rest in between, shuffled."""
    X = rng.standard_normal((n, n))
    H = X @ X.T + 0.1 * np.eye(n)
    H /= np.max(np.abs(H))
    C = rng.standard_normal((m, n))
    C /= np.linalg.norm(C, axis=1, keepdims=True)
    kind = rng.permutation(np.arange(m) % 3)
    kind[rng.choice(m, n - 1, replace=False)] = 0  # n - 1 active rows
    small, large = 10.0 ** rng.uniform(-6, -4, m), 10.0 ** rng.uniform(-0.5, 0.5, m)
    mid = 10.0 ** rng.uniform(-2, 0, (2, m))
    s = np.where(kind == 0, small, np.where(kind == 1, large, mid[0]))
    z = np.where(kind == 0, large, np.where(kind == 1, small, mid[1]))
    return dict(
        H=H,
        C=C,
        s=s,
        z=z,
        r_d=1e-2 * rng.standard_normal(n),
        r_p=1e-2 * rng.standard_normal(m),
        r_c=s * z + 1e-3 * rng.standard_normal(m),
    )


def dense_newton(H, C, s, z, r_d, r_p, r_c):
    """The full Newton system (H dx + C'dz = -r_d, C dx + ds = -r_p, Z ds + S dz = -r_c), float64."""
    n, m = H.shape[0], C.shape[0]
    K = np.zeros((n + 2 * m, n + 2 * m))
    K[:n, :n], K[:n, n + m :] = H, C.T
    K[n : n + m, :n], K[n : n + m, n : n + m] = C, np.eye(m)
    K[n + m :, n : n + m], K[n + m :, n + m :] = np.diag(z), np.diag(s)
    d = np.linalg.solve(K, -np.concatenate([r_d, r_p, r_c]))
    return d[:n], d[n : n + m], d[n + m :]


@functools.cache
def newton_direction():
    """``(H, C, s, z, r_d, r_p, r_c) -> (dx, ds, dz)`` of qp_ipm's solver, vmapped and compiled."""

    def direction(H, C, s, z, r_d, r_p, r_c):
        n, m = H.shape[0], C.shape[0]
        C_pad = jnp.concatenate([C, jnp.zeros((m, n), C.dtype)], axis=1)
        dx, dsz = qp_ipm._newton_solver(H, C, C_pad, s, z, r_d, r_p, n)(r_c)
        return dx, dsz[:m], dsz[m:]

    return jax.jit(jax.vmap(direction))


# Bars ~10x the errors measured (the same with the solver before qpn46): float64 3e-10; float32
# 4.6e-6 at n = 6, 1.3e-2 at n = 12 (11 active rows: the kept system's float32 conditioning).
@pytest.mark.parametrize("n, m, bar32", [(6, 38, 5e-5), (12, 38, 0.1)])
def test_newton_direction_matches_dense_float64_solve(n, m, bar32):
    rng = np.random.default_rng(46 + n)
    states = [interior_point_state(rng, n, m) for _ in range(16)]
    keys = ("H", "C", "s", "z", "r_d", "r_p", "r_c")
    batch = {k: np.stack([st[k] for st in states]) for k in keys}
    refs = [dense_newton(*(st[k] for k in keys)) for st in states]
    for dtype, bar in ((jnp.float64, 3e-9), (jnp.float32, bar32)):
        got = newton_direction()(*(jnp.asarray(batch[k], dtype) for k in keys))
        for part, name in enumerate(("dx", "ds", "dz")):
            ref = np.stack([r[part] for r in refs])
            err = np.max(np.abs(np.asarray(got[part], np.float64) - ref), axis=1) / np.max(np.abs(ref), axis=1)
            assert np.max(err) < bar, (dtype.__name__, name, float(np.max(err)))


def test_max_step_is_nan_for_a_non_finite_direction():
    v = jnp.array([1.0, 2.0, 4.0])
    assert float(qp_ipm._max_step(v, jnp.array([-2.0, 1.0, -1.0]))) == 0.5
    assert float(qp_ipm._max_step(v, jnp.array([1.0, 1.0, 1.0]))) == 1.0
    for bad in (jnp.nan, jnp.inf, -jnp.inf):
        assert np.isnan(float(qp_ipm._max_step(v, jnp.array([-2.0, bad, 1.0])))), bad
