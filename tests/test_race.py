"""Issue 35's pieces without compiling the closed loop: the gradient estimators against known gradients,
the gain schedule (bounds, stability, files), the window loss, the race's verdict and files, the
campaign's gain files (two devices against one: tests/test_tune_devices.py). The closed-loop
runs of all of it (gradient, windows, searches, held-out, report) are the slow end-to-end test at the
end (`pytest -m slow`)."""

import json
import os
import pathlib
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from wbc_jax.control import gains as C
from wbc_jax.core import constants
from wbc_jax.core.constants import GAIN_FIELDS
from wbc_jax.robot.icub import DESCRIPTION as ICUB
from wbc_jax.tuning import store
from wbc_jax.tuning.algorithms import estimators
from wbc_jax.tuning.algorithms import loss as tuning_loss
from wbc_jax.tuning.algorithms import params as tuning_params
from wbc_jax.tuning.algorithms import schedule as gs
from wbc_jax.tuning.orchestration import race

ROOT = pathlib.Path(__file__).resolve().parent.parent


# ---------------------------------------------------------------------------------------------
# Estimators


def _quadratic():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(5, 5))
    A = A @ A.T / 5 + np.eye(5)
    b = rng.normal(size=5)
    theta = rng.normal(size=5)
    return (lambda x: 0.5 * x @ A @ x + b @ x), A @ theta + b, theta


def test_antithetic_pairs_and_zeroth_order_estimate_of_a_quadratic_gradient():
    """Antithetic differences of a quadratic are exact directional derivatives, so the zeroth-order
    estimate is unbiased with the sampling error of E[eps eps^T] = I alone: within 5 % at 20,000 pairs."""
    f, grad, theta = _quadratic()
    params = {"x": jnp.asarray(theta)}
    pb, eps = estimators.antithetic(params, jax.random.key(1), 20000, 0.1)
    # One product and one sum: measured bit-equal here and with XLA held to AVX2 (z: 6.1e-16 relative).
    np.testing.assert_allclose(pb["x"][0::2], theta + 0.1 * eps, rtol=1e-12)
    np.testing.assert_allclose(pb["x"][1::2], theta - 0.1 * eps, rtol=1e-12)
    values = jax.vmap(f)(pb["x"])
    z, ok = estimators.zeroth_order_rows(values, eps, 0.1)
    assert bool(jnp.all(ok))
    np.testing.assert_allclose(z[0], (grad @ eps[0]) * eps[0], rtol=1e-8)  # one pair, exactly
    assert np.linalg.norm(np.asarray(z.mean(0)) - grad) < 0.05 * np.linalg.norm(grad)
    # A non-finite value drops its pair only.
    values = values.at[3].set(jnp.nan)
    z, ok = estimators.zeroth_order_rows(values, eps, 0.1)
    assert int(jnp.sum(~ok)) == 1 and not bool(ok[1]) and bool(jnp.all(jnp.isfinite(z)))


def test_interpolation_weights_by_variance_and_falls_back_on_bias():
    """alpha = var_ZO / (var_FO + var_ZO) of the means; where the first-order mean is biased beyond
    bias_factor standard errors, alpha is cut so that the mix lies within that bound of the
    zeroth-order mean."""
    rng = np.random.default_rng(2)
    g = np.array([1.0, -2.0, 0.5])
    fo = g + 0.01 * rng.normal(size=(64, 3))
    zo = g + 1.0 * rng.normal(size=(32, 3))
    ok_fo, ok_zo = np.ones(64, bool), np.ones(32, bool)
    mix, st = estimators.interpolate(jnp.asarray(fo), jnp.asarray(ok_fo), jnp.asarray(zo), jnp.asarray(ok_zo), 2.0)
    v1 = np.sum(fo.var(0, ddof=1)) / 64
    v0 = np.sum(zo.var(0, ddof=1)) / 32
    assert float(st["fo_var"]) == pytest.approx(v1, rel=1e-6) and float(st["zo_var"]) == pytest.approx(v0, rel=1e-6)
    assert float(st["alpha"]) == pytest.approx(v0 / (v0 + v1), rel=1e-6) and float(st["alpha"]) > 0.99
    np.testing.assert_allclose(mix, st["alpha"] * fo.mean(0) + (1 - st["alpha"]) * zo.mean(0), rtol=1e-6)
    # A biased first-order estimate (contact): its share shrinks to gamma / |bias|.
    biased = fo + np.array([5.0, 0.0, 0.0])
    mix, st = estimators.interpolate(jnp.asarray(biased), jnp.asarray(ok_fo), jnp.asarray(zo), jnp.asarray(ok_zo), 2.0)
    gamma = 2.0 * np.sqrt(v0 + np.sum(biased.var(0, ddof=1)) / 64)
    bias = np.linalg.norm(biased.mean(0) - zo.mean(0))
    assert float(st["alpha"]) == pytest.approx(gamma / bias, rel=1e-5)
    assert np.linalg.norm(np.asarray(mix) - zo.mean(0)) == pytest.approx(gamma, rel=1e-5)


