"""Gain tuning: the closed loop's gradient against finite differences (float64), no NaN over
random scenarios, the bounded parameterisation, the NaN guard, checkpoint/resume, gains files
(bad input; tuned gains loading back into balance and push-sweep)."""

import json
import os
import pathlib
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from wbc_jax import cli, tune
from wbc_jax import gains as C
from wbc_jax.constants import GAIN_FIELDS

# One subprocess (float64, XLA backend optimisation lowered: compile ~3.5 min instead of ~5)
# holds the one gradient program: experiments/grad_check.py, per-scenario gradients over N random
# push scenarios at a 0.1 s horizon, and central differences of the loss on one of them.
GRAD_CHECK = pathlib.Path(__file__).resolve().parent.parent / "experiments" / "grad_check.py"


@pytest.fixture(scope="module")
def grad_check():
    root = str(GRAD_CHECK.parent.parent)  # the package from this checkout, however it is installed
    env = {**os.environ, "JAX_PLATFORMS": "cpu",
           "PYTHONPATH": os.pathsep.join([root, os.environ.get("PYTHONPATH", "")]),
           "XLA_FLAGS": "--xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true"}  # fmt: skip
    proc = subprocess.run([sys.executable, str(GRAD_CHECK), "24"], capture_output=True, text=True,
                          timeout=1500, env=env)  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("group", (*tune.TUNED_FIELDS, "regularisation"))
def test_closed_loop_gradient_matches_central_differences(grad_check, group):
    """On the first scenarios: where central differences at steps 1e-4 and 1e-5 agree (the loss is
    smooth at that scale), the reverse-mode gradient matches them within 5 %."""
    rows = grad_check["fd"][group]
    smooth = [r for r in rows if r["smooth"]]
    assert smooth, f"{group}: central differences disagree between steps on every scenario: {rows}"
    for r in smooth:
        assert r["rel_err"] < 0.05, (group, r)


def test_no_nan_gradients_over_random_scenarios(grad_check):
    assert grad_check["n"] == 24 and grad_check["nonfinite"] == 0
    loss = np.asarray(grad_check["loss"])
    assert np.all(np.isfinite(loss)) and np.ptp(loss) > 0  # the scenarios differ


def test_bounded_parameters_round_trip_and_stay_in_bounds():
    base = C.default_gains()
    bounds = tune.default_bounds(base, 4.0)
    p = tune.gains_to_params(base, bounds)
    for k in tune.TUNED_FIELDS:
        np.testing.assert_allclose(p[k], 0.0, atol=1e-5)  # default = geometric mid-point
    g = tune.params_to_gains({k: v + 1e3 * np.sign(np.arange(v.size) % 2 - 0.5) for k, v in p.items()},
                             bounds, base)  # fmt: skip
    for k in tune.TUNED_FIELDS:
        v = np.asarray(getattr(g, k))
        assert np.all(v > 0) and np.all(v <= np.asarray(bounds.hi[k]) * (1 + 1e-5))
        assert np.all(v >= np.asarray(bounds.lo[k]) * (1 - 1e-5))
        np.testing.assert_allclose(v[1::2], np.asarray(bounds.hi[k])[1::2], rtol=1e-5)
    np.testing.assert_array_equal(g.ki_com, base.ki_com)  # not tuned
    shifted = base.replace(kp_com=base.kp_com * 2.0)
    back = tune.params_to_gains(tune.gains_to_params(shifted, bounds), bounds, base)
    np.testing.assert_allclose(back.kp_com, shifted.kp_com, rtol=1e-4)


def test_optimizer_skips_and_counts_nonfinite_gradients():
    opt = tune.make_optimizer(0.1, 1.0)
    params = {"a": jnp.ones(3)}
    state = opt.init(params)
    for bad in (np.nan, np.inf):
        updates, state = opt.update({"a": jnp.array([1.0, bad, 1.0])}, state, params)
        np.testing.assert_array_equal(updates["a"], 0.0)  # nothing applied
    assert tune.skipped_count(state) == 2
    updates, state = opt.update({"a": jnp.array([10.0, 0.0, 0.0])}, state, params)
    assert float(updates["a"][0]) == pytest.approx(-0.1, rel=1e-3)  # adam's first step: -lr sign(g)
    assert tune.skipped_count(state) == 2


class _Interrupt(Exception):
    pass


def _fake_step(optimizer, bounds, base, target, stop_at=None, nan_at=()):
    """A train step on a known quadratic (log-gain distance to ``target``), the real optimiser;
    a NaN gradient at the steps in ``nan_at``; raises at ``stop_at`` (a killed run)."""
    import optax

    calls = {"k": 0}

    def loss(p):
        g = tune.params_to_gains(p, bounds, base)
        return sum(jnp.sum((jnp.log(getattr(g, k)) - jnp.log(getattr(target, k))) ** 2) for k in tune.TUNED_FIELDS)

    def step(params, opt_state, scen):
        k = calls["k"]
        calls["k"] += 1
        if k == stop_at:
            raise _Interrupt
        value, grad = jax.value_and_grad(loss)(params)
        if k in nan_at:
            grad = jax.tree_util.tree_map(lambda x: x * jnp.nan, grad)
        updates, opt_state = optimizer.update(grad, opt_state, params)
        terms = {n: value for n in ("com", "effort", "capture", "height")}
        finite = all(bool(jnp.all(jnp.isfinite(g))) for g in jax.tree_util.tree_leaves(grad))
        return optax.apply_updates(params, updates), opt_state, value, terms, optax.global_norm(grad), finite

    return step


