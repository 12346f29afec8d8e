"""The check scripts (experiments/checks/, benchmarks/benchmark.py, experiments/acceptance/cpu_targets.py): each
states its bar in ``--help``, and its ``failures(result)`` passes a result within the bar and fails one outside it.
The recorded results (results/) serve as inputs where they exist: some pass, and some (TensorFloat-32 on the GPU, the soak
before the margin fix) are known failures that the bar must catch. No JAX compile: the functions read dicts."""

import ast
import copy
import json
import pathlib
import sys

import pandas as pd
import pytest
from conftest import load_script

from wbc_jax.core import checks

ROOT = pathlib.Path(__file__).resolve().parent.parent
SCRIPTS = {
    "backend_check": "experiments/checks/backend_check.py",
    "envelope_check": "experiments/checks/envelope_check.py",
    "island_check": "experiments/checks/island_check.py",
    "queue_check": "experiments/checks/queue_check.py",
    "margin_precision_check": "experiments/checks/margin_precision_check.py",
    "kill_trials": "experiments/checks/kill_trials.py",
    "soak": "experiments/checks/soak.py",
    "grad_check": "experiments/checks/grad_check.py",
    "bad_input": "experiments/checks/bad_input.py",
    "memory_estimate": "experiments/checks/memory_estimate.py",
    "tune_gpus_check": "experiments/checks/tune_gpus_check.py",
    "benchmark": "benchmarks/benchmark.py",
    "cpu_targets": "experiments/acceptance/cpu_targets.py",
}


def script(name: str):
    """A script of SCRIPTS loaded from its file (scripts are not a package), once."""
    return load_script(SCRIPTS[name])


def doc(path: str) -> dict:
    return json.loads((ROOT / path).read_text())


@pytest.mark.parametrize("name", sorted(SCRIPTS))
def test_help_states_the_bar_and_the_exit_status(name, capsys):
    with pytest.raises(SystemExit) as stop:
        script(name).main(["--help"])
    assert stop.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "Check:" in text and "exit status 1" in text, text[-600:]


def _calls(node) -> set[str]:
    return {ast.unparse(n.func) for n in ast.walk(node) if isinstance(n, ast.Call)}


@pytest.mark.parametrize("name", sorted(SCRIPTS))
def test_script_applies_its_check_and_exits_with_it(name):
    """The script records checks.verdict(failures(...)) and its __main__ exits with checks.exit_status."""
    tree = ast.parse((ROOT / SCRIPTS[name]).read_text())
    verdicts = [n for n in ast.walk(tree) if isinstance(n, ast.Call) and ast.unparse(n.func) == "checks.verdict"]
    assert verdicts and all(_calls(v.args[0]) & {"failures"} for v in verdicts), "no checks.verdict(failures(...))"
    mains = [n for n in tree.body if isinstance(n, ast.If) and "__main__" in ast.unparse(n.test)]
    assert mains and "sys.exit" in _calls(mains[0]) and "checks.exit_status" in _calls(mains[0])


def test_exit_status_follows_the_verdict(capsys):
    assert checks.exit_status({"check": checks.verdict([], "bar")}) == 0
    assert checks.exit_status({"check": checks.verdict(["a is 2 > 1"], "bar")}) == 1
    assert "check failed: a is 2 > 1" in capsys.readouterr().err
    assert checks.exit_status({}) == 1  # no verdict: nothing was checked


def test_backend_check_bar_is_one_millimetre():
    bc = script("backend_check")
    ok = doc("results/gpu_h200/check/backend_check.json")  # H200: Warp, JAX, C MuJoCo within 4e-6 m
    assert bc.failures(ok) == []
    bad = copy.deepcopy(ok)
    bad["max_com_difference_m"]["warp-jax"] = 1.5e-3
    assert len(bc.failures(bad)) == 1 and "warp-jax" in bc.failures(bad)[0]
    bad["max_com_difference_m"]["jax-mujoco"] = float("nan")
    assert len(bc.failures(bad)) == 2
    assert bc.failures({"max_com_difference_m": {}}) != []  # one backend: nothing compared