def test_combine_first_order_is_the_robust_mean_and_interpolated_the_mix():
    rng = np.random.default_rng(3)
    grads = {"a": jnp.asarray(rng.normal(size=(8, 2))), "b": jnp.asarray(rng.normal(size=(8, 3)))}
    values = jnp.asarray(rng.normal(size=8))
    eps = jnp.asarray(rng.normal(size=(4, 5)))
    kw = dict(sigma=0.1, clip_factor=3.0, bias_factor=2.0)
    fo, stats = estimators.combine("first-order", values, grads, None, **kw)
    ref, _ = estimators.robust_mean_gradient(grads, 3.0)
    for k in grads:
        np.testing.assert_allclose(fo[k], ref[k], rtol=1e-12)
    assert float(stats["alpha"]) == 1.0
    mixed, stats = estimators.combine("interpolated", values, grads, eps, **kw)
    flat = np.concatenate([np.asarray(mixed["a"]), np.asarray(mixed["b"])])
    zo = np.asarray(estimators.zeroth_order_rows(values, eps, 0.1)[0]).mean(0)
    a = float(stats["alpha"])
    np.testing.assert_allclose(flat, a * np.concatenate([ref["a"], ref["b"]]) + (1 - a) * zo, rtol=1e-6, atol=1e-12)
    with pytest.raises(ValueError, match="unknown estimator"):
        estimators.combine("adjoint", values, grads, eps, **kw)


# ---------------------------------------------------------------------------------------------
# The gain schedule


@pytest.fixture(scope="module")
def bounds():
    return tuning_params.default_bounds(
        C.default_gains(ICUB), 10.0, (0.02, 2.0), tuning_params.default_regularisation()
    )


def _schedule(bounds, scale):
    base = C.default_gains(ICUB)
    plain = tuning_params.controls_to_params(base, tuning_params.default_regularisation(), bounds, regularisation=False)
    p = gs.init_params(plain)
    rng = np.random.default_rng(4)
    p["weights"] = {k: jnp.asarray(scale * rng.normal(size=v.shape)) for k, v in p["weights"].items()}
    return gs.from_params(p, bounds, base.ki_com, np.array([0.01, -0.02])), p, base


def test_schedule_has_348_entries_starts_at_the_plain_gains_and_stays_bounded(bounds):
    sched, p, base = _schedule(bounds, 0.0)
    assert gs.size(p) == 58 * 6 == 348
    still = sched.gains_at(jnp.zeros(30).at[:2].set(sched.origin), jnp.zeros(29))
    for k in GAIN_FIELDS:  # W = 0: the plain parameterisation's gains, whatever the state
        np.testing.assert_allclose(getattr(still, k), getattr(base, k), rtol=1e-4)
    sched, _, _ = _schedule(bounds, 30.0)  # large weights: the sigmoid saturates, the bounds hold
    rng = np.random.default_rng(5)
    for _ in range(20):
        q, v = jnp.asarray(rng.normal(scale=0.3, size=30)), jnp.asarray(rng.normal(scale=2.0, size=29))
        g = sched.gains_at(q, v)
        tuning_params.check_in_bounds(g, tuning_params.default_regularisation(), bounds)
        assert tuning_params.nava_conditions(g, tuning_params.default_regularisation())["holds"]


