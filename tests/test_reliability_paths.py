"""Issue 41, classes 9 and 10: several processes that never meet end in one line within a bound, and
the paths that varied the closed loop by subclassing (``tune --window-s``, held-out gain schedules)
run in the default suite.

Class 10's break was a signature: the drivers pass a feedforward the subclasses did not take, so it
showed only when a program was traced. Here the composed loops are traced through the real drivers
(``jax.eval_shape``: nothing is compiled), and (nightly, ``slow``) one control tick of the loop that ``tune
--window-s`` builds with a gain schedule is compiled once and compared number by number with the plain loop."""

import os
import pathlib
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import load_script

from wbc_jax.control.controller import ControllerConfig
from wbc_jax.core import processes
from wbc_jax.sim import host_loop, mjx_loop, physics, scenario
from wbc_jax.sim.state import Feedforward, SimConfig
from wbc_jax.tuning import config
from wbc_jax.tuning.algorithms import gradient, objectives
from wbc_jax.tuning.algorithms import loss as tuning_loss
from wbc_jax.tuning.algorithms import problem as tp
from wbc_jax.tuning.algorithms import schedule as gain_schedule
from wbc_jax.tuning.algorithms import windows as tw

distributed = load_script("experiments/checks/multihost_check.py")  # the multi-process test harness

ROOT = pathlib.Path(__file__).resolve().parent.parent

# ---------------------------------------------------------------------------------------------
# Class 9: a process whose peers never come


def _join(rank: int, port: int, timeout_s: float) -> subprocess.Popen:
    cmd = [
        sys.executable,
        "-m",
        "wbc_jax.cli",
        "--distributed",
        "--coordinator",
        f"localhost:{port}",
        "--num-processes",
        "2",
        "--process-id",
        str(rank),
        "--initialization-timeout",
        f"{timeout_s:g}",
        "info",
    ]
    env = {
        **os.environ,
        "JAX_PLATFORMS": "cpu",
        "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
    }
    return subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def test_processes_whose_peers_never_come_exit_within_the_timeout_naming_the_coordinator():
    """A worker whose coordinator never comes, and a coordinator whose worker never comes (two
    addresses: they do not meet): each exits 2 within the timeout plus start-up, with one line
    naming its coordinator's address (JAX alone waits 300 s and aborts with a C++ stack)."""
    timeout_s = 3.0
    ports = {rank: distributed.free_port() for rank in (0, 1)}
    t0 = time.perf_counter()
    procs = {rank: _join(rank, port, timeout_s) for rank, port in ports.items()}
    for rank, proc in procs.items():
        out, err = proc.communicate(timeout=120)
        seconds = time.perf_counter() - t0
        lines = [line for line in err.splitlines() if line.strip()]
        assert proc.returncode == processes.TIMEOUT_EXIT_CODE == 2, (rank, proc.returncode, err[-2000:])
        assert len(lines) == 1 and out == "", (rank, err[-2000:])
        assert f"process {rank} of 2:" in lines[0] and f"coordinator at localhost:{ports[rank]} within 3 s" in lines[0]
        # The bound: the timeout plus the interpreter's and JAX's start on a loaded 2-core machine.
        assert timeout_s <= seconds < timeout_s + 60, seconds


# ---------------------------------------------------------------------------------------------
# Class 10: the loops of tune --window-s and of held-out gain schedules, composed, not subclassed


@pytest.fixture(scope="module")
def window_problem():
    """The problem of ``wbc-jax tune --parameterisation scheduled --window-s 0.02 --windows 2`` at tiny size."""
    tc = config.TuneConfig(
        horizon=0.1,
        push_onset=0.0,
        duration_range=(0.02, 0.05),
        eval_horizon=0.1,
        batch=4,
        parameterisation="scheduled",
        window_s=0.02,
        windows=2,
        estimator="first-order",
        search_backend="jax",
    )
    return tp.make_problem(tc)


def _varying_schedule(problem):
    """The problem's schedule with weights 0.5: its gains vary with the base's motion."""
    params = problem.init_params()
    params = {**params, "weights": jax.tree_util.tree_map(lambda w: jnp.full_like(w, 0.5), params["weights"])}
    return tp.controls_cast(problem, params)[0]


@pytest.mark.slow  # tracing the closed loop's rollout takes a minute on the 2-core machine
def test_window_sampler_traces_through_the_driver(window_problem):
    """The forward program of a --window-s step, traced as tune builds it (a recording, scheduled,
    tuning loop under mjx_loop): R rollouts x K windows of starts. (The windows' gradients run in
    tests/test_race.py's slow end-to-end test.)"""
    problem = window_problem
    tc = problem.tc
    R, K, W = tc.distinct_rollouts // tc.windows, tc.windows, tw.window_ticks(problem)
    assert (R, K, W) == (2, 2, 2)
    params = problem.init_params()
    scen = objectives.cast_batch(gradient.training_batch(problem, 0)[0], problem.setup.dtype)
    ticks = tw.sample_starts(np.random.default_rng(0), R, K, problem.loop.n_ticks, W)
    assert ticks.shape == (R, K) and ticks.max() <= problem.loop.n_ticks - W
    starts, terms, metrics = tw.make_sampler(problem, R, K).eval_shape(params, scen, ticks)
    nq, nv = problem.robot.mj_model.nq, problem.robot.mj_model.nv
    assert starts.qpos.shape == (R * K, nq) and starts.qvel.shape == (R * K, nv) and starts.tick.shape == (R * K,)
    assert starts.normal0.shape == (R * K, 2, 3) and terms["total"].shape == (R,)
    assert jax.tree_util.tree_leaves(metrics)[0].shape == (R,)


