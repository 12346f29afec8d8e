"""Gain tuning on several devices of one process (issue 45): the gradient step and the searches' population
program run one single-device program per device (wbc_jax.tuning.algorithms.objectives.DevicePrograms over
wbc_jax.sim.per_device.PerDevice) and give the one-device loss, gradient and objectives; a stalled device is
the watchdog's one-line error. Two host CPU devices in a subprocess. The default test replaces the closed
loop's physics by a closed form (compiling the closed loop's gradient takes minutes here); the slow one runs the
closed loop itself. On GPUs: experiments/checks/tune_gpus_check.py."""

import json
import os
import pathlib
import subprocess
import sys

import numpy as np
import pytest

from wbc_jax.core import options
from wbc_jax.tuning import config
from wbc_jax.tuning.algorithms.baselines import NOT_SEARCH

ROOT = pathlib.Path(__file__).resolve().parent.parent
TWO_DEVICES = {
    "JAX_PLATFORMS": "cpu",
    "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
    "XLA_FLAGS": f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=2",
}

# The tuning programs with the rollout replaced by a closed form of each row's gains and push, nonlinear in both,
# diverging (division by zero) on floors of friction > 1: what is under test is how the batch is split over the
# devices and gathered back, the per-rollout gradients, the step's robust mean, the antithetic pairs and the
# population's padding (3 x 3 rollouts on 2 devices), all the job's own code.
CLOSED_FORM = r"""
import json, pathlib, sys, tempfile, time
import jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
from jax.flatten_util import ravel_pytree
from jax.sharding import Mesh
from wbc_jax.sim import metrics as metrics_lib, watchdog
from wbc_jax.tuning import config
from wbc_jax.tuning.algorithms import baselines, estimators, gradient, loss
from wbc_jax.tuning.algorithms import problem as tp

def closed_form_rollout(problem, n_ticks=None, *, batch=1):
    def env(gains, reg, scen):
        g = jnp.concatenate([jnp.ravel(x) for x in jax.tree_util.tree_leaves(gains)])
        g = g / (1.0 + jnp.abs(g))
        p = jnp.concatenate([jnp.ravel(x) for x in jax.tree_util.tree_leaves(scen.push)])
        total = (jnp.sum(jnp.sin(jnp.linspace(0.5, 1.5, g.size) * g) ** 2) * scen.friction
                 + 1e-3 * jnp.sum(p ** 2) * scen.mass_scale + jnp.sum(g) ** 2 / g.size)
        total = total / jnp.where(scen.friction > 1.0, 0.0, 1.0)
        terms = {name: total * (k + 1) / 10 for k, name in enumerate(loss.TERMS)}
        metrics = metrics_lib.initial(jnp.asarray(0.5, g.dtype), g.dtype)
        return {**terms, "total": total}, metrics.replace(fell=total > 3.85)
    return env

tp.rollout_fn = closed_form_rollout
from wbc_jax.sim import warp_graphs
bounds, warp_bound = [], warp_graphs.bound
warp_graphs.bound = lambda limit, devices=1: bounds.append([limit, devices]) or warp_bound(limit, devices)
tc = config.TuneConfig(horizon=0.5, push_onset=0.05, duration_range=(0.05, 0.1), eval_horizon=0.5, batch=8, steps=2,
                       estimator="interpolated", population=2, es_batch=3, quality_pushes=4)
problem = tp.make_problem(tc)
out, tmp = {}, pathlib.Path(tempfile.mkdtemp())
for n in (1, 2):
    mesh = Mesh(np.asarray(jax.devices()[:n]), ("batch",))
    step = gradient.GradientStep(problem, gradient.make_optimizer(tc.lr, tc.clip_norm), mesh)
    params = problem.init_params()
    step.compile(params, step.optimizer.init(params))
    params_b, eps, rollouts, _, _ = step.rows_of(params, 0)
    values, grads, _, _ = step.grads(params_b, rollouts)
    grad, stats = estimators.combine(tc.estimator, jnp.asarray(values), jax.tree_util.tree_map(jnp.asarray, grads),
                                     eps, sigma=tc.smoothing_sigma, clip_factor=tc.env_clip, bias_factor=tc.bias_factor)
    _, _, rows, info = gradient.train(problem, tmp / f"gradient{n}", progress=False, step_fn=step)
    found = baselines.search(problem, "random", tmp / f"random{n}", budget={"sim_steps": 10**12, "wall_s": 0.0},
                             max_generations=2, progress=False, mesh=mesh)
    out[n] = {"values": np.asarray(values).tolist(), "grad": np.asarray(ravel_pytree(grad)[0]).tolist(),
              "nonfinite": int(stats["nonfinite_envs"]), "steps": [[r["loss"], r["grad_norm"]] for r in rows],
              "n_devices": info["n_devices"], "ran_on": info["ran_on"],
              "search": [[float(r[k]) for k in ("loss", "best_candidate_loss", "median_candidate_loss")]
                         for r in found["history"]]}
    if n == 2:  # device 1 blocks in the next call of the gradient program: the watchdog's error after 1 s
        step.grads.stall_timeout_s, step.grads.simulate_stall = 1.0, (step.grads.calls, 1)
        t0 = time.perf_counter()
        try:
            step(params, step.optimizer.init(params), 0)
        except watchdog.DeviceStalled as err:
            out["stall"], out["stall_after_s"] = str(err), time.perf_counter() - t0
out["warp_graph_bounds"] = bounds
print(json.dumps(out), flush=True)
import os
os._exit(0)  # as the CLI leaves: a stalled device's daemon thread may still be in XLA at teardown
"""


