"""The force QP's dual active-set engines (issue 46), each against quadprog (the Goldfarb-Idnani method in C) and the
interior point: the solution and the multipliers on random problems of the controller's shapes, dependent and
inactive rows, infeasible and non-finite problems, the implicit derivative, and the settings they refuse.
``warp_active_set`` (wbc_jax/control/qp_active_set_kernel.py) runs on Warp's CPU backend where warp-lang is installed
(the `cuda` extra; the `gpu` set runs it on the GPU); ``eiquadprog`` (wbc_jax/control/qp_eiquadprog.py) where its
library builds (the `eiquadprog` extra, in `dev`, and a C++ compiler)."""

import dataclasses
import functools
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

quadprog = pytest.importorskip("quadprog")

from wbc_jax.control import controller, qp, qp_eiquadprog, qp_ipm  # noqa: E402
from wbc_jax.sim import physics  # noqa: E402

FIELDS = [f.name for f in dataclasses.fields(qp_ipm.IPMResult)]


def _unavailable(engine: str) -> str | None:
    if engine == "warp_active_set":
        return None if physics.has_warp() else "the Warp engines need warp-lang (pip install 'wbc_jax[cuda]')"
    return qp_eiquadprog.available()


@pytest.fixture(params=qp.ACTIVE_SET_ENGINES)
def engine(request):
    reason = _unavailable(request.param)
    if reason is not None:
        pytest.skip(reason)
    return request.param


def _problems(batch, n=6, m=38, dtype=np.float64, seed=0):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(batch, n, n))
    H = A @ A.transpose(0, 2, 1) + 0.1 * np.eye(n)
    g = 10.0 * rng.normal(size=(batch, n))
    C = rng.normal(size=(batch, m, n))
    b = rng.uniform(0.1, 2.0, size=(batch, m))
    return [np.asarray(a, dtype) for a in (H, g, C, b)]


def _active_set(engine, H, g, C, b, *, tol, weight=None):
    def one(H, g, C, b, weight):
        if engine == "warp_active_set":
            from wbc_jax.control import qp_warp

            result = qp_warp.active_set_warp(H, g, C, b, tol, weight)
        else:
            result = qp_eiquadprog.active_set_eiquadprog(H, g, C, b, tol, weight)
        return tuple(getattr(result, name) for name in FIELDS)

    axes = (0, 0, 0, 0, None if weight is None else 0)
    out = jax.jit(jax.vmap(one, in_axes=axes))(*(jnp.asarray(a) for a in (H, g, C, b)), weight)
    return {name: np.asarray(v) for name, v in zip(FIELDS, out)}


def _quadprog(H, g, C, b):
    """quadprog's x and multipliers of min 1/2 x'Hx + g'x s.t. Cx <= b (its form: G x >= h with G = -C')."""
    x, _, _, _, lam, _ = quadprog.solve_qp(np.float64(H), -np.float64(g), -np.float64(C).T, -np.float64(b))
    return x, lam


def _relative(a, ref):
    return np.max(np.abs(a - ref)) / (1.0 + np.max(np.abs(ref)))


@pytest.mark.parametrize("dtype, bound", [(np.float64, 1e-11), (np.float32, 2e-6)])
@pytest.mark.parametrize("n", [6, 12])
def test_the_solution_and_multipliers_are_quadprogs(engine, dtype, bound, n):
    """Random problems of the equality QP's (6 x 38) and the soft QP's (12 x 38) shapes, 3-10 rows active: x and
    the multipliers within float64 rounding of quadprog's (measured 4e-14), or float32's rounding of the inputs
    and outputs (measured 4e-7; the interior point's float32 error is up to 9e-5, wbc_jax/control/qp.py)."""
    H, g, C, b = _problems(48, n=n, dtype=dtype, seed=n)
    got = _active_set(engine, H, g, C, b, tol=1e-11 if dtype == np.float64 else 2e-6)
    assert np.all(got["converged"]) and np.all(got["finite"])
    active = []
    for i in range(len(g)):
        x, lam = _quadprog(H[i], g[i], C[i], b[i])
        assert _relative(got["x"][i], x) < bound, i
        assert _relative(got["lam"][i], lam) < 10 * bound, i
        active.append(np.sum(lam > 0))
        # off the active set: no multiplier, a positive slack
        np.testing.assert_array_equal(got["lam"][i][lam == 0], 0.0)
        assert np.all(got["s"][i] > 0)
    assert 3 <= min(active) and max(active) <= n  # the problems exercise the active set
    assert np.max(got["kkt_residual"]) < 1e-12  # the float64 solve's own KKT residual, scaled