@pytest.mark.slow  # as above; the default suite's sibling is the compiled tick below
def test_a_gain_schedule_traces_in_every_driver_with_a_feedforward(window_problem):
    """Held-out evaluation of a schedule file runs the scheduled loop on MJX (mjx_loop) and on C
    MuJoCo (host_loop's tick); both drivers pass a feedforward (wbc-jax limit's)."""
    problem = window_problem
    st = problem.setup
    loop = gain_schedule.scheduled_loop(st.loop)
    assert gain_schedule.scheduled_loop(loop) is loop and loop.structure_key != st.loop.structure_key
    sched = _varying_schedule(problem)
    qpos = jnp.asarray(st.qpos0, st.dtype)
    push = jax.tree_util.tree_map(lambda x: jnp.asarray(x)[0], gradient.training_batch(problem, 0)[0].push)
    ff = Feedforward(start=jnp.int32(1), torque=jnp.zeros((3, problem.robot.index.n), st.dtype))
    plant = physics.device_model(st.robot.mj_model, "jax", loop.cfg.physics)
    metrics, _ = jax.eval_shape(lambda s: mjx_loop.rollout(loop, plant, qpos, s, push, feedforward=ff), sched)
    assert metrics.ticks.shape == ()
    state = jax.eval_shape(loop.init, qpos)
    out = jax.eval_shape(
        lambda s, x: host_loop.control_host(
            loop, s, x, qpos, qpos[: loop.idx.nv], jnp.int32(0), jnp.ones((), bool), push, ff
        ),
        sched,
        state,
    )
    assert out[1].shape == (st.robot.mj_model.nu,)


# Its compile took 52-54 s of the 2-core suite: nightly (`slow`); the default suite keeps the tracing checks above.
@pytest.mark.slow
def test_the_window_loop_with_a_schedule_computes_the_plain_loops_tick(window_problem):
    """One tick, compiled once: the loop tune --window-s builds (schedule -> gains, TuneTrace, window
    start recorder; here on the analytic force distribution), given a feedforward, gives the plain tuning loop's torques and trace at the
    schedule's gains of the state (which differ from its gains at rest) plus the feedforward, and its
    record holds the state it started from."""
    problem = window_problem
    built = tw.recording_loop(problem.loop)  # as tune builds it
    assert built.gains_at is gain_schedule.gains_of_schedule
    assert built.recorders == (tuning_loss.tune_trace, tw.record_start)
    # The same composition on the analytic force distribution: it compiles in a fraction of the QP's time.
    sim = SimConfig(record=False)
    st = scenario.setup("stand", duration=0.1, sim=sim, controller=ControllerConfig(forces="analytic"))
    loop = tw.recording_loop(gain_schedule.scheduled_loop(tuning_loss.tuning_loop(st.loop)))
    assert (loop.gains_at, loop.recorders) == (built.gains_at, built.recorders)
    plain = tuning_loss.tuning_loop(st.loop)
    assert plain.gains_at is None and plain.recorders == (tuning_loss.tune_trace,)
    sched = _varying_schedule(problem)
    qpos = jnp.asarray(st.qpos0, st.dtype)
    qvel = jnp.zeros(st.robot.mj_model.nv, st.dtype).at[0].set(0.15)  # the base moves: the schedule's gains vary
    assert not np.allclose(sched.gains_at(qpos, qvel).kd_com, sched.at_rest().kd_com, rtol=1e-3)
    push = jax.tree_util.tree_map(lambda x: jnp.asarray(x)[0], gradient.training_batch(problem, 0)[0].push)
    n = problem.robot.index.n
    ff = Feedforward(start=jnp.int32(0), torque=jnp.zeros((2, n), st.dtype).at[0, 0].set(0.5))
    k, ok = jnp.int32(0), jnp.ones((), bool)

    @jax.jit
    def ticks(s):
        state = loop.init(qpos)
        composed = loop.control(s, state, qpos, qvel, k, ok, push, ff)
        direct = plain.control(s.gains_at(qpos, qvel), state, qpos, qvel, k, ok, push)
        return state, composed, direct

    state, (_, ctrl, (trace, (q0, v0, state0))), (_, ctrl_d, trace_d) = ticks(sched)
    assert isinstance(trace, tuning_loss.TuneTrace) and isinstance(trace_d, tuning_loss.TuneTrace)
    np.testing.assert_array_equal(q0, qpos)
    np.testing.assert_array_equal(v0, qvel)
    np.testing.assert_array_equal(state0.com0_height, state.com0_height)
    # The same torques but the feedforward's 0.5 N m on the first joint (unless saturated there).
    diff = np.asarray(ctrl - ctrl_d)[np.asarray(problem.robot.index.actuators)]
    assert abs(diff[0] - 0.5) < 1e-5 and np.allclose(diff[1:], 0.0, atol=1e-5), diff
    np.testing.assert_allclose(np.asarray(trace.base.tau - trace_d.base.tau), diff, atol=1e-5)