def test_envelope_check_bar_is_one_grid_step_in_every_direction():
    ec = script("envelope_check")
    assert ec.failures(doc("results/envelope/cpu_mujoco/envelope_check.json")) == []
    assert ec.failures(doc("results/envelope/h100_warp_highest/envelope_check.json")) == []  # exactly one step
    # TensorFloat-32 products on the H100 (before SimConfig.matmul_precision): 0.77 N s > the 0.62 N s step.
    tf32 = ec.failures(doc("results/envelope/h100_jax_tf32/envelope_check.json"))
    assert len(tf32) >= 1 and all("grid step" in line for line in tf32)
    # The verdict is recomputed from the directions, not read from the recorded flag.
    forged = doc("results/envelope/h100_jax_tf32/envelope_check.json")
    forged["within_one_grid_step"] = True
    assert ec.failures(forged) == tf32


def _grid(survived: dict) -> pd.DataFrame:
    """A sweep table (gain set 0): {azimuth: [survived at 10, 20, ..., 100 N]}."""
    rows = [
        {"gain_set": 0, "azimuth_deg": az, "magnitude_n": 10.0 * (k + 1), "survived": bool(v)}
        for az, outcome in survived.items()
        for k, v in enumerate(outcome)
    ]
    return pd.DataFrame(rows)


# Direction 0 survives to 50 N; direction 90 to 30 N, with an island at 50 N.
REFERENCE = {0.0: [1, 1, 1, 1, 1, 0, 0, 0, 0, 0], 90.0: [1, 1, 1, 0, 1, 0, 0, 0, 0, 0]}
NEAR = {0.0: [1, 1, 1, 1, 0, 0, 0, 0, 0, 0], 90.0: [1, 1, 1, 1, 0, 1, 0, 0, 0, 0]}  # the boundary moved a step
FAR = {0.0: [1, 0, 1, 1, 1, 0, 0, 0, 0, 0], 90.0: REFERENCE[90.0]}  # a fall at 20 N: 3 steps below the band


def test_island_check_passes_flips_near_the_boundary_and_fails_far_ones():
    ic = script("island_check")
    ref = _grid(REFERENCE)
    band, stats = ic.transition(ref, 10.0)
    assert band == {0.0: (60.0, 50.0), 90.0: (40.0, 50.0)} and stats["island_cells"] == 1
    near = ic.compare(ref, _grid(NEAR), band, 10.0)
    assert near == {
        "cells_differing": 4,
        "outside_the_first_sweeps_band": 1,
        "max_steps_from_the_first_sweeps_band": 1.0,
    }  # (90 deg at 60 N: one step above)
    far = ic.compare(ref, _grid(FAR), band, 10.0)
    assert far["cells_differing"] == 1 and far["max_steps_from_the_first_sweeps_band"] == 3.0
    assert ic.failures({"flips": {"near": near}}) == []
    assert ic.failures({"flips": {"near": near}}, max_steps=0.5) != []
    assert len(ic.failures({"flips": {"near": near, "far": far}})) == 1
    assert ic.failures({"flips": {}}) != []  # one sweep: nothing compared


def test_island_check_script_exits_1_on_a_far_flip(tmp_path):
    """The script end to end (pandas only): exit status 0 near the boundary, 1 with a far flip."""
    import subprocess

    for name, grid in (("ref", REFERENCE), ("near", NEAR), ("far", FAR)):
        (tmp_path / name).mkdir()
        _grid(grid).to_parquet(tmp_path / name / "results.parquet")
    run = [sys.executable, str(ROOT / SCRIPTS["island_check"]), str(tmp_path / "ref")]
    ok = subprocess.run(
        [*run, str(tmp_path / "near"), "--out", str(tmp_path / "ok.json")], capture_output=True, text=True
    )
    assert ok.returncode == 0, ok.stderr[-2000:]
    assert json.loads((tmp_path / "ok.json").read_text())["check"]["passed"]
    bad = subprocess.run(
        [*run, str(tmp_path / "near"), str(tmp_path / "far"), "--out", str(tmp_path / "bad.json")],
        capture_output=True,
        text=True,
    )
    assert bad.returncode == 1 and "check failed: far:" in bad.stderr
    written = json.loads((tmp_path / "bad.json").read_text())
    assert not written["check"]["passed"] and written["provenance"]["inputs"]["sweep:far"]["sha256"]


