"""Several processes joined by jax.distributed (CPU devices, Gloo) give the one-process results
table (experiments/checks/multihost_check.py), and a failing process fails the comparison."""

import pytest
from conftest import load_script

distributed = load_script("experiments/checks/multihost_check.py")

# 4 magnitudes x 2 directions: 8 envs over 0.6 s, two of which fall (their trajectories amplify
# rounding, so float64: the tables then agree to ~1e-8). The analytic force distribution (no QP)
# compiles in a fraction of the time and is as good a witness of the sharding.
SWEEP = [
    "--magnitudes",
    "20",
    "300",
    "4",
    "--directions",
    "2",
    "--horizon",
    "0.6",
    "--push-onset",
    "0.1",
    "--chunk-size",
    "8",
    "--backend",
    "jax",
    "--forces",
    "analytic",
]
# Compile-time flags only (XLA's own optimisation level): the programs compute the same values.
FAST_COMPILE = {
    "JAX_ENABLE_X64": "1",
    "XLA_FLAGS": "--xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true",
}


@pytest.mark.slow  # two processes compile the sweep side by side (about 250 s on the 2-core CI machine); the
# default set keeps the failing-process comparison and tests/test_reliability_paths.py's join timeout
def test_two_processes_give_the_one_process_table(tmp_path):
    result = distributed.compare_processes(SWEEP, tmp_path, processes=2, env=FAST_COMPILE, timeout_s=900)
    assert result["failures"] == [], result
    assert result["envs"] == 8 and [p["rc"] for p in result["many"]] == [0, 0]
    # The distributed run spanned both processes' devices (one each); the reference ran alone.
    assert result["many_ran_on"] == {"n_devices": 2, "processes": 2}, result
    assert result["one_ran_on"] == {"n_devices": 1, "processes": 1}, result


def test_a_failing_process_fails_the_comparison(tmp_path):
    result = distributed.compare_processes([*SWEEP, "--body", "nose"], tmp_path, processes=2, timeout_s=300)
    assert len(result["failures"]) == 3  # the one-process run and both processes
    assert all("--body 'nose' is not a valid name" in f for f in result["failures"]), result["failures"]


def test_tables_that_differ_are_named():
    pd = pytest.importorskip("pandas")
    a = pd.DataFrame({"env": [0, 1], "survived": [True, False], "com_rmse_m": [1e-3, 2e-3]})
    assert distributed.compare_tables(a, a.copy(), 1e-6, 1e-9) == []
    b = a.copy()
    b.loc[1, "survived"] = True
    b.loc[0, "com_rmse_m"] = 1.1e-3
    problems = distributed.compare_tables(a, b, 1e-6, 1e-9)
    assert problems[0] == "survived: 1 of 2 entries differ" and problems[1].startswith("com_rmse_m: 1 entries")
