"""The batch's slowest force QP (issue 46, qpmax46): on the benchmark loop's own post-push problems
(results/cpu_targets/qpmax46/slowest_qps.npz, written by benchmarks/qp_slowest.py) a warm start
takes the slowest from 14 Newton steps to 10, at the warm start's own tighter float32 tolerance
(``qp.WARM_START_TOL_FLOAT32``); the settings behind it are refused when bad, before anything compiles."""

import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import quadprog
from conftest import load_script, refused_in_one_line

from wbc_jax.control import controller, qp

ROOT = pathlib.Path(__file__).resolve().parent.parent
PROBLEMS = ROOT / "results" / "cpu_targets" / "qpmax46" / "slowest_qps.npz"


@pytest.fixture(scope="module")
def slowest():
    """The 16 slowest cold problems after the push (float32) and their tick before; quadprog's y*."""
    with np.load(PROBLEMS) as z:
        data = {k: z[k] for k in ("H", "g", "C", "b", "cold_newton_steps")}
    H, g, C, b = (data[k][:, 1].astype(np.float64) for k in "HgCb")
    y_ref = np.stack(
        [quadprog.solve_qp(0.5 * (h + h.T), -gg, -c.T, -bb, 0)[0] for h, gg, c, bb in zip(H, g, C, b, strict=True)]
    )
    return data, y_ref


@pytest.fixture(scope="module")
def cold_solves(slowest):
    """The cold solver (the default iterations, no step written out) on both recorded ticks: (ticks, solutions)."""
    data, _ = slowest
    solve_cold = jax.jit(jax.vmap(lambda H, g, C, b: qp.solve_qp(H, g, C, b)))
    tick = [tuple(jnp.asarray(data[k][:, i]) for k in "HgCb") for i in (0, 1)]
    return tick, [solve_cold(*t) for t in tick]


def test_warm_start_cuts_the_slowest_post_push_qp(slowest, cold_solves):
    data, y_ref = slowest
    solve = jax.jit(jax.vmap(lambda H, g, C, b, start: qp.solve_qp(H, g, C, b, start=start)))
    tick, ((_, before), (y_cold, cold)) = cold_solves  # the tick before: its solution the warm start
    y_warm, warm = solve(*tick[1], before.start)
    # The recorded problems are the batch's slowest: cold, the solver here takes what the script counted.
    np.testing.assert_array_equal(np.asarray(cold.iterations), data["cold_newton_steps"])
    # Measured (AMD EPYC): cold 11-14 Newton steps, warm 7-10.
    assert int(np.max(cold.iterations)) >= 13 and int(np.max(warm.iterations)) <= 10, (cold.iterations, warm.iterations)
    assert np.all(warm.converged) and not np.any(warm.infeasible)
    # The warm start stops at its own tolerance (5e-7 in float32; 1.7e-6 measured at the cold 2e-6).
    assert qp.default_tolerances(jnp.float32, warm_start=True)[0] == qp.WARM_START_TOL_FLOAT32 == 5e-7
    assert float(np.max(warm.kkt_residual)) <= qp.WARM_START_TOL_FLOAT32
    # Against quadprog (float64): measured 9.1e-6 warm, 3.5e-5 cold; the cold start's bar of 1e-4 holds both.
    scale = 1.0 + np.max(np.abs(y_ref), axis=1)
    for y in (y_warm, y_cold):
        assert np.max(np.max(np.abs(np.asarray(y, np.float64) - y_ref), axis=1) / scale) < 1e-4