def test_schedule_follows_its_features(bounds):
    """A positive weight of kp_com[0] on the feature vx raises K_P,CoM x with the base's forward speed, as
    sigmoid(b + w tanh(vx / V)) says, and leaves the other entries alone."""
    sched, p, base = _schedule(bounds, 0.0)
    w = {k: jnp.zeros_like(v) for k, v in p["weights"].items()}
    w["kp_com"] = w["kp_com"].at[0, gs.FEATURES.index("vx")].set(1.5)
    sched = sched.replace(weights=w)
    q = jnp.zeros(30).at[:2].set(sched.origin)
    kp = [float(sched.gains_at(q, jnp.zeros(29).at[0].set(vx)).kp_com[0]) for vx in (-0.4, 0.0, 0.4)]
    assert kp[0] < kp[1] < kp[2]
    lo, hi = float(bounds.lo["kp_com"][0]), float(bounds.hi["kp_com"][0])
    z = float(p["base"]["kp_com"][0]) + 1.5 * np.tanh(0.4 / gs.SPEED_SCALE_MPS)
    assert kp[2] == pytest.approx(np.exp(np.log(lo) + (np.log(hi) - np.log(lo)) / (1 + np.exp(-z))), rel=1e-5)
    other = sched.gains_at(q, jnp.zeros(29).at[0].set(0.4))
    np.testing.assert_allclose(other.kp_com[1:], base.kp_com[1:], rtol=1e-4)


def test_schedule_file_round_trip_and_bad_files(bounds, tmp_path):
    sched, _, _ = _schedule(bounds, 0.7)
    path = tmp_path / "s.json"
    store.write_once(path, store.controls_dict(sched))
    assert gs.is_schedule_file(path) and not gs.is_schedule_file(ROOT / "assets" / "gains" / "com_critical_100.json")
    back = gs.load_schedule(path, np.float64)
    q, v = jnp.asarray(np.linspace(-0.1, 0.1, 30)), jnp.asarray(np.linspace(-1, 1, 29))
    for k in GAIN_FIELDS:
        np.testing.assert_allclose(getattr(back.gains_at(q, v), k), getattr(sched.gains_at(q, v), k), rtol=1e-6)
    data = json.loads(path.read_text())
    data["weights"]["kp_com"] = [[0.0] * 4] * 3
    path.write_text(json.dumps(data))
    with pytest.raises(ValueError, match="kp_com has inconsistent shapes"):
        gs.load_schedule(path)
    data["weights"]["kp_com"] = [[0.0] * 5] * 3
    data["lo"]["ki_ang"] = [1.0, -1.0, 1.0]
    path.write_text(json.dumps(data))
    with pytest.raises(ValueError, match="ki_ang has non-finite values or bounds"):
        gs.load_schedule(path)


# ---------------------------------------------------------------------------------------------
# The window loss


def _trace(T=20, com_x=0.0, vx=0.0, tilt=0.0):
    corners = np.array([[x, y] for y0 in (0.07, -0.07) for x in (-0.05, 0.1) for y in (y0 - 0.03, y0 + 0.03)])
    n = np.array([np.sin(tilt), 0.0, np.cos(tilt)])
    normals = np.repeat(np.stack([[0, 0, 1.0], n])[None], T, 0)
    base = tuning_loss.LossTrace(
        com=jnp.asarray(np.tile([com_x, 0.0, 0.5], (T, 1))),
        com_ref=jnp.zeros((T, 3)).at[:, 2].set(0.5),
        com_vel=jnp.asarray(np.tile([vx, 0.0, 0.0], (T, 1))),
        tau=jnp.zeros((T, 23)),
        support_xy=jnp.asarray(np.repeat(corners[None], T, 0)),
        com_height0=jnp.full(T, 0.5),
        foot_normal=jnp.asarray(normals),
    )
    return tuning_loss.TuneTrace(base=base, foot_normal=jnp.asarray(normals), qp_infeasible=jnp.zeros(T, bool))