def test_dependent_rows_inactive_rows_and_row_weights(engine):
    """A row repeated, a row that is a multiple of another, and a problem whose unconstrained minimiser is feasible
    (no step): quadprog's solution; row weights change the scaling, not the solution."""
    H, g, C, b = _problems(8, seed=21)
    x0 = np.stack([np.linalg.solve(H[i], -g[i]) for i in range(8)])
    C[0, 1], b[0, 1] = C[0, 0], b[0, 0]  # the same row twice
    C[1, 2], b[1, 2] = 3.0 * C[1, 0], 3.0 * b[1, 0]  # a multiple of a row
    b[2] = C[2] @ x0[2] + 1.0  # no row active
    weight = np.random.default_rng(22).uniform(0.5, 3.0, size=(8, 38))
    for w in (None, weight):
        got = _active_set(engine, H, g, C, b, tol=1e-11, weight=w)
        assert np.all(got["converged"])
        for i in range(8):
            assert _relative(got["x"][i], _quadprog(H[i], g[i], C[i], b[i])[0]) < 1e-11, (i, w is None)
        assert got["iterations"][2] == 0
        np.testing.assert_allclose(got["x"][2], x0[2], rtol=1e-12)


def test_an_infeasible_or_non_finite_problem_is_flagged_and_falls_back_as_the_interior_points(engine):
    """x_0 <= -1 and -x_0 <= -1 cannot both hold: not converged, and solve_qp falls back to the unconstrained
    minimiser as with the interior point; NaN data: not finite, x NaN. The batch's other problems are untouched."""
    H, g, C, b = _problems(6, seed=23)
    C[1, :2] = 0.0
    C[1, 0, 0], C[1, 1, 0], b[1, 0], b[1, 1] = 1.0, -1.0, -1.0, -1.0
    g[4, 0] = np.nan
    got = _active_set(engine, H, g, C, b, tol=1e-11)
    assert not got["converged"][1] and got["finite"][1]
    assert not got["finite"][4] and not got["converged"][4] and np.all(np.isnan(got["x"][4]))
    for i in (0, 2, 3, 5):
        assert got["converged"][i] and _relative(got["x"][i], _quadprog(H[i], g[i], C[i], b[i])[0]) < 1e-11

    def solve(engine):
        return jax.vmap(lambda H, g, C, b: qp.solve_qp(H, g, C, b, engine=engine))(H, g, C, b)

    (x_as, info_as), (x_ipm, info_ipm) = solve(engine), solve("jax")
    np.testing.assert_array_equal(info_as.infeasible, info_ipm.infeasible)
    assert info_as.infeasible[1] and info_as.infeasible[4]
    np.testing.assert_allclose(x_as[1], x_ipm[1], rtol=1e-12)  # the same fallback point


FALLING_ROBOT = Path(__file__).with_name("qp_falling_robot.npz")
"""Eleven equality QPs (6 x 38, float32) of robots falling after a 300-400 N push, captured from the controller in
`wbc-jax push-sweep --horizon 3 --push-onset 0.5 --push-duration 0.1 --magnitudes 300 400 2 --directions 4 --backend
jax --qp-engine warp_active_set`: infeasible, with rows that float32 rounding alone keeps independent."""


def _falling_robot():
    data = np.load(FALLING_ROBOT)
    return [data[k] for k in "HgCb"]


def test_a_falling_robots_infeasible_problems_are_flagged_in_few_steps(engine):
    """quadprog finds each inconsistent; the engine flags each not converged (solve_qp falls back), finite, within
    STEP_LIMIT_PER_ROW's bound. The Warp kernel took up to 114 steps here and wrote past its n-row arrays before
    qp_active_set_kernel.DEPENDENT_ROW (an illegal address on the GPU: results/gpu_h100/s61)."""
    H, g, C, b = _falling_robot()
    for i in range(len(g)):
        with pytest.raises(ValueError, match="inconsistent"):
            _quadprog(H[i], g[i], C[i], b[i])
    got = _active_set(engine, H, g, C, b, tol=2e-6)
    assert np.all(got["finite"]) and not np.any(got["converged"])
    assert np.max(got["iterations"]) <= 30  # measured: at most 22 (warp_active_set), 7 (eiquadprog); the limit 114


