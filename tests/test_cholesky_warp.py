"""The torque law's mass-matrix solve as one Warp tile kernel (wbc_jax/control/cholesky_warp.py, issue 46) against
float64 NumPy and the JAX solve it replaces: the factor and the solve on the robot's own M, the derivatives (the JAX
solve's), the whole torque law with either engine, and the settings refused without warp-lang. The kernel runs on
Warp's CPU backend where warp-lang is installed (the `cuda` extra); the `gpu` set runs it on the GPU."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import moving_terms

from wbc_jax.control.controller import ControllerConfig
from wbc_jax.core.math import cholesky_solve
from wbc_jax.robot.model import load_robot
from wbc_jax.sim import physics

BATCH = 6


@pytest.fixture(scope="module")
def standing():
    """(robot, DynamicsTerms batched over BATCH states near the standing posture, right-hand sides (B, 29, 36))."""
    robot = load_robot("icub")
    idx = robot.index
    t, rng = moving_terms(robot, BATCH)
    B = rng.normal(size=(BATCH, idx.nv, 12 + 1 + idx.nv - 6)).astype(np.float32)
    return robot, t, B


@pytest.fixture(scope="module")
def cholesky_solve_warp():
    """The kernel's solve; the test skipped (before `standing` is built) without warp-lang."""
    pytest.importorskip("warp", reason="the Warp engine needs warp-lang (pip install 'wbc_jax[cuda]')")
    from wbc_jax.control import cholesky_warp

    return cholesky_warp.cholesky_solve_warp


def test_the_factor_and_the_solve_are_float64s_to_float32_rounding(cholesky_solve_warp, standing):
    """On the robot's M (29 x 29) with 36 right-hand sides, both engines' L within 1e-6 of float64's largest entry
    and K^-1 B within cond(M) x 1e-6 (measured: L 3.5e-7, X 1e-5 against JAX's at cond 1e3-1e4 on Warp's CPU
    backend); float64 data: 1e-12."""
    _, t, B = standing
    M = np.asarray(t.M, np.float64)
    L_ref = np.linalg.cholesky(M)
    X_ref = np.linalg.solve(M, B.astype(np.float64))
    cond = max(np.linalg.cond(m) for m in M)
    for dtype, bound in ((np.float32, 1e-6), (np.float64, 1e-12)):
        for solve in (cholesky_solve, cholesky_solve_warp):
            L, X = jax.jit(jax.vmap(solve))(jnp.asarray(M, dtype), jnp.asarray(B, dtype))
            assert L.dtype == dtype
            assert np.max(np.abs(np.asarray(L) - L_ref)) <= bound * np.max(np.abs(L_ref)), (solve, dtype)
            assert np.max(np.abs(np.asarray(X) - X_ref)) <= cond * bound * np.max(np.abs(X_ref)), (solve, dtype)
    assert 10.0 < cond < 1e6  # a real inertia: the light links make it far from the identity


def test_its_derivatives_are_the_jax_solves(cholesky_solve_warp, standing):
    """Reverse and forward mode through the kernel equal those through the JAX solve (float64: to 1e-12)."""
    _, t, B = standing
    M, B = jnp.asarray(t.M, jnp.float64), jnp.asarray(B, jnp.float64)

    def loss(M, B, solve):
        L, X = jax.vmap(solve)(M, B)
        return jnp.sum(X**2) + jnp.sum(jnp.sin(L))

    grads = [
        jax.jit(jax.grad(loss, argnums=(0, 1)), static_argnums=2)(M, B, s)
        for s in (cholesky_solve, cholesky_solve_warp)
    ]
    for a, b in zip(*grads):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * float(jnp.max(jnp.abs(b))))
    assert float(jnp.max(jnp.abs(grads[0][0]))) > 1e-3
    tangent = jnp.ones_like(B)
    jvps = [jax.jvp(lambda B, s=s: loss(M, B, s), (B,), (tangent,))[1] for s in (cholesky_solve, cholesky_solve_warp)]
    np.testing.assert_allclose(jvps[1], jvps[0], rtol=1e-12)


def test_the_torque_law_is_the_same_with_either_engine(cholesky_solve_warp, standing):
    """torque_terms with mass_solve_engine 'warp' against 'jax' at six moving states (float32, the loop's
    precision): Sigma and tau_model within 5e-5 of their scale (measured on Warp's CPU backend: 7.8e-7 and 4.3e-6)."""
    from wbc_jax.control import torques

    robot, t, _ = standing
    t = jax.tree.map(lambda a: a.astype(jnp.float32) if jnp.issubdtype(a.dtype, jnp.floating) else a, t)
    idx = robot.index
    n = idx.nv - 6

    def law(t, engine):  # the two soles' frames (dynamics.terms' default): D = 12 rows
        J_c = t.J_frames.reshape(-1, idx.nv)
        Jdot = t.Jdot_nu_frames.reshape(-1)
        tt = torques.torque_terms(
            t,
            J_c,
            Jdot,
            postural="stable",
            kp_postural=jnp.full(n, 10.0, jnp.float32),
            kd_postural=jnp.full(n, 1.0, jnp.float32),
            s_des=t.s + 0.05,
            mass_solve_engine=engine,
        )
        return tt.Sigma, tt.tau_model

    with jax.default_matmul_precision("highest"):
        ref, got = (jax.jit(jax.vmap(lambda tt, e=e: law(tt, e)))(t) for e in ("jax", "warp"))
    for a, b in zip(got, ref):
        scale = float(jnp.max(jnp.abs(b)))
        assert float(jnp.max(jnp.abs(a - b))) <= 5e-5 * scale
        assert scale > 0.5


def test_an_unknown_engine_or_warp_without_warp_lang_is_refused_in_one_line(monkeypatch):
    with pytest.raises(ValueError, match=r"mass_solve_engine 'cusolver'; valid: \['auto', 'jax', 'warp'\]"):
        ControllerConfig(mass_solve_engine="cusolver")
    from wbc_jax.sim import scenario

    monkeypatch.setattr(physics, "has_warp", lambda: False)
    with pytest.raises(ValueError, match="mass_solve_engine 'warp' .* needs warp-lang"):
        scenario.setup("stand", duration=0.02, controller=ControllerConfig(mass_solve_engine="warp"))
