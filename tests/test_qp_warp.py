"""The force QP's Warp engine (wbc_jax/control/qp_warp.py, issue 46) against the JAX interior point it transcribes:
the same Newton steps and the same iterate to rounding, on random problems of the controller's shape, weighted,
warm-started, under nested vmaps, and with non-finite data. Runs on Warp's CPU backend where warp-lang is
installed (the `cuda` extra); the `gpu` set runs it on the GPU."""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

pytest.importorskip("warp", reason="the Warp engine needs warp-lang (pip install 'wbc_jax[cuda]')")

from wbc_jax.control import qp_ipm, qp_warp

FIELDS = [f.name for f in dataclasses.fields(qp_ipm.IPMResult)]


def _as_tuple(result):
    return tuple(getattr(result, name) for name in FIELDS)


def _problems(batch, n=6, m=38, dtype=np.float32, seed=0):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(batch, n, n))
    H = A @ A.transpose(0, 2, 1) + 0.1 * np.eye(n)
    g = 10.0 * rng.normal(size=(batch, n))
    C = rng.normal(size=(batch, m, n))
    b = rng.uniform(0.1, 2.0, size=(batch, m))
    return [jnp.asarray(a, dtype) for a in (H, g, C, b)]


def _solve(engine, H, g, C, b, *, tol, weight=None, start=None, iterations=25):
    def one(H, g, C, b, weight, start):
        if engine == "jax":
            return _as_tuple(qp_ipm.interior_point(H, g, C, b, iterations, tol, weight, start))
        return _as_tuple(qp_warp.interior_point_warp(H, g, C, b, iterations, tol, weight, start))

    axes = (0, 0, 0, 0, None if weight is None else 0, None if start is None else 0)
    return dict(zip(FIELDS, jax.jit(jax.vmap(one, in_axes=axes))(H, g, C, b, weight, start)))


def _assert_same(warp, ref, atol):
    # Float32 rounding can leave the residual of a step on the other side of tol: one more (or one fewer) Newton
    # step in a few problems (1 of 64 in the first test, 1 of 32 in the second), to a point as close.
    steps = np.abs(np.asarray(warp["iterations"]) - np.asarray(ref["iterations"]))
    assert np.max(steps) <= 1 and np.mean(steps) <= 0.05, (warp["iterations"], ref["iterations"])
    np.testing.assert_array_equal(warp["converged"], ref["converged"])
    np.testing.assert_array_equal(warp["finite"], ref["finite"])
    for name in ("x", "lam", "s"):
        scale = np.max(np.abs(ref[name]), axis=-1, keepdims=True)
        np.testing.assert_allclose(warp[name], ref[name], rtol=0, atol=atol * (1 + np.max(scale)), err_msg=name)
    np.testing.assert_allclose(warp["kkt_residual"], ref["kkt_residual"], rtol=0, atol=10 * atol)


@pytest.mark.parametrize("dtype, tol, atol", [(np.float32, 2e-6, 1e-5), (np.float64, 1e-11, 1e-10)])
def test_the_same_newton_steps_and_solution_as_the_jax_interior_point(dtype, tol, atol):
    """At each precision's tol: the same Newton steps (6-11) and iterates within a few tol of each other."""
    H, g, C, b = _problems(64, dtype=dtype)
    ref, warp = _solve("jax", H, g, C, b, tol=tol), _solve("warp", H, g, C, b, tol=tol)
    assert np.all(ref["converged"]) and 6 <= np.min(ref["iterations"]) < np.max(ref["iterations"])
    _assert_same(warp, ref, atol)


def test_row_weights_and_a_warm_start_as_the_jax_interior_point():
    H, g, C, b = _problems(32, seed=1)
    weight = jnp.asarray(np.random.default_rng(2).uniform(0.5, 3.0, size=(32, 38)), jnp.float32)
    cold = _solve("jax", H, g, C, b, tol=5e-7, weight=weight)
    start = jnp.stack([cold["lam"], cold["s"]], axis=1) * 1.1  # a nearby problem's solution
    start = start.at[3].set(jnp.nan)  # one problem with a non-finite start: its cold start
    ref = _solve("jax", H, g, C, b, tol=5e-7, weight=weight, start=start)
    warp = _solve("warp", H, g, C, b, tol=5e-7, weight=weight, start=start)
    _assert_same(warp, ref, 1e-5)
    assert warp["iterations"][3] == cold["iterations"][3]
    assert np.mean(ref["iterations"]) < np.mean(cold["iterations"])  # the start is used


