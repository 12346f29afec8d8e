"""``wbc-jax limit``: the feedforward torques of the tick, the bracket of the bisection rounds, bad
input named before anything compiles, the C MuJoCo replay check, and (slow) the optimiser
recovering a push that the controller alone cannot."""

import dataclasses
import json
import re
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from wbc_jax import cli
from wbc_jax.control.controller import ControllerConfig
from wbc_jax.core import constants
from wbc_jax.jobs import limit, limit_rounds, trajopt
from wbc_jax.sim import host_loop, native, physics, runner, scenario
from wbc_jax.sim.state import Feedforward, SimConfig, feedforward_torque


def test_feedforward_torque_adds_in_its_window_and_saturates():
    tau = jnp.array([10.0, -50.0, 59.0])
    ff = Feedforward(start=jnp.asarray(5, jnp.int32), torque=jnp.array([[1.0, -20.0, 5.0], [2.0, 0.0, 0.0]]))
    np.testing.assert_array_equal(feedforward_torque(ff, 4, tau, 60.0), tau)  # before the window
    np.testing.assert_array_equal(feedforward_torque(ff, 5, tau, 60.0), [11.0, -60.0, 60.0])  # saturated
    np.testing.assert_array_equal(feedforward_torque(ff, 6, tau, 60.0), [12.0, -50.0, 59.0])
    np.testing.assert_array_equal(feedforward_torque(ff, 7, tau, 60.0), tau)  # after it
    np.testing.assert_array_equal(feedforward_torque(None, 5, tau, 60.0), tau)
    # The gradient reaches u inside the window, not where the saturation holds the torque.
    g = jax.grad(lambda u: jnp.sum(feedforward_torque(ff.replace(torque=u), 5, tau, 60.0)))(ff.torque)
    np.testing.assert_array_equal(g, [[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])


def test_feedforward_runs_on_either_host_loop(monkeypatch):
    """Feedforward torques run on the compiled C MuJoCo loop ('auto' where the native step builds: the limit
    job's replays, ``replayed`` below) and on the Python loop ('python', or where it cannot build)."""
    auto, python = (SimpleNamespace(cfg=SimpleNamespace(host_loop=c)) for c in ("auto", "python"))
    built = native.available() is None
    assert host_loop.driver(auto) == ("compiled" if built else "python")
    assert host_loop.driver(python) == "python"
    monkeypatch.setattr(native, "available", lambda: "no C++ compiler found")
    assert host_loop.driver(auto) == "python"


# Two loops of a batch with feedforward torques compile here (about a minute on the 2-core machine): nightly.
@pytest.mark.slow
def test_feedforward_gives_the_same_metrics_on_both_host_loops():
    """45 N m more on the left hip roll for 0.1 s from 0.2 s, and none, in one batch: the compiled loop's metrics
    equal the Python loop's to float noise (two code paths; the controller's terms from C MuJoCo and from XLA),
    and the torque changed them."""
    if native.available() is not None:
        pytest.skip(f"native step: {native.available()}")
    metrics = {}
    for driver in ("compiled", "python"):
        st = scenario.setup(
            "stand",
            duration=0.5,
            sim=SimConfig(record=False, host_loop=driver, physics=physics.PhysicsConfig(backend="mujoco")),
            controller=ControllerConfig(forces="analytic"),
        )
        scen = jax.tree_util.tree_map(lambda x: np.concatenate([np.asarray(x)] * 2), scenario.single(st, None))
        torque = np.zeros((2, 10, st.robot.index.n))
        torque[1, :, st.robot.index.joints.index("l_hip_roll")] = 45.0
        ff = Feedforward(start=np.full(2, 20, np.int32), torque=torque)
        metrics[driver] = runner.run(st, scen, feedforward=ff).metrics
    for name, value in vars(metrics["python"]).items():
        # Measured up to 1.1e-9 relative between the two loops on x86 CPUs (issue 41's bars, tests/test_rollout.py).
        np.testing.assert_allclose(
            np.asarray(getattr(metrics["compiled"], name), float), np.asarray(value, float), rtol=1e-7, atol=3e-9
        )
    assert float(metrics["compiled"].max_slip[1]) > 10 * float(metrics["compiled"].max_slip[0])


def test_bracket_and_next_impulses():
    # Round 1: from the lower start to the upper end; nothing failed above 6: above the tested span.
    np.testing.assert_allclose(limit.next_impulses([], 4, 3.0, 9.0), [3.0, 5.0, 7.0, 9.0])
    tested = [(3.0, True), (5.0, True), (7.0, False), (9.0, False)]
    assert limit.bracket(tested) == (5.0, 7.0)
    np.testing.assert_allclose(limit.next_impulses(tested, 3, 3.0, 9.0), [5.5, 6.0, 6.5])
    # A verified impulse above a failed one moves the bracket up: the limit is a lower bound.
    assert limit.bracket([(3.0, False), (5.0, True), (7.0, False)]) == (5.0, 7.0)
    assert limit.bracket([(3.0, False)]) == (0.0, 3.0)
    at_cap = [(3.0, True), (9.0, True)]
    assert limit.bracket(at_cap) == (9.0, np.inf)
    np.testing.assert_allclose(limit.next_impulses(at_cap, 2, 3.0, 9.0), [12.0, 15.0])


def test_knots_interpolate_linearly():
    W = trajopt.knot_matrix(30, 5)
    assert W.shape == (30, 7)
    np.testing.assert_allclose(W.sum(1), 1.0)
    z = np.arange(7.0)[:, None] * [1.0, -2.0]  # a linear u is reproduced at every tick
    np.testing.assert_allclose(W @ z, np.arange(30)[:, None] / 5 * [1.0, -2.0])
    np.testing.assert_array_equal(trajopt.knot_matrix(4, 1), np.eye(4))


def test_warm_starts_take_the_next_lower_verified_trajectory():
    u3, u5 = np.full((2, 1), 3.0), np.full((2, 1), 5.0)
    tested = [[(3.0, u3), (5.0, u5)], []]
    out = trajopt.warm_starts(tested, [(0, 4.0), (0, 6.0), (0, 2.0), (1, 6.0)], 2, 1)
    np.testing.assert_array_equal(out[:, 0, 0], [3.0, 5.0, 0.0, 0.0])


@pytest.fixture
def tripwire(monkeypatch):
    """Any jax.jit after this point means the input check came too late."""

    def late(*args, **kwargs):
        raise AssertionError("late failure: the bad input reached jax.jit (compilation)")

    monkeypatch.setattr(jax, "jit", late)


def _envelope_file(tmp_path, body="chest", azimuths=(0.0, 90.0, 180.0, 270.0)):
    path = tmp_path / f"env_{body}" / "summary.json"
    path.parent.mkdir()
    env = {str(a): {"impulse_ns": 4.0} for a in azimuths}
    config = {"body": body, "push_duration": 0.1, "push_onset": 0.5, "elevation": 0.0}
    path.write_text(json.dumps({"envelope": {"0": env}, "config": config}))
    return str(path)


BAD = [
    (["--lower-fraction", "-0.5"], r"--lower-fraction must be a number in \(0, 10\], got -0.5"),
    (["--lower-fraction", "0"], r"--lower-fraction must be a number in \(0, 10\], got 0"),
    (["--upper-fraction", "0.2"], r"--upper-fraction 0.2 must exceed --lower-fraction 0.3"),
    (["--body", "nose"], r"--body 'nose' is not a valid name here; valid: \[.*'chest'"),
    (["--window", "3"], r"--horizon 3 s must end after the push and the optimised window"),
    (["--candidates", "0"], r"--candidates must be a whole number in \[1, 64\], got 0"),
    (["--slip-margin", "0.03"], r"--slip-margin must be a number in \(0, 0.02\) m, got 0.03"),
    (["--learning-rate", "nan"], r"--learning-rate must be a number in \(0, 10000\] N m, got nan"),
    (["--es-sigma", "100"], r"--es-sigma 100 N m exceeds the largest motor limit of robot 'icub' \(60 N m\)"),
    (["--robot", "talos", "--learning-rate", "400"], r"--learning-rate 400 N m exceeds .* 'talos' \(300 N m\)"),
    (["--time-limit", "-1"], r"--time-limit must be a number in \[0, 10,000,000\] s, got -1"),
    (["--envelopes", "ENV_ROOT"], r"its pushes have body 'root_link', the search 'chest'"),
    (["--envelopes", "ENV_FEW"], r"no envelope at azimuths \[90.0, 270.0\]"),
    (["--gains", "MISSING"], r"--gains file .* does not exist"),
]


@pytest.mark.parametrize("k", range(len(BAD)))
def test_bad_input_fails_before_compiling(k, tmp_path, capsys, tripwire):
    flags, message = BAD[k]
    files = {
        "ENV_ROOT": _envelope_file(tmp_path, "root_link"),
        "ENV_FEW": _envelope_file(tmp_path, "chest", (0.0, 180.0)),
        "MISSING": str(tmp_path / "none.json"),
    }
    flags = [files.get(f, f) for f in flags]
    rc = cli.main(["limit", *flags, "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert rc == 2 and "Traceback" not in err and re.search(message, err), err
    assert len([line for line in err.splitlines() if line.strip()]) == 1, err
    assert not (tmp_path / "out").exists(), "nothing is written for bad input"


def test_torque_flags_and_the_effort_scale_come_from_the_robots_motors(tmp_path):
    """Issue 47: Talos's motors reach 300 N m: a spread of 100 N m is valid there (the iCub's 60 N m
    refuses it, above), and the optimiser's effort divides each joint's u by its own motor limit."""
    dataclasses.replace(limit.LimitConfig(), robot="talos", es_sigma=100.0, out=str(tmp_path / "out")).check()
    T, limits = 5, np.array([17.86, 100.0, 300.0])
    trace = SimpleNamespace(
        com=np.tile([0.0, 0.0, 0.9], (T, 1)),
        com_vel=np.zeros((T, 3)),
        support_xy=np.tile([[x, y] for y in (-0.1, 0.1) for x in (-0.1, 0.1)] * 2, (T, 1, 1)),
        foot_normal=np.tile([[0.0, 0.0, 1.0]] * 2, (T, 1, 1)),
        com_height0=np.full(T, 0.9),
    )
    effort = jax.jit(lambda u, lim: trajopt.terms(trace, u, T, trajopt.Cost(), lim)["effort"])  # one compile
    assert float(effort(jnp.full((T, 3), 50.0), jnp.asarray(limits))) == pytest.approx(
        np.mean((50.0 / limits) ** 2), rel=1e-9
    )  # 60 N m on every joint: 0.694


def test_flags_are_the_config_fields(capsys):
    with pytest.raises(SystemExit):
        cli.main(["limit", "--help"])
    text = capsys.readouterr().out
    for field in limit.LimitConfig.__dataclass_fields__:
        assert f"--{field.replace('_', '-')}" in text, field
    args = cli.build_parser().parse_args(["limit", "--directions", "32", "--envelopes", "a.json", "b.json"])
    cfg = cli.config_from_args(args, limit.default_config())
    assert len(cfg.directions) == 32 and cfg.envelopes == ("a.json", "b.json")


# A push of 1 N s forward, horizon 1.5 s; u adds 45 N m to the left hip roll for 0.1 s from the onset.
SMALL = limit.LimitConfig(directions=(0.0,), horizon=1.5, window=0.3, tail=0.1, out=None)


@pytest.fixture(scope="module")
def replayed():
    """Two policies of a forward push of 1 N s and their C MuJoCo replay: (search, scenarios, knots,
    strict columns): the controller's own (u = 0), and 45 N m more on the left hip roll for 0.1 s
    (then down to 0 in 0.05 s). The batch is padded to 4, the shape the round's replay of 2
    candidates compiles."""
    search = limit_rounds.Search(SMALL)
    scen = search.scenarios(np.zeros(2, int), np.array([1.0, 1.0]))
    z = np.zeros((2, search.Kn, search.n))
    z[1, :3, search.grad_setup.robot.index.joints.index("l_hip_roll")] = 45.0
    cols = search.judge(runner.pad_batch(scen, 4), runner.pad_batch(z, 4), "mujoco")
    return search, scen, z, {k: v[:2] for k, v in cols.items()}


def test_replay_rejects_a_trajectory_that_slips(replayed):
    """The controller's own policy passes the strict criterion in the C MuJoCo replay; the hip roll
    drags the left sole over 2 cm and is rejected."""
    *_, cols = replayed
    assert cols["survived"][0] and cols["failed"][0] == [], cols["failed"]
    assert not cols["survived"][1] and "slip" in cols["failed"][1], cols["failed"]
    assert cols["max_foot_slip_m"][1] > constants.SURVIVAL_MAX_SLIP_M > cols["max_foot_slip_m"][0]
    assert np.all(cols["max_abs_torque_nm"] <= 60.0 + 1e-9)


def test_a_candidate_is_verified_by_its_first_passing_replay(replayed):
    """The round's replay: candidate 0 passed on MJX with the slipping knots, so C MuJoCo replays
    those alone and rejects them; candidate 1 never passed on MJX: its last knots (slipping) fail
    in C MuJoCo, its warm start (the controller's own trajectory) passes and is kept."""
    search, scen, z, _ = replayed
    slip, zero = np.stack([z[1], z[1]]), np.stack([z[0], z[0]])
    passed = np.array([True, False])
    out, kept = search._replay(scen, [slip, slip, zero], [passed, ~passed, ~passed])
    assert list(out["survived"]) == [False, True] and list(out["replayed"]) == [-1, 2], out
    assert "slip" in out["replay_failed"][0] and out["replay_failed"][1] == [], out["replay_failed"]
    assert out["replay_max_foot_slip_m"][0] > constants.SURVIVAL_MAX_SLIP_M > out["replay_max_foot_slip_m"][1]
    np.testing.assert_array_equal(kept, [z[1], z[0]])


@pytest.mark.slow
def test_mjx_judges_the_replayed_policies_alike(replayed):
    """The same policies on MJX (the feedforward threaded through runner.run's per-device program):
    the same verdicts, the slips as C MuJoCo's (float64)."""
    search, scen, z, cols = replayed
    mjx = {k: v[:2] for k, v in search.judge(scen, z, "jax").items()}
    assert list(mjx["survived"]) == list(cols["survived"]) and mjx["failed"] == cols["failed"], mjx["failed"]
    np.testing.assert_allclose(mjx["max_foot_slip_m"], cols["max_foot_slip_m"], atol=1e-3)


def test_es_gradient_points_uphill_and_sees_only_ranks():
    """On f(z) = |z - a|^2 the antithetic ES gradient correlates with the true one, 2 (z - a), and a
    monotone transform of f leaves it unchanged."""
    rng = np.random.default_rng(0)
    a, z = rng.normal(size=(3, 4)), np.zeros((3, 4))
    eps = jnp.asarray(rng.normal(size=(64, 3, 4)))
    samples = np.concatenate([z + 0.1 * eps, z - 0.1 * eps])
    f = jnp.asarray(np.sum((samples - a) ** 2, axis=(1, 2)))
    g = np.asarray(trajopt.es_gradient(f, eps, 0.1)).ravel()
    true = (2 * (z - a)).ravel()
    assert g @ true / np.linalg.norm(g) / np.linalg.norm(true) > 0.8
    np.testing.assert_array_equal(trajopt.es_gradient(jnp.log1p(f), eps, 0.1), g.reshape(3, 4))


@pytest.mark.slow
def test_optimiser_recovers_a_push_the_controller_cannot(tmp_path):
    """Forward push of 11 N s on the chest: the tuned controller alone tilts a sole past 5 deg
    (strict failure); the optimised torques around it pass the strict criterion on MJX and in the
    C MuJoCo replay. A rerun resumes (nothing to do), another config is refused."""
    cfg = limit.LimitConfig(
        directions=(0.0,),
        gains="experiments/gains/tuned_gradient.json",
        window=0.5,
        tail=0.3,
        candidates=1,
        rounds=1,
        iterations=60,
        judge_every=10,
        lower_fraction=0.5,
        upper_fraction=0.673,
        out=str(tmp_path / "lim"),
    )
    summary = limit_rounds.run(cfg, progress=False)
    (cand,) = summary["candidates"]
    assert abs(cand["impulse_ns"] - 11.0) < 0.05
    assert "tilt" in cand["warm_failed"], cand  # the controller alone
    assert cand["mjx_passed"] and cand["verified"] and cand["replay_failed"] == [], cand
    assert cand["replay_max_foot_tilt_deg"] <= constants.SURVIVAL_MAX_TILT_DEG
    assert cand["replay_max_foot_slip_m"] <= constants.SURVIVAL_MAX_SLIP_M
    row = summary["directions"][0.0]
    assert row["limit_ns"] == cand["impulse_ns"] and row["at_cap"]
    with np.load(tmp_path / "lim" / "witness.npz") as w:
        assert w["u"].shape == (1, 50, 23) and np.abs(w["u"]).max() > 1.0
    again = limit_rounds.run(cfg, progress=False)
    assert again["directions"][0.0]["limit_ns"] == row["limit_ns"] and again["optimiser_steps"] == 0
    with pytest.raises(ValueError, match="made with other inputs"):
        limit_rounds.run(dataclasses.replace(cfg, iterations=61), progress=False)