@pytest.mark.parametrize(
    "path",
    ["results/gpu_h200/queue/queue_check.json", "results/gpu_h200/queue/constant_activation/queue_check_32.json"],
)
def test_queue_check_passes_the_measured_floor(path):
    assert script("queue_check").failures(doc(path)) == []


def test_queue_check_fails_over_the_bar_and_any_nan_difference():
    qc = script("queue_check")
    ok = doc("results/gpu_h200/queue/queue_check.json")
    n = ok["plain"]["n_envs"]
    bad = copy.deepcopy(ok)
    bad["queued"][1]["outcomes"]["survived"]["differ"] = int(0.02 * n)  # 2 % > 1.5 %
    assert len(qc.failures(bad)) == 1 and "survived" in qc.failures(bad)[0]
    assert qc.failures(bad, max_differ=0.025) == []
    bad = copy.deepcopy(ok)
    bad["plain"]["repeat_outcomes"]["nan"]["differ"] = 1
    assert len(qc.failures(bad)) == 1 and "repeat" in qc.failures(bad)[0]


def test_margin_precision_check_bar():
    mp = script("margin_precision_check")
    exact = {"max_abs_err_m": 1.19e-7, "sign_flips": 0}  # the H200 after the fix (tf32_check.json: new_default)
    ok = {
        "n": 256,
        "current_default": exact,
        "current_highest": exact,
        "old_default": {"max_abs_err_m": 0.267, "sign_flips": 32},
    }
    assert mp.failures(ok) == []  # the old function is shown, not checked
    tf32 = dict(ok, current_default=doc("results/gpu_h200/margin_fix/tf32_check.json")["old_default"])
    assert len(mp.failures(tf32)) == 2  # 32 sign flips, 0.27 m off
    assert mp.failures({"n": 256, "current_default": exact}) == ["current_highest: not measured"]


def test_kill_trials_bar():
    kt = script("kill_trials")
    reliability = doc("results/reliability.json")  # counts only (recorded before the trials were kept)
    assert kt.failures(reliability["kill_sweep"]) == []
    assert kt.failures(reliability["kill_tune"]) == []  # 8 of 10 killed, none differs
    assert len(kt.failures(dict(reliability["kill_sweep"], kill_mismatches=2))) == 1
    trials = [{"trial": k, "killed": k != 1, "differences": []} for k in range(4)]
    result = {"kill_trials": 4, "kill_killed": 3, "kill_mismatches": 0, "trials": trials}
    assert kt.failures(result) == []
    result["trials"][3]["differences"] = ["survived"]
    assert kt.failures(result) == ["trial 3: differs from the reference in ['survived']"]
    never = {**result, "trials": [dict(t, killed=False, differences=[]) for t in trials]}
    assert len(kt.failures(never)) == 1 and "killed" in kt.failures(never)[0]


def test_soak_bar():
    soak = script("soak")
    reliability = doc("results/reliability.json")
    assert soak.failures(reliability["soak_jax_h200_1m"]) == []  # 592 divergences flagged: outcomes, not failures
    leaky = soak.failures(reliability["soak_warp_h200"])  # before the margin fix: 170,317 NaN leaks
    assert len(leaky) == 1 and "NaN leaks" in leaky[0]
    hung = dict(reliability["soak_jax_h200_1m"], soak_hangs=1)
    assert len(soak.failures(hung)) == 1 and "hung" in soak.failures(hung)[0]
    short = dict(reliability["soak_jax_h200_1m"], soak_envs_requested=2_000_000)
    assert len(soak.failures(short)) == 1


def test_grad_check_bar():
    gc = script("grad_check")
    ok = doc("results/tuning/grad_check_100.json")  # H100, N = 100
    assert gc.failures(ok) == []
    off = copy.deepcopy(ok)
    off["fd"]["kd_postural"][0]["rel_err"] = 0.09  # the frozen projector's 9 % (results/tuning/grad_check_sources.json)
    assert len(gc.failures(off)) == 1 and "kd_postural" in gc.failures(off)[0]
    rough = copy.deepcopy(ok)
    for row in rough["fd"]["kp_com"]:
        row["smooth"] = False
    assert len(gc.failures(rough)) == 1 and "kp_com" in gc.failures(rough)[0]
    nan = dict(ok, nonfinite=2, loss=[*ok["loss"][:-1], float("nan")])
    assert len(gc.failures(nan)) == 2