def test_terminal_cost_is_the_capture_point_outside_the_feet_and_tilt_is_measured_from_the_reference():
    lc = tuning_loss.LossConfig().with_motor_limits(np.full(23, 60.0))  # the iCub's motors
    assert float(tuning_loss.terminal_cost(_trace(), lc)) == 0.0  # capture point at the centre
    omega = np.sqrt(constants.GRAVITY / 0.5)
    # Moving forward at 0.5 m/s from x = 0: capture point at 0.5 / omega, beyond the toes at 0.1 m.
    xi = 0.5 / omega
    expected = (lc.capture_margin + xi - 0.1) ** 2 / lc.capture_scale**2
    assert float(tuning_loss.terminal_cost(_trace(vx=0.5), lc)) == pytest.approx(expected, rel=1e-6)
    # A window whose feet are tilted all along shows no tilt against its own first tick, the full tilt
    # against the rollout's first tick.
    tilted = _trace(tilt=np.deg2rad(5.0))
    assert float(tuning_loss.loss_terms(tilted, lc)["tilt"]) == pytest.approx(0.0, abs=1e-12)
    flat = (jnp.asarray([[0, 0, 1.0], [0, 0, 1.0]]), tilted.base.support_xy[0])
    assert float(tuning_loss.loss_terms(tilted, lc, reference=flat)["tilt"]) == pytest.approx(1.0, rel=1e-6)


def test_seeded_carry_keeps_a_non_finite_cotangent_of_the_initial_state_out_of_the_gradient():
    """The initial carry is made to depend on the parameters (``problem._touch``) only to shorten the
    trace; its derivative must be a true zero, or an infinite cotangent of a state entry (sqrt at 0)
    reaches the gradient as inf x 0 = NaN."""
    from wbc_jax.tuning.algorithms import problem

    def f(p):
        x = problem._touch({"a": jnp.zeros(2), "n": jnp.arange(2)}, jnp.sum(p))
        return jnp.sum(jnp.sqrt(x["a"])) + jnp.sum(p**2) + jnp.sum(x["n"])

    p = jnp.asarray([1.0, -2.0])
    np.testing.assert_array_equal(np.asarray(jax.grad(f)(p)), [2.0, -4.0])
    batched = jax.vmap(jax.grad(f))(jnp.stack([p, 2 * p]))
    np.testing.assert_array_equal(np.asarray(batched), [[2.0, -4.0], [4.0, -8.0]])


# ---------------------------------------------------------------------------------------------
# The race's verdict and files


def _rep(entries):
    rep = {}
    for name, (med, mn, rmse) in entries.items():
        env = {
            "0.0": {"impulse_ns": 10 * med, "fraction": med, "bound_impulse_ns": 10.0},
            "90.0": {"impulse_ns": 10 * mn, "fraction": mn, "bound_impulse_ns": 10.0},
        }
        rep[name] = {
            "envelope_fraction_median": med,
            "envelope_fraction_min": mn,
            "survival_rate": med / 3,
            "sinusoid_com_rmse_m": rmse,
            "grid_envelope": env,
        }
    return rep


def test_race_verdict_recommendation_and_files(tmp_path):
    rep = _rep(
        {
            "gradient_t120": (0.40, 0.30, 1.0e-3),
            "gradient": (0.60, 0.42, 1.2e-3),
            "cmaes_t120": (0.50, 0.35, 1.0e-3),
            "cmaes": (0.52, 0.40, 1.0e-3),
            "random_t120": (0.45, 0.31, 1.0e-3),
            "random": (0.62, 0.45, 2.0e-3),
            "default": (0.25, 0.17, 1.0e-3),
            "critical": (0.41, 0.29, 0.3e-3),
        }
    )
    index = {
        n: {
            "method": n.split("_")[0],
            "budget_s": 120.0 if n.endswith("t120") else 300.0,
            "wall_s": 100.0,
            "sim_steps": 1000,
        }
        for n in rep
        if n.split("_")[0] in race.METHODS
    }
    pts = race.points(rep, index)
    assert [p["budget_s"] for p in pts["gradient"]] == [120.0, 300.0]
    v = race.verdict(pts)
    assert v["120"]["gradient_minus_cmaes_median"] == pytest.approx(-0.10) and not v["120"]["target_met"]
    assert v["300"]["gradient_minus_cmaes_median"] == pytest.approx(0.08)
    assert v["300"]["gradient_min_ge_cmaes_min"] and v["300"]["gradient_sinusoid_ok"] and v["300"]["target_met"]
    # random search has the best median but breaks the sinusoid bound: the gradient set is recommended.
    assert race.recommended(rep, list(rep)) == "gradient"
    rep["gradient"]["sinusoid_com_rmse_m"] = 1.6e-3
    assert not race.verdict(race.points(rep, index))["300"]["target_met"]
    assert race.recommended(rep, list(rep)) == "cmaes"
    from wbc_jax.report import tuning_plots

    tuning_plots.race_curves(pts, tmp_path / "race.png", reference={"default": rep["default"]})
    assert (tmp_path / "race.png").stat().st_size > 0