def test_unrolled_newton_steps_give_the_loops_solutions_and_all_of_them_leave_no_while_loop(slowest, cold_solves):
    """``unrolled`` (ControllerConfig.qp_unrolled_steps): the first Newton steps written out before the while loop.
    A problem that converged within them takes none of the later ones, so the solutions, step counts and residuals
    are the loop's (11-14 steps here: 2 written out, the loop the rest); all of a budget written out, no while
    loop is left in the program (on a GPU each pass of one waits for its predicate on the host; its solutions: the
    slow sibling below)."""
    tick, (_, (y0, info0)) = cold_solves

    def solver(unrolled):
        return jax.vmap(lambda H, g, C, b: qp.solve_qp(H, g, C, b, unrolled=unrolled))

    assert np.all(info0.converged) and int(np.max(info0.iterations)) == 14
    y, info = jax.jit(solver(2))(*tick[1])
    np.testing.assert_array_equal(np.asarray(info.iterations), np.asarray(info0.iterations))
    np.testing.assert_allclose(np.asarray(y), np.asarray(y0), rtol=0, atol=1e-6 * float(np.max(np.abs(y0))))
    np.testing.assert_allclose(np.asarray(info.kkt_residual), np.asarray(info0.kkt_residual), rtol=1e-3, atol=1e-9)

    def loops(unrolled, iterations=6):
        fn = jax.vmap(lambda H, g, C, b: qp.solve_qp(H, g, C, b, iterations=iterations, unrolled=unrolled))
        return str(jax.make_jaxpr(fn)(*tick[1])).count("while[")

    assert loops(0) >= 1 and loops(2) == loops(0) and loops(6) == loops(0) - 1
    with pytest.raises(ValueError, match=r"unrolled must be an integer from 0 to iterations \(14\), got 15"):
        qp.solve_qp(*(a[0] for a in tick[1]), iterations=14, unrolled=15)


@pytest.mark.slow
def test_all_newton_steps_unrolled_give_the_loops_solutions(slowest):
    """The sibling above with every step of the budget written out (no while loop): 9 s of compiling."""
    data, _ = slowest
    tick = tuple(jnp.asarray(data[k][:, 1]) for k in "HgCb")
    solve = lambda u: jax.jit(jax.vmap(lambda H, g, C, b: qp.solve_qp(H, g, C, b, iterations=14, unrolled=u)))  # noqa: E731
    (y0, info0), (y, info) = solve(0)(*tick), solve(14)(*tick)
    np.testing.assert_array_equal(np.asarray(info.iterations), np.asarray(info0.iterations))
    np.testing.assert_allclose(np.asarray(y), np.asarray(y0), rtol=0, atol=1e-6 * float(np.max(np.abs(y0))))


def test_qp_tol_setting_reaches_the_force_qp_and_bad_values_are_refused():
    assert controller.ControllerConfig().force_settings.qp_tol is None  # the solver's default by precision
    assert controller.ControllerConfig(qp_tol=1e-6).force_settings.qp_tol == 1e-6
    for bad in (0.0, -1e-6, float("nan"), float("inf")):
        with pytest.raises(ValueError, match=r"qp_tol must be positive or None"):
            controller.ControllerConfig(qp_tol=bad)


def test_qp_engine_setting_reaches_the_force_qp_and_bad_values_are_refused():
    """``engine`` (ControllerConfig.qp_engine): "jax" or "warp"; the Warp kernel has no while loop to unroll, so
    "warp" with unrolled steps is refused (before Warp is imported)."""
    assert controller.ControllerConfig().force_settings.qp_engine == qp.resolve_engine("auto")
    assert controller.ControllerConfig(qp_engine="warp").force_settings.qp_engine == "warp"
    with pytest.raises(
        ValueError, match=r"qp_engine 'cuda'; valid: \['jax', 'warp', 'warp_active_set', 'eiquadprog'\]"
    ):
        controller.ControllerConfig(qp_engine="cuda")
    with pytest.raises(ValueError, match=r"qp_engine 'warp' takes qp_unrolled_steps 0 .*no while loop.*got 2"):
        controller.ControllerConfig(qp_engine="warp", qp_unrolled_steps=2)
    H, g, C, b = jnp.eye(2), jnp.ones(2), jnp.eye(2), jnp.ones(2)
    with pytest.raises(
        ValueError, match=r"unknown engine 'cuda'; valid: \['jax', 'warp', 'warp_active_set', 'eiquadprog'\]"
    ):
        qp.solve_qp(H, g, C, b, engine="cuda")
    with pytest.raises(ValueError, match=r"engine 'warp' takes unrolled 0 \(the Warp kernel has no while loop"):
        qp.solve_qp(H, g, C, b, engine="warp", unrolled=2)


