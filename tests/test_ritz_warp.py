"""The postural projector's Ritz decomposition as one Warp kernel (wbc_jax/control/ritz_warp.py, issue 46) against
float64 NumPy and the JAX decomposition it replaces: the basis, A Q and the Ritz pairs, a basis with a zero or a
dependent column, the certified projector and the whole torque law with either engine, its derivative, and the
settings refused. The kernel runs on Warp's CPU backend where warp-lang is installed (the `cuda` extra)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import moving_terms

from wbc_jax.control import torques
from wbc_jax.control.controller import ControllerConfig
from wbc_jax.robot.model import load_robot
from wbc_jax.sim import physics

BATCH = 6


@pytest.fixture(scope="module")
def ritz_warp():
    """The kernel's decomposition; the test skipped (before any fixture is built) without warp-lang."""
    pytest.importorskip("warp", reason="the Warp engine needs warp-lang (pip install 'wbc_jax[cuda]')")
    return torques.ritz_decomposer("warp")


@pytest.fixture(scope="module")
def standing():
    """(robot, DynamicsTerms (float32) batched over BATCH moving states near the standing posture)."""
    robot = load_robot("icub")
    return robot, moving_terms(robot, BATCH)[0]


def _law(robot, t, ritz_engine, s_offset=0.05):
    """torque_terms of the two soles (D = 12 rows), the stable postural task."""
    idx = robot.index
    n = idx.nv - 6
    return torques.torque_terms(
        t,
        t.J_frames.reshape(-1, idx.nv),
        t.Jdot_nu_frames.reshape(-1),
        postural="stable",
        kp_postural=jnp.full(n, 10.0, t.M.dtype),
        kd_postural=jnp.full(n, 1.0, t.M.dtype),
        s_des=t.s + s_offset,
        ritz_engine=ritz_engine,
    )


@pytest.fixture(scope="module")
def problems(standing):
    """(A (B, 23, 23), threshold, S (B, 23, 12)): the projector's eigenproblems at the moving states (float32)."""
    robot, t = standing
    cfg = ControllerConfig()

    def one(t):
        tt = _law(robot, t, "jax")
        return torques.projector_problem(tt.Lambda, tt.Mbar, cfg.pinv_damping, cfg.pinv_tol, None)

    with jax.default_matmul_precision("highest"):
        A, threshold, S = jax.jit(jax.vmap(one))(t)
    return A, float(threshold[0]), S


def test_the_basis_and_the_ritz_pairs_are_float64s(ritz_warp, problems):
    """Q orthonormal and spanning A S, A Q, and the Ritz pairs of Q' A Q, against float64 NumPy on the robot's own
    eigenproblems (float32 data: within 1e-6 relative; computed in float64 in the kernel: measured 3e-9 to 8e-8 on
    Warp's CPU backend)."""
    A, _, S = problems
    B = jnp.einsum("bij,bjk->bik", A, S, precision="highest")
    Q, AQ, theta, W = (np.asarray(x, np.float64) for x in jax.jit(jax.vmap(ritz_warp))(A, B))
    A64, B64 = np.asarray(A, np.float64), np.asarray(B, np.float64)
    k = B.shape[-1]
    for b in range(BATCH):
        assert np.abs(Q[b].T @ Q[b] - np.eye(k)).max() < 1e-6
        # Q's span holds B's columns (B's own span is ill-determined: A's eigenvalues span 1e10, so cond(B) does too)
        assert np.abs(Q[b] @ (Q[b].T @ B64[b]) - B64[b]).max() <= 1e-6 * np.abs(B64[b]).max()
        np.testing.assert_allclose(AQ[b], A64[b] @ Q[b], atol=1e-6 * np.abs(A64[b]).max() * 23)
        T = Q[b].T @ A64[b] @ Q[b]
        ref = np.linalg.eigvalsh(T)
        np.testing.assert_allclose(theta[b], ref, atol=1e-6 * np.abs(ref).max())
        assert np.abs(W[b].T @ W[b] - np.eye(k)).max() < 1e-6
        np.testing.assert_allclose(T @ W[b], W[b] * theta[b], atol=1e-5 * np.abs(ref).max())
    assert np.ptp(theta) > 1e3 * np.abs(theta).min()  # eigenvalues far apart: a real test of the Jacobi sweeps