def test_tuning_on_two_devices_gives_the_one_device_loss_gradient_and_search_and_a_stall_is_an_error():
    """The 2-device gradient step and random search equal the 1-device ones (measured: bit-equal on two host
    CPU devices; the bound leaves room for float summation order only); the training record names both
    devices, whose shares finished; device 1 blocked in a gradient call is one line naming it and the call."""
    proc = subprocess.run(
        [sys.executable, "-c", CLOSED_FORM],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, **TWO_DEVICES},
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    res = json.loads(proc.stdout.strip().splitlines()[-1])
    one, two = res["1"], res["2"]
    assert (one["n_devices"], one["ran_on"]) == (1, ["cpu:0"])
    assert (two["n_devices"], two["ran_on"]) == (2, ["cpu:0", "cpu:1"])  # both devices' shares ran
    assert one["nonfinite"] == two["nonfinite"] >= 2  # a diverged antithetic pair (friction > 1) left out of both
    np.testing.assert_allclose(two["values"], one["values"], rtol=1e-12)  # measured: bit-equal
    np.testing.assert_allclose(two["grad"], one["grad"], rtol=1e-12)  # measured: bit-equal
    assert np.isfinite(one["grad"]).all() and np.linalg.norm(one["grad"]) > 0
    np.testing.assert_allclose(two["steps"], one["steps"], rtol=1e-12)  # two training steps: loss, gradient norm
    np.testing.assert_allclose(two["search"], one["search"], rtol=1e-12)  # (P + 1) x b = 9 rollouts, padded to 10
    assert res["stall"] == (
        "gradient program call 3: device cpu:1 did not finish its run within 1 s (1 of 2 "
        "device(s) did; bound: --stall-timeout-s); the gradient program calls finished before "
        "are kept: rerun the same command to resume"
    )
    assert 1.0 <= res["stall_after_s"] < 10.0
    # Each 2-device program, once compiled, sets MJX-Warp's graph bound for 2 devices (32 each), as a sweep does
    assert res["warp_graph_bounds"] and all(b == [None, 2] for b in res["warp_graph_bounds"])


def test_stall_timeout_is_checked_and_no_part_of_the_run_keys():
    """--stall-timeout-s bounds how a run proceeds: a bad value is a clear error; any value leaves the
    gradient's and the searches' checkpoint keys (and the run's fingerprint, campaign.run) as they were."""
    with pytest.raises(ValueError, match=r"--stall-timeout-s must be a number in \(0, 86400\] s, got 0"):
        options.replace(config.TuneConfig(), stall_timeout_s=0.0)
    base, bounded = config.TuneConfig(), config.TuneConfig(stall_timeout_s=30.0)
    for exclude in (config.NOT_TRAINING, NOT_SEARCH):
        assert config.config_key(base, exclude=exclude) == config.config_key(bounded, exclude=exclude)
    assert config.config_key(base) != config.config_key(bounded)  # the key sees the field unless excluded