@pytest.fixture(scope="module")
def qp_slowest():
    return load_script("benchmarks/qp_slowest.py")


@pytest.mark.parametrize(
    "argv, names",
    [
        (["--pairs", "1e-6:hot"], ("--pairs", "'cold'", "'warm'")),
        (["--pairs", "2:cold"], ("--pairs", "TOL", "(0, 1)")),
        (["--ticks", "50"], ("--ticks", "0..49")),
        (["--explain-tick", "60"], ("--explain-tick", "0..49")),
    ],
)
def test_qp_slowest_refuses_bad_flags_in_one_line(qp_slowest, capsys, argv, names):
    error = refused_in_one_line(qp_slowest.main, [*argv, "--out", "/nonexistent/never_written"], capsys)
    assert all(name in error for name in names), error


def test_the_warp_qp_without_warp_lang_is_refused_in_one_line_before_anything_compiles(monkeypatch, capsys, tmp_path):
    """``--qp-engine warp`` where warp-lang is not installed: the loop's set-up refuses it, naming what to install
    and the engine valid here, before the first program is traced (not from inside a compile)."""
    from wbc_jax import cli
    from wbc_jax.sim import physics

    monkeypatch.setattr(physics, "has_warp", lambda: False)
    argv = ["balance", "--task", "stand", "--duration", "0.1", "--qp-engine", "warp", "--out", str(tmp_path / "b")]
    assert cli.main(argv) == 2
    errors = [line for line in capsys.readouterr().err.splitlines() if "error:" in line]
    assert len(errors) == 1, errors
    line = errors[0]
    assert "qp_engine 'warp'" in line and "pip install 'wbc_jax[cuda]'" in line and "valid here: ['jax']" in line
    assert not (tmp_path / "b" / "metrics.json").exists()


def test_the_eiquadprog_qp_where_it_cannot_build_is_refused_in_one_line_before_anything_compiles(
    monkeypatch, capsys, tmp_path
):
    """``--qp-engine eiquadprog`` where its library cannot be built (no eiquadprog, no Eigen headers, no compiler):
    the loop's set-up refuses it with the reason and the engine valid here, before the first program is traced."""
    from wbc_jax import cli
    from wbc_jax.control import qp_eiquadprog

    reason = "the force QP's eiquadprog engine needs eiquadprog: pip install eiquadprog cmeel-eigen"
    monkeypatch.setattr(qp_eiquadprog, "available", lambda: reason)
    argv = [
        "balance",
        "--task",
        "stand",
        "--duration",
        "0.1",
        "--qp-engine",
        "eiquadprog",
        "--out",
        str(tmp_path / "b"),
    ]
    assert cli.main(argv) == 2
    errors = [line for line in capsys.readouterr().err.splitlines() if "error:" in line]
    assert len(errors) == 1, errors
    assert "qp_engine 'eiquadprog'" in errors[0] and reason in errors[0] and "valid here: ['jax']" in errors[0]
    assert not (tmp_path / "b" / "metrics.json").exists()