def test_benchmark_trajectory_check_bar():
    bm = script("benchmark")
    eq = {"solver_iterations": 4, "com_max_diff_m": 2.1e-5, "same_within_1mm": True}
    assert bm.failures({"equivalence": [eq]}) == []
    assert bm.failures({}) == []  # --skip-equivalence: nothing to check
    off = dict(eq, com_max_diff_m=1.2e-3)
    assert len(bm.failures({"equivalence": [eq, off]})) == 1
    assert len(bm.failures({"equivalence": [dict(eq, com_max_diff_m=float("nan"))]})) == 1


def test_benchmark_json_keeps_a_warm_started_row_beside_the_cold_one(tmp_path):
    """Issue 46: a ``--qp-warm-start`` run's row is its own setting in results/benchmarks.json; a cold run
    replaces the cold row (the rows before the flag have no such key)."""
    bm = script("benchmark")
    path = tmp_path / "benchmarks.json"
    setting = {"device": "gpu", "backend": "warp", "solver_iterations": 4, "batch": 65536, "n_devices": 1}
    result = {"date": "d", "command": "c", "runs": [dict(setting, closed_loop_steps_per_s=1.0)]}
    bm.update_json_rows(path, bm.json_rows(result))
    warm = dict(result, runs=[dict(setting, closed_loop_steps_per_s=2.0, qp_warm_start=True)])
    bm.update_json_rows(path, bm.json_rows(warm))
    cold = dict(result, runs=[dict(setting, closed_loop_steps_per_s=3.0, qp_warm_start=False)])
    rows = bm.update_json_rows(path, bm.json_rows(cold))
    assert sorted((r["closed_loop_steps_per_s"], r.get("qp_warm_start")) for r in rows) == [(2.0, True), (3.0, None)]
    # A run under other XLA flags (gpu_run.sh bench46_cbuf) or with unrolled QP steps: rows of their own too.
    flagged = dict(
        result, runs=[dict(setting, closed_loop_steps_per_s=4.0, xla_flags="--xla_gpu_enable_command_buffer=")]
    )
    unrolled = dict(result, runs=[dict(setting, closed_loop_steps_per_s=5.0, qp_unrolled_steps=6)])
    bm.update_json_rows(path, bm.json_rows(flagged))
    rows = bm.update_json_rows(path, bm.json_rows(unrolled))
    assert sorted(r["closed_loop_steps_per_s"] for r in rows) == [2.0, 3.0, 4.0, 5.0]
    # The force QP's interior point in Warp (gpu_run.sh bench46_wqp): a row of its own; "jax" is the cold row's.
    wqp = dict(result, runs=[dict(setting, closed_loop_steps_per_s=6.0, qp_engine="warp")])
    jax_engine = dict(result, runs=[dict(setting, closed_loop_steps_per_s=7.0, qp_engine="jax")])
    bm.update_json_rows(path, bm.json_rows(wqp))
    rows = bm.update_json_rows(path, bm.json_rows(jax_engine))
    assert sorted((r["closed_loop_steps_per_s"], r.get("qp_engine")) for r in rows) == [
        (2.0, None),
        (4.0, None),
        (5.0, None),
        (6.0, "warp"),
        (7.0, None),
    ]
    assert [r.get("xla_flags") for r in rows if r["closed_loop_steps_per_s"] == 4.0] == [
        "--xla_gpu_enable_command_buffer="
    ]


def test_cpu_targets_bar():
    ct = script("cpu_targets")
    ok = doc("results/cpu_targets/cpu_targets.json")
    assert ct.failures(ok) == []
    slow = copy.deepcopy(ok)
    slow["main_job"]["met"] = False
    assert ct.failures(slow) == [f"main_job: {ok['main_job']['target']} not met"]