def test_training_loop_guard_resume_and_gains_file(robot, tmp_path):
    tc = tune.TuneConfig(steps=6, batch=2, lr=0.2, clip_norm=10.0)
    lc = tune.LossConfig()
    base = C.default_gains(robot.index.n)
    bounds = tune.default_bounds(base, tc.bound_factor)
    target = base.replace(kp_com=base.kp_com * 2.0, kd_postural=base.kd_postural * 0.5)
    opt = tune.make_optimizer(tc.lr, tc.clip_norm)
    # Uninterrupted run.
    full, rows_full, _ = tune.train(robot, tc, lc, tmp_path / "a", progress=False,
                                    step_fn=_fake_step(opt, bounds, base, target, nan_at=(2,)))  # fmt: skip
    losses = [float(r["loss"]) for r in rows_full]
    assert losses[-1] < 0.5 * losses[0]  # it optimises
    assert [r["finite"] for r in rows_full] == [True, True, False, True, True, True]
    assert rows_full[-1]["skipped_total"] == 1
    # Killed at step 4, then resumed: same result, history without duplicates.
    with pytest.raises(_Interrupt):
        tune.train(robot, tc, lc, tmp_path / "b", progress=False,
                   step_fn=_fake_step(opt, bounds, base, target, stop_at=4, nan_at=(2,)))  # fmt: skip
    resumed, rows, _ = tune.train(robot, tc, lc, tmp_path / "b", progress=False,
                                  step_fn=_fake_step(opt, bounds, base, target))  # fmt: skip
    assert [int(r["step"]) for r in rows] == list(range(6))
    for k in GAIN_FIELDS:
        np.testing.assert_allclose(getattr(resumed, k), getattr(full, k), rtol=1e-6)
    with pytest.raises(ValueError, match="another tuning config"):
        tune.train(robot, tune.TuneConfig(steps=7, batch=2), lc, tmp_path / "b", progress=False,
                   step_fn=_fake_step(opt, bounds, base, target))  # fmt: skip
    # tuned_gains.json has gains_to_dict's format and loads back.
    saved = json.loads((tmp_path / "a" / "tuned_gains.json").read_text())
    assert saved == C.gains_to_dict(full)
    loaded = C.load_gains(tmp_path / "a" / "tuned_gains.json")
    np.testing.assert_allclose(loaded.kp_com, full.kp_com, rtol=1e-6)
    assert (tmp_path / "a" / "history.csv").read_text().splitlines()[0].startswith("step,loss,com")


def test_bad_gains_files_name_the_problem(tmp_path):
    good = C.gains_to_dict(C.default_gains())
    cases = [
        ({**good, "kp_foo": [1.0]}, r"unknown keys \['kp_foo'\]"),
        ({k: v for k, v in good.items() if k != "kd_com"}, r"missing keys \['kd_com'\]"),
        ({**good, "kp_postural": good["kp_postural"][:5]}, r"kp_postural must have 23 entries"),
        ({**good, "kp_com": [50.0, 0.0, 10.0]}, r"non-positive entries .*'kp_com': \[1\]"),
        ({**good, "kd_postural": [-1.0] * 23}, r"kd_postural has negative entries"),
        ({**good, "ki_ang": ["a", "b", "c"]}, r"gain ki_ang must be a list of numbers"),
    ]
    for values, message in cases:
        path = tmp_path / "g.json"
        path.write_text(json.dumps(values))
        with pytest.raises(ValueError, match=message):
            C.load_gains(path)
    assert np.all(np.asarray(C.gains_from_dict(good).ki_com) == 0)  # ki_com = 0 stays allowed


def test_tuned_gains_file_runs_in_balance_and_push_sweep(tmp_path, capsys):
    """A tuned file (gains_to_dict of bounded gains) through both CLI paths."""
    base = C.default_gains()
    bounds = tune.default_bounds(base)
    gains = tune.params_to_gains({k: v + 0.3 for k, v in tune.gains_to_params(base, bounds).items()},
                                 bounds, base)  # fmt: skip
    path = tmp_path / "tuned_gains.json"
    path.write_text(json.dumps(C.gains_to_dict(gains)))
    rc = cli.main(["balance", "--gains", str(path), "--duration", "0.05", "--out", str(tmp_path / "bal"),
                   "--quiet"])  # fmt: skip
    assert rc == 0, capsys.readouterr().err
    metrics = json.loads((tmp_path / "bal" / "metrics.json").read_text())
    np.testing.assert_allclose(metrics["gains"]["kp_postural"], np.asarray(gains.kp_postural), rtol=1e-6)
    assert not metrics["fell"] and not metrics["nan"]
    rc = cli.main(["push-sweep", "--gains", str(path), "--magnitudes", "20", "20", "1", "--directions", "1",
                   "--horizon", "0.05", "--push-onset", "0.0", "--push-duration", "0.02", "--chunk-size", "1",
                   "--out", str(tmp_path / "sw"), "--quiet"])  # fmt: skip
    assert rc == 0, capsys.readouterr().err
    summary = json.loads((tmp_path / "sw" / "summary.json").read_text())
    np.testing.assert_allclose(summary["gains"]["kp_com"], np.asarray(gains.kp_com), rtol=1e-6)
    assert summary["n_envs"] == 1 and summary["nan_envs"] == 0