def test_a_zero_or_dependent_column_still_gives_an_orthonormal_basis_of_the_span(ritz_warp):
    """B with a zero column and a column equal to another (rank k - 2): Q orthonormal (as LAPACK's: the reflector
    of a zero column is the identity) and its span holds B's columns (float64: 1e-12)."""
    rng = np.random.default_rng(1)
    X = rng.normal(size=(9, 9))
    A = X @ X.T
    B = rng.normal(size=(9, 5))
    B[:, 1] = 0.0
    B[:, 3] = B[:, 0]
    Q, AQ, theta, W = (np.asarray(x) for x in ritz_warp(jnp.asarray(A), jnp.asarray(B)))
    assert np.abs(Q.T @ Q - np.eye(5)).max() < 1e-12
    assert np.abs(Q @ (Q.T @ B) - B).max() < 1e-12 * np.abs(B).max()
    np.testing.assert_allclose(theta, np.linalg.eigvalsh(Q.T @ A @ Q), atol=1e-12 * np.abs(A).max())


def test_the_projector_and_the_torque_law_are_the_same_with_either_engine(ritz_warp, standing, problems):
    """The certified Ritz projector (every environment certified by both) within 1e-5, and torque_terms' Sigma and
    tau_model within 1e-5 of their scale (measured on Warp's CPU backend: the projector 6.6e-7, tau_model 1.0e-7,
    Sigma equal: it does not involve the projector)."""
    A, threshold, S = problems
    P = {}
    for name in ("jax", "warp"):
        decompose = torques.ritz_decomposer(name)
        P[name], certified = jax.jit(jax.vmap(lambda A, S, d=decompose: torques.ritz_projector(A, threshold, S, d)))(
            A, S
        )
        assert bool(jnp.all(certified)), name
    assert float(jnp.max(jnp.abs(P["warp"] - P["jax"]))) < 1e-5
    robot, t = standing
    with jax.default_matmul_precision("highest"):
        ref, got = (jax.jit(jax.vmap(lambda t, e=e: _law(robot, t, e)))(t) for e in ("jax", "warp"))
    for field in ("Sigma", "tau_model"):
        a, b = getattr(got, field), getattr(ref, field)
        scale = float(jnp.max(jnp.abs(b)))
        assert float(jnp.max(jnp.abs(a - b))) <= 1e-5 * scale and scale > 0.5, field


def test_the_torque_laws_derivative_is_the_same_with_either_engine(ritz_warp, standing):
    """d tau_model / d s_des (forward mode, the postural reference's offset) with the Warp decomposition equals the
    JAX one's: the projector's derivative comes from the whole eigendecomposition either way (float32: 1e-4)."""
    robot, t = standing
    t0 = jax.tree.map(lambda a: a[0], t)

    def tau(offset, engine):
        return _law(robot, t0, engine, offset).tau_model

    with jax.default_matmul_precision("highest"):
        d = [
            jax.jit(lambda o, e=e: jax.jvp(lambda o: tau(o, e), (o,), (jnp.ones_like(o),))[1])(0.05)
            for e in ("jax", "warp")
        ]
    scale = float(jnp.max(jnp.abs(d[0])))
    assert scale > 1.0
    assert float(jnp.max(jnp.abs(d[1] - d[0]))) <= 1e-4 * scale


def test_an_unknown_engine_or_warp_without_warp_lang_is_refused_in_one_line(monkeypatch):
    with pytest.raises(ValueError, match=r"ritz_engine 'lapack'; valid: \['jax', 'warp'\]"):
        ControllerConfig(ritz_engine="lapack")
    from wbc_jax.sim import scenario

    monkeypatch.setattr(physics, "has_warp", lambda: False)
    with pytest.raises(ValueError, match="ritz_engine 'warp' .* needs warp-lang"):
        scenario.setup("stand", duration=0.02, controller=ControllerConfig(ritz_engine="warp"))