def test_bad_input_bar_is_every_case_failing_fast_and_clearly():
    bi = script("bad_input")
    ok = doc("results/reliability.json")["bad_input_pass3"]  # 151 cases on the 2-core CPU, all passed
    assert ok["cases"] >= 90 and bi.failures(ok) == []
    bad = copy.deepcopy(ok)
    bad["cases_run"][0].update(ok=False, problems=["exit code 0", "wrote --out"])
    assert bi.failures(bad) == [f"{ok['cases_run'][0]['command']}: exit code 0, wrote --out"]
    assert bi.failures({"cases_run": []}) == ["no case was run"]
    # The judge of one case: each way of misbehaving is named.
    assert bi.judge(2, "wbc-jax x: error: --a must be 1\n", 1.0, "--a must", False, 30.0) == []
    assert bi.judge(0, "", 1.0, "--a", True, 30.0) == [
        "exit code 0",
        "0 error lines",
        "message does not match",
        "wrote --out",
    ]
    assert bi.judge(2, "Traceback\n  x\nValueError: --a\n", 40.0, "--a", False, 30.0) == [
        "traceback",
        "3 error lines",
        "40.0 s > 30 s",
    ]


def test_memory_estimate_bar_is_no_measurement_above_the_estimate():
    me = script("memory_estimate")
    ok = doc("results/memory_estimate/memory_estimate.json")  # the 2-core CPU: at most 0.66 of the estimate
    assert me.failures(ok) == [] and all(r["measured_over_estimate"] <= 1.0 for r in ok["rows"])
    bad = copy.deepcopy(ok)
    bad["rows"][-1]["measured_over_estimate"] = 1.2
    assert len(me.failures(bad)) == 1 and "1.2 x the estimate" in me.failures(bad)[0]
    assert me.failures({"rows": []}) == ["nothing was measured"]


def test_tune_gpus_check_takes_the_one_device_half_only_from_a_call_measured_alike(tmp_path):
    """A call cut off in the N-device half leaves the one-device figures; the next call with the same tune flags,
    repeats and device kind reuses them, any other call (or a damaged file) measures them again."""
    tg = script("tune_gpus_check")
    half = {"tune_flags": ["--batch", "4"], "repeats": 2, "device": "NVIDIA H200"}
    path = tmp_path / tg.ONE_DEVICE_FILE
    assert tg.one_device_half(path, half) is None  # nothing there yet
    path.write_text(json.dumps({**half, "one": {"loss": 2.5}}))
    assert tg.one_device_half(path, half) == {"loss": 2.5}
    for key, other in (("repeats", 3), ("device", "NVIDIA H100 80GB HBM3"), ("tune_flags", ["--batch", "8"])):
        assert tg.one_device_half(path, {**half, key: other}) is None, key
    path.write_text("{not json")
    assert tg.one_device_half(path, half) is None


def test_tune_gpus_check_bar_is_the_gradient_within_the_bound_on_every_device():
    tg = script("tune_gpus_check")
    run = {
        "values": [1.0, 2.0, float("nan"), 4.0],
        "gradient": [0.5, -2.0, 1e-9],
        "loss": 2.0,
        "step_s_median": 4.0,
        "cmaes": {"gen_s_median": 3.0, "generation_0": {"loss": 1.0}},
        "devices": 1,
        "ran_on": ["gpu:0"],
    }
    two = {
        **run,
        "gradient": [0.5, -2.0 + 1e-4, 2e-9],
        "step_s_median": 2.5,
        "devices": 2,
        "ran_on": ["gpu:0", "gpu:1"],
    }
    cmp = tg.compare(run, two, 1e-3)
    assert cmp["gradient_max_rel_diff"] == pytest.approx(5e-5) and cmp["step_speedup"] == 1.6
    assert cmp["rollout_values_max_rel_diff"] == 0.0 and cmp["finiteness_differs"] == 0
    assert tg.failures({"comparison": cmp, "all": two}) == []
    off = {**two, "gradient": [0.5, -2.01, 0.0], "ran_on": ["gpu:0"]}
    assert tg.failures({"comparison": tg.compare(run, off, 1e-3), "all": off}) == [
        "the 2-device gradient differs from one device's by 0.005 of its largest entry (bound 0.001)",
        "the 2-device step's last call finished on ['gpu:0'] only",
    ]
    nan = {**two, "gradient": [float("nan"), -2.0, 0.0]}
    assert "differs from one device's by inf" in tg.failures({"comparison": tg.compare(run, nan, 1e-3), "all": nan})[0]
    # With the shares run on one device: the bar is the split against them; the whole batch's rounding is reported.
    far = {
        **two,
        "gradient": [0.6, -2.0, 0.0],
        "shares_on_first_device": {"values": run["values"], "gradient": [0.6, -2.0, 1e-9]},
    }
    cmp = tg.compare(run, far, 1e-3)
    assert cmp["gradient_vs_shares_max_rel_diff"] == pytest.approx(5e-10) and cmp[
        "gradient_max_rel_diff"
    ] == pytest.approx(0.05)
    assert (
        cmp["shares_vs_one_gradient_max_rel_diff"] == pytest.approx(0.05)
        and tg.failures({"comparison": cmp, "all": far}) == []
    )
    split_off = {**far, "gradient": [0.6, -2.01, 0.0]}
    assert tg.failures({"comparison": tg.compare(run, split_off, 1e-3), "all": split_off}) == [
        "the 2-device gradient differs from the same shares on one device by 0.005 of its largest entry (bound 0.001)"
    ]