CLOSED_LOOP = r"""
import json, jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
from jax.sharding import Mesh
from wbc_jax.tuning import config
from wbc_jax.tuning.algorithms import estimators, objectives, gradient
from wbc_jax.tuning.algorithms import problem as tp

tc = config.TuneConfig(horizon=0.05, push_onset=0.0, duration_range=(0.02, 0.04), eval_horizon=0.1, batch=2,
                       quality_pushes=2, population=2, es_batch=1)
problem = tp.make_problem(tc)
params = problem.init_params()
scen = objectives.cast_batch(gradient.training_batch(problem, 0)[0], problem.setup.dtype)
out = {}
for n in (1, 2):
    mesh = Mesh(np.asarray(jax.devices()[:n]), ("batch",))
    grads_fn = objectives.make_rollout_grads(problem, mesh)
    values, grads, _, _ = grads_fn(estimators.repeated(params, 2), scen)
    grad, _ = estimators.robust_mean_gradient(jax.tree_util.tree_map(jnp.asarray, grads), 3.0)
    pop = jax.tree_util.tree_map(lambda x: jnp.stack([x, x + 0.2]), params)
    pop_fn = objectives.make_population_objective(problem, 2, 1, mesh)
    obj, _, _ = pop_fn(pop, jax.tree_util.tree_map(lambda x: x[:1], scen))
    out[n] = {"values": np.asarray(values).tolist(), "grad": np.asarray(estimators.rows(
        jax.tree_util.tree_map(lambda x: x[None], grad))[0]).tolist(), "population": np.asarray(obj).tolist(),
        "ran_on": grads_fn.ran_on, "population_ran_on": pop_fn.ran_on}
print(json.dumps(out), flush=True)
import os
os._exit(0)  # as the CLI leaves: a stalled device's daemon thread may still be in XLA at teardown
"""


@pytest.mark.slow
@pytest.mark.timeout(2400)  # the subprocess's own limit: two gradient and two population compiles
def test_closed_loop_gradient_and_population_on_two_devices_match_one():
    """The tuning programs themselves (closed loop, 0.05 s, float64) on two host devices, one rollout each."""
    env = {
        **os.environ,
        **TWO_DEVICES,
        "XLA_FLAGS": f"{TWO_DEVICES['XLA_FLAGS']} --xla_backend_optimization_level=0 "
        "--xla_llvm_disable_expensive_passes=true",
    }
    proc = subprocess.run([sys.executable, "-c", CLOSED_LOOP], capture_output=True, text=True, timeout=2400, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    res = json.loads(proc.stdout.strip().splitlines()[-1])
    assert res["1"]["ran_on"] == ["cpu:0"] and res["2"]["ran_on"] == res["2"]["population_ran_on"] == ["cpu:0", "cpu:1"]
    np.testing.assert_allclose(res["2"]["values"], res["1"]["values"], rtol=1e-9)
    np.testing.assert_allclose(res["2"]["grad"], res["1"]["grad"], rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(res["2"]["population"], res["1"]["population"], rtol=1e-9)


def test_tune_refuses_several_processes_before_writing_anything(tmp_path, monkeypatch):
    """Under jax.distributed (class 9 of issue 41): one line naming the way out, no run folder; the devices of
    one process are what the tuning programs split over."""
    import jax

    from wbc_jax.tuning.orchestration import campaign

    monkeypatch.setattr(jax, "process_count", lambda: 2)
    with pytest.raises(
        ValueError,
        match=r"^wbc-jax tune runs in one process on its local devices \(every local GPU\), "
        r"not in 2 processes: run it without --distributed$",
    ):
        campaign.run(config.TuneConfig(out=str(tmp_path / "run")), progress=False)
    assert not (tmp_path / "run").exists()