def test_the_warp_kernel_stays_inside_its_arrays_under_warps_bounds_checks():
    """The kernel built in Warp's debug mode (every vector and matrix index checked, a failed check aborts) on the
    falling robot's problems: the active set never exceeds n rows. A child process, as the abort would end pytest's."""
    if _unavailable("warp_active_set"):
        pytest.skip(_unavailable("warp_active_set"))
    import warp as wp

    if not wp.is_cpu_available():  # the GPU machines' warp-lang travels without its CPU compiler
        pytest.skip("Warp's CPU backend (its LLVM compiler) is not installed")
    code = f"""
import warp as wp
wp.config.mode = "debug"
import jax, numpy as np
from wbc_jax.control import qp_warp
d = np.load({str(FALLING_ROBOT)!r})
solve = jax.vmap(lambda H, g, C, b: qp_warp.active_set_warp(H, g, C, b, 2e-6).iterations)
print("steps", np.asarray(jax.jit(solve)(d["H"], d["g"], d["C"], d["b"])).tolist())
"""
    env = dict(os.environ, JAX_PLATFORMS="cpu", WARP_CACHE_PATH=str(Path(tempfile.mkdtemp()) / "warp"))
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600, env=env)
    out = run.stdout + run.stderr
    assert run.returncode == 0 and "out of bounds" not in out, out[-2000:]
    assert "steps" in run.stdout


def test_solve_qp_differentiates_the_active_set_solution_as_the_interior_points(engine):
    """The kernel is never differentiated; solve_qp's implicit derivative at its (exact) solution is the interior
    point's, at float64's interior-point tolerance (1e-11): reverse and forward mode within 1e-6 relative."""
    H, g, C, b = (jnp.asarray(a) for a in _problems(4, seed=24))

    def loss(g, engine):
        x, _ = jax.vmap(lambda H, g, C, b: qp.solve_qp(H, g, C, b, engine=engine))(H, g, C, b)
        return jnp.sum(x**2)

    grads = {e: jax.jit(jax.grad(loss), static_argnums=1)(g, e) for e in ("jax", engine)}
    assert np.max(np.abs(grads["jax"])) > 1e-3
    np.testing.assert_allclose(grads[engine], grads["jax"], rtol=1e-6, atol=1e-9)
    tangents = {e: jax.jvp(functools.partial(loss, engine=e), (g,), (jnp.ones_like(g),))[1] for e in ("jax", engine)}
    np.testing.assert_allclose(tangents[engine], tangents["jax"], rtol=1e-6)


@pytest.mark.parametrize("name", qp.ACTIVE_SET_ENGINES)
def test_a_warm_start_or_unrolled_steps_with_an_active_set_engine_are_refused_in_one_line(name):
    H, g, C, b = (jnp.asarray(a[0]) for a in _problems(1, seed=25))
    with pytest.raises(ValueError, match="takes no start"):
        qp.solve_qp(H, g, C, b, engine=name, start=jnp.ones((2, 38)))
    with pytest.raises(ValueError, match="takes unrolled 0"):
        qp.solve_qp(H, g, C, b, engine=name, unrolled=2)
    with pytest.raises(ValueError, match="qp_warm_start False"):
        controller.ControllerConfig(qp_engine=name, qp_warm_start=True)
    with pytest.raises(ValueError, match="qp_unrolled_steps 0"):
        controller.ControllerConfig(qp_engine=name, qp_unrolled_steps=3)


@pytest.mark.gpu
def test_on_the_gpu_the_solution_is_quadprogs():
    """The kernel as CUDA code (NVRTC), float32 data as the controller's: quadprog's solution to float32 rounding."""
    assert jax.devices()[0].platform == "gpu"
    if _unavailable("warp_active_set"):
        pytest.skip(_unavailable("warp_active_set"))
    H, g, C, b = _problems(256, dtype=np.float32, seed=26)
    got = _active_set("warp_active_set", H, g, C, b, tol=2e-6)
    assert np.all(got["converged"])
    for i in range(256):
        assert _relative(got["x"][i], _quadprog(H[i], g[i], C[i], b[i])[0]) < 2e-6, i