def test_nested_vmaps_give_one_launch_of_the_flat_batch():
    """vmap over gains of vmap over scenarios (the sweep's batch): the kernel sees the flattened batch, and each
    problem's result is its own (no leak between the batch's problems)."""
    H, g, C, b = _problems(12, seed=3)
    flat = _solve("warp", H, g, C, b, tol=2e-6)

    def one(H, g, C, b):
        return _as_tuple(qp_warp.interior_point_warp(H, g, C, b, 25, 2e-6))

    nested = jax.jit(jax.vmap(jax.vmap(one)))(*(a.reshape((3, 4) + a.shape[1:]) for a in (H, g, C, b)))
    for name, value in zip(FIELDS, nested):
        np.testing.assert_array_equal(np.asarray(value).reshape(flat[name].shape), flat[name], err_msg=name)
    shared_H = jax.jit(jax.vmap(one, in_axes=(None, 0, 0, 0)))(H[0], g, C, b)  # an unbatched argument broadcast
    np.testing.assert_array_equal(shared_H[0][0], flat["x"][0])


def test_a_non_finite_problem_is_flagged_and_does_not_touch_the_others():
    H, g, C, b = _problems(8, seed=4)
    g = g.at[2, 0].set(jnp.nan)
    C = C.at[5, 7, 1].set(jnp.inf)
    ref, warp = _solve("jax", H, g, C, b, tol=2e-6), _solve("warp", H, g, C, b, tol=2e-6)
    for name in ("finite", "converged", "iterations"):
        np.testing.assert_array_equal(warp[name], ref[name], err_msg=name)
    assert not warp["finite"][2] and not warp["converged"][5]
    ok = np.asarray([i not in (2, 5) for i in range(8)])
    assert np.all(warp["converged"][ok])
    np.testing.assert_allclose(warp["x"][ok], ref["x"][ok], rtol=0, atol=1e-5)


@pytest.mark.gpu
def test_on_the_gpu_the_same_newton_steps_and_solution_as_the_jax_interior_point():
    """The kernel as CUDA code (NVRTC), against the JAX engine on the same GPU, float32 at the controller's tol."""
    assert jax.devices()[0].platform == "gpu"
    H, g, C, b = _problems(256, seed=5)  # float32
    ref, warp = _solve("jax", H, g, C, b, tol=2e-6), _solve("warp", H, g, C, b, tol=2e-6)
    assert np.all(ref["converged"])
    _assert_same(warp, ref, 1e-5)


def test_solve_qp_differentiates_the_warp_engines_solution_as_the_jax_engines():
    """solve_qp(engine="warp"): the kernel is never differentiated (its inputs are stop_gradient data), and the
    implicit derivative at its solution is the JAX engine's: reverse and forward mode agree to float64 rounding."""
    from wbc_jax.control import qp

    H, g, C, b = _problems(4, dtype=np.float64, seed=6)

    def loss(g, engine):
        x, _ = jax.vmap(lambda H, g, C, b: qp.solve_qp(H, g, C, b, engine=engine))(H, g, C, b)
        return jnp.sum(x**2)

    grads = {e: jax.jit(jax.grad(loss), static_argnums=1)(g, e) for e in ("jax", "warp")}
    np.testing.assert_allclose(grads["warp"], grads["jax"], rtol=1e-9, atol=1e-12)
    assert np.max(np.abs(grads["jax"])) > 1e-3  # a gradient, not zeros
    tangents = {e: jax.jvp(functools.partial(loss, engine=e), (g,), (jnp.ones_like(g),))[1] for e in ("jax", "warp")}
    np.testing.assert_allclose(tangents["warp"], tangents["jax"], rtol=1e-9)