def test_tune_gpus_check_bound_is_the_shares_repeat_floor_where_the_device_is_not_deterministic():
    """On a GPU the same executable gives other values run to run (results/tuning/tune_gpus_h200x2_s56/): the bound
    is then FLOOR_FACTOR x the shares' repeat on the first device, for the gradient and the rollouts' median; a
    split that scrambles the rollouts fails on their values though the floor lifts the gradient's bound."""
    tg = script("tune_gpus_check")
    one = {
        "values": [1.0, 2.0, 4.0, 8.0],
        "gradient": [1.0, -2.0],
        "loss": 2.0,
        "step_s_median": 4.0,
        "cmaes": {"gen_s_median": 3.0, "generation_0": {"loss": 1.0}},
        "devices": 1,
        "ran_on": ["gpu:0"],
    }
    shares = {"values": [1.0, 2.0, 4.0, 8.0], "gradient": [1.0, -2.0]}
    repeat = {"values": [1.01, 2.02, 4.0, 8.0], "gradient": [1.1, -2.0]}  # median 0.5 %, gradient 0.05
    noisy = {
        **one,
        "values": [1.0075, 2.015, 4.03, 8.0],  # median 0.75 %
        "gradient": [1.0, -2.16],  # 0.08 of the largest entry
        "devices": 2,
        "ran_on": ["gpu:0", "gpu:1"],
        "shares_on_first_device": shares,
        "shares_repeat_on_first_device": repeat,
    }
    cmp = tg.compare(one, noisy, 1e-3)
    assert cmp["repeat_gradient_max_rel_diff"] == pytest.approx(0.05)
    assert cmp["repeat_rollout_values_median_rel_diff"] == pytest.approx(0.005)
    assert cmp["rollout_values_vs_shares_median_rel_diff"] == pytest.approx(0.0075)
    assert tg.failures({"comparison": cmp, "all": noisy}) == []  # within 2 x the floor: 0.1 and 1 %
    scrambled = {**noisy, "values": [8.0, 4.0, 2.0, 1.0]}  # rows gathered out of order
    assert tg.failures({"comparison": tg.compare(one, scrambled, 1e-3), "all": scrambled}) == [
        "the 2-device rollouts' values differ from the same shares on one device by 0.938 in the median"
        " (bound 2 x the shares' own repeat, 0.01)"
    ]
    far = {**noisy, "gradient": [1.0, -2.3]}
    assert tg.failures({"comparison": tg.compare(one, far, 1e-3), "all": far}) == [
        "the 2-device gradient differs from the same shares on one device by 0.15 of its largest entry"
        " (bound 2 x the shares' own repeat, 0.1)"
    ]
    broken = {**noisy, "shares_repeat_on_first_device": {**repeat, "gradient": [float("nan"), -2.0]}}
    assert tg.failures({"comparison": tg.compare(one, broken, 1e-3), "all": broken})[0].startswith(
        "the shares' repeat on one device is not finite"
    )