def test_the_auto_engine_is_eiquadprog_on_the_cpu_where_it_builds_else_the_interior_point(monkeypatch):
    """Issue 46 (s62): ``qp_engine`` ``auto`` (the default) resolves when the controller's config is made (and in
    jobs' fingerprints, :func:`wbc_jax.jobs.runs.fingerprint`), so that they record the engine that ran: eiquadprog in a CPU program where it builds, the interior
    point where it does not and with a warm start or unrolled steps (the active-set method takes neither); on a GPU
    the next test's."""
    from wbc_jax.control import qp_eiquadprog
    from wbc_jax.control.flags import ControllerFlags

    if jax.default_backend() != "cpu":
        assert qp.resolve_engine("auto") in ("warp_active_set", "jax")  # the next test's
        return
    builds = qp_eiquadprog.available() is None
    assert controller.ControllerConfig().qp_engine == ("eiquadprog" if builds else "jax")
    assert ControllerFlags().config().qp_engine == ("eiquadprog" if builds else "jax")
    assert controller.ControllerConfig(qp_warm_start=True).qp_engine == "jax"
    assert controller.ControllerConfig(qp_unrolled_steps=3).qp_engine == "jax"
    assert ControllerFlags(qp_warm_start=True).config().qp_engine == "jax"
    assert controller.ControllerConfig(qp_engine="jax").qp_engine == "jax"
    from wbc_jax.jobs import runs

    config = {"qp_engine": "auto", "qp_warm_start": False, "qp_unrolled_steps": 0}
    assert runs.fingerprint(config, [], "icub")["config"]["qp_engine"] == ("eiquadprog" if builds else "jax")
    warm = runs.fingerprint({**config, "qp_warm_start": True}, [], "icub")
    assert warm["config"]["qp_engine"] == "jax"
    monkeypatch.setattr(qp_eiquadprog, "available", lambda: "no C++ compiler")
    assert controller.ControllerConfig().qp_engine == "jax"


def test_the_auto_engines_on_a_gpu_are_the_warp_kernels_where_warp_lang_is_installed(monkeypatch):
    """Issue 46 (s63): on a GPU the ``auto`` QP is the active-set Warp kernel and the ``auto`` M solve the Warp tile
    kernel where warp-lang is installed (JAX's engines without it, and the interior point with a warm start or
    unrolled steps); on the CPU the M solve stays JAX's. ``warp_terms`` ``auto`` is the split on the warp backend
    with an unperturbed plant only, resolved by the loop."""
    from wbc_jax.control import torques, warp_launch
    from wbc_jax.sim import physics, scenario, warp_split
    from wbc_jax.sim.state import SimConfig

    if jax.default_backend() == "cpu":
        assert controller.ControllerConfig().mass_solve_engine == "jax"
    assert controller.ControllerConfig(mass_solve_engine="jax").mass_solve_engine == "jax"
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    for installed, engines in ((True, ("warp_active_set", "warp")), (False, ("jax", "jax"))):
        monkeypatch.setattr(warp_launch, "installed", lambda installed=installed: installed)
        assert (qp.resolve_engine("auto"), torques.resolve_mass_solve_engine("auto")) == engines
        c = controller.ControllerConfig()
        assert (c.qp_engine, c.mass_solve_engine) == engines
        assert controller.ControllerConfig(qp_warm_start=True).qp_engine == "jax"
        assert controller.ControllerConfig(qp_unrolled_steps=2).qp_engine == "jax"
    with pytest.raises(ValueError, match=r"mass_solve_engine 'cusolver'; valid: \['auto', 'jax', 'warp'\]"):
        controller.ControllerConfig(mass_solve_engine="cusolver")
    monkeypatch.undo()
    assert physics.PhysicsConfig().warp_terms == "auto"
    assert warp_split.resolve_terms("auto", "warp", perturbed=False) == "step1"
    assert warp_split.resolve_terms("auto", "warp", perturbed=True) == "jax"
    assert warp_split.resolve_terms("auto", "jax", perturbed=False) == "jax"
    assert warp_split.resolve_terms("jax", "warp", perturbed=False) == "jax"
    with pytest.raises(ValueError, match=r"unknown warp_terms 'mjx'; valid: \['auto', 'jax', 'step1'\]"):
        physics.PhysicsConfig(warp_terms="mjx")
    st = scenario.setup("stand", duration=0.02, sim=SimConfig(physics=physics.PhysicsConfig(backend="jax")))
    assert st.loop.warp_terms == "jax"