def test_write_once_refuses_other_contents(tmp_path):
    path = tmp_path / "a.json"
    assert store.write_once(path, {"x": [1.0, 2.0]})
    assert not store.write_once(path, {"x": np.array([1.0, 2.0])})  # the same again: accepted
    with pytest.raises(ValueError, match="never overwrites"):
        store.write_once(path, {"x": [1.0, 2.5]})


def test_tuning_programs_are_shared_by_phases_alike_and_only_by_them():
    """The race's phases and processes load each other's compiled gradient and window programs
    (sim/executables.py, keyed by Problem.program_identity and the arguments' shapes): problems built alike share
    a key whatever --out and --phases; a setting that changes the program without changing the arguments'
    shapes (the horizon, a loss weight, the start) or the tuning code gives another key."""
    from wbc_jax.sim import executables
    from wbc_jax.tuning import config
    from wbc_jax.tuning.algorithms import problem as tp

    tc = config.TuneConfig(batch=2, horizon=0.1, push_onset=0.0, duration_range=(0.02, 0.05), eval_horizon=0.1)
    base = tp.make_problem(tc)
    ident = base.program_identity()
    args = (base.init_params(),)
    key = executables.program_key("tune_gradient", ident, args)
    alike = tp.make_problem(config.TuneConfig(**{**vars(tc), "out": "elsewhere", "phases": ("quality",)}))
    assert executables.program_key("tune_gradient", alike.program_identity(), args) == key
    others = [
        tp.make_problem(config.TuneConfig(**{**vars(tc), "horizon": 0.2})),
        tp.make_problem(tc, tuning_loss.LossConfig(w_tilt=2.0)),
        tp.make_problem(
            config.TuneConfig(**{**vars(tc), "init_gains": str(ROOT / "experiments" / "gains" / "tuned_cmaes.json")})
        ),
    ]
    keys = {executables.program_key("tune_gradient", p.program_identity(), args) for p in others}
    assert len(keys) == len(others) and key not in keys
    assert executables.source_digest(("tuning",)) in ident and executables.source_digest(("tuning",)) != (
        executables.source_digest()
    )


# ---------------------------------------------------------------------------------------------
# The whole pipeline at tiny sizes (slow: compiles the gradient, window and population programs)

TINY_RUN = [
    "--horizon",
    "0.3",
    "--push-onset",
    "0.05",
    "--duration-range",
    "0.05",
    "0.1",
    "--eval-horizon",
    "0.3",
    "--batch",
    "4",
    "--steps",
    "2",
    "--population",
    "2",
    "--es-batch",
    "1",
    "--quality-pushes",
    "4",
    "--quality-directions",
    "2",
    "--eval-pushes",
    "2",
    "--grid-magnitudes",
    "20",
    "200",
    "3",
    "--grid-directions",
    "2",
    "--variation-magnitudes",
    "2",
    "--variation-directions",
    "2",
    "--variations",
    "left_hand",
    "--grid-onset",
    "0.1",
    "--grid-horizon",
    "0.4",
    "--one-foot-onset",
    "7.5",
    "--one-foot-horizon",
    "7.7",
    "--sinusoid-s",
    "0.3",
    "--quiet",
]


# pytest's 1200 s is too short for the race on a loaded 2-core machine: the gradient, window, population and held-out
# programs compile whatever the sizes (the gains case: 628 s at load 3.5, its gradient program traced and compiled once
# and loaded by the hybrid's budgets; 3000 s and over at load 7-10 while each budget traced it again). The limit
# covers both calls' subprocess timeouts.
@pytest.mark.slow
@pytest.mark.timeout(3000 + 1500)
@pytest.mark.parametrize(
    "extra",
    [
        ["--parameterisation", "gains"],
        ["--parameterisation", "scheduled", "--window-s", "0.1", "--windows", "2", "--estimator", "interpolated"],
    ],
    ids=["gains", "scheduled-windows"],
)
def test_race_pipeline_end_to_end(tmp_path, extra):
    """wbc-jax tune with a wall budget: every phase runs, each method's sets at the snapshot and at the
    budget are written once and held out (with their sinusoid RMSE), race.json names a recommendation;
    the hybrid starts from CMA-ES's set at half of each budget (kept for it) and adds both halves; a
    second call resumes without redoing anything."""
    out = tmp_path / "run"
    env = {
        **os.environ,
        "JAX_PLATFORMS": "cpu",
        "WBC_JAX_CACHE": os.environ.get("WBC_JAX_CACHE", ""),
        "XLA_FLAGS": "--xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true",
        "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
    }
    phases = ["train", "quality", "cmaes", "random", "hybrid", "heldout", "report"]
    cmd = [
        sys.executable,
        "-m",
        "wbc_jax.cli",
        "tune",
        "--out",
        str(out),
        *TINY_RUN,
        *extra,
        "--budget-s",
        "30",
        "--snapshots-s",
        "5",
    ]
    proc = subprocess.run([*cmd, "--phases", *phases], capture_output=True, text=True, timeout=3000, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    names = {f"{m}{t}" for m in race.METHODS for t in ("", "_t5")} | {"cmaes_t2.5", "cmaes_t15"}
    index = json.loads((out / "gains" / "provenance.json").read_text())
    assert set(index) == names and all(len(e["sha256"]) == 64 for e in index.values())
    for name, budget in (("hybrid_t5", 5.0), ("hybrid", 30.0)):
        hyb, parent = index[name], index[f"cmaes_t{budget / 2:g}"]
        assert hyb["parent"] == f"cmaes_t{budget / 2:g}" and hyb["parent_sha256"] == parent["sha256"]
        assert hyb["sim_steps"] == parent["sim_steps"] + hyb["gradient_sim_steps"]
        assert hyb["wall_s"] == pytest.approx(parent["wall_s"] + hyb["gradient_wall_s"], abs=1e-3)
        assert hyb["gradient_compile_s"] > 0 and hyb["gradient_wall_s"] <= budget / 2  # compile counted
        if hyb["step"] < 0:  # the compile took the half: the parent itself
            assert hyb["sha256"] == parent["sha256"] and hyb["gradient_sim_steps"] == 0
        if hyb["step"] >= 0 and parent["generation"] >= 0:  # it stepped from the parent's parameters
            with (
                np.load(out / "hybrid" / f"t{budget:g}" / "checkpoint.npz") as z,
                np.load(out / "cmaes" / "checkpoint.npz") as c,
            ):
                np.testing.assert_array_equal(z["extra_start"], c["extra_snapshots"][parent["generation"]])
    held = json.loads((out / "heldout.json").read_text())
    for name in names | {"default", "critical"}:
        assert 0.0 <= held[name]["envelope_fraction_median"] and held[name]["sinusoid_com_rmse_m"] > 0, name
    assert held["provenance"]["inputs"]["gradient"]["sha256"] == index["gradient"]["sha256"]
    rc = json.loads((out / "race.json").read_text())
    assert set(rc["methods"]) == set(race.METHODS) and rc["budgets_s"] == [5.0, 30.0]
    assert [p["budget_s"] for p in rc["methods"]["hybrid"]["points"]] == [5.0, 30.0]
    assert [p["budget_s"] for p in rc["methods"]["cmaes"]["points"]] == [2.5, 5.0, 15.0, 30.0]
    assert rc["recommended"] in held and "hybrid_minus_cmaes_median" in rc["verdict"]["30"]
    q = json.loads((out / "quality.json").read_text())
    assert set(q["estimates"]) >= {"first-order", "zeroth-order"} and q["parameters"] == (
        348 if "scheduled" in extra else 58
    )
    assert (out / "race.png").stat().st_size > 0
    # Resumed: nothing left to do, the same files.
    before = (out / "heldout.json").read_text()
    proc = subprocess.run(
        [*cmd, "--phases", "train", "cmaes", "random", "hybrid"], capture_output=True, text=True, timeout=1500, env=env
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert json.loads((out / "gains" / "provenance.json").read_text()).keys() == index.keys()
    assert (out / "heldout.json").read_text() == before
