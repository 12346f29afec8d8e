"""The diagnostics of issue 45 (why 4 GPUs of MJX-Warp ran slower than one): the sweep's
--warp-graph-cache and scaling.py's --launch / --switch-interval-ms are refused in one line when
wrong, before anything compiles, and reach what runs."""

import argparse
import json
import pathlib

import pytest
from conftest import load_script

from wbc_jax import cli
from wbc_jax.jobs import sweep, sweep_config
from wbc_jax.sim import physics, warp_graphs

scaling = load_script("benchmarks/scaling.py")


def _one_line(capsys) -> str:
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def test_a_bad_warp_graph_cache_is_one_line_before_compiling(tmp_path, capsys):
    out = tmp_path / "sw"
    assert cli.main(["push-sweep", "--warp-graph-cache", "-1", "--out", str(out)]) == 2
    assert _one_line(capsys) == (
        "wbc-jax push-sweep: error: --warp-graph-cache must be a whole number in [0, 100000], got -1"
    )
    # On this CPU --backend auto runs C MuJoCo: a Warp bound there would measure nothing.
    assert cli.main(["push-sweep", "--warp-graph-cache", "8", "--out", str(out)]) == 2
    assert _one_line(capsys) == (
        "wbc-jax push-sweep: error: --warp-graph-cache sets MJX-Warp's CUDA graphs: it needs --backend warp "
        "(--backend auto runs mujoco here)"
    )
    assert cli.main(["push-sweep", "--warp-graph-mode", "jax", "--out", str(out)]) == 2
    assert _one_line(capsys).startswith("wbc-jax push-sweep: error: --warp-graph-mode sets MJX-Warp's CUDA graphs")
    assert not out.exists()
    with pytest.raises(ValueError, match=r"--warp-graph-cache must be a whole number in \[0, 100,?000\].*got True"):
        physics.PhysicsConfig(warp_graph_cache=True)
    # The staged modes share one capture between a process's GPUs: not offered.
    with pytest.raises(
        ValueError, match=r"--warp-graph-mode must be one of \['warp', 'jax', 'none'\], got 'warp_staged'"
    ):
        physics.PhysicsConfig(warp_graph_mode="warp_staged")


def test_the_warp_graph_cache_reaches_the_loop_and_shapes_no_program():
    """The bound travels from the sweep's config into the loop's physics config, and, changing no
    program, leaves the loop's program key (the in-process cache of compiled programs) as it was."""
    plain = sweep.make_setup(sweep_config.SweepConfig(backend="jax"))
    bounded = sweep.make_setup(sweep_config.SweepConfig(backend="jax", warp_graph_cache=7, warp_graph_mode="jax"))
    assert bounded.loop.cfg.physics.warp_graph_cache == 7 and plain.loop.cfg.physics.warp_graph_cache is None
    assert bounded.loop.cfg.physics.warp_graph_mode == "jax"
    bounded = sweep.make_setup(sweep_config.SweepConfig(backend="jax", warp_graph_cache=7))
    assert bounded.loop.structure_key == plain.loop.structure_key
    # Neither enters a run's fingerprint: runs written before these flags existed still resume.
    assert {"warp_graph_cache", "warp_graph_mode"} <= set(sweep_config.SweepConfig.PROCEDURE)
    assert "warp_graph_mode" not in str(sweep_config.SweepConfig(backend="jax").fingerprint())


def test_the_default_bound_gives_each_device_warps_32_graphs(monkeypatch):
    """On one device Warp's own bound is left alone; on N devices, 32 N (four GPUs' sweep held 50
    graphs, which a shared 32 made every call capture again); an asked bound, 0 included, wins."""

    class Callable:  # Warp 1.18's FfiCallable, as far as warp_graphs uses it
        name, graph_cache_max, graph_cache_size = "step", 32, 0

    calls = [Callable(), Callable()]
    monkeypatch.setattr(warp_graphs, "_callables", lambda: calls)
    assert warp_graphs.bound(None, 1) == 0 and [c.graph_cache_max for c in calls] == [32, 32]
    assert warp_graphs.bound(None, 4) == 2 and [c.graph_cache_max for c in calls] == [128, 128]
    assert warp_graphs.bound(7, 4) == 2 and [c.graph_cache_max for c in calls] == [7, 7]
    assert warp_graphs.bound(0, 4) == 2 and [c.graph_cache_max for c in calls] == [None, None]
    assert warp_graphs.default_bound(3) == 96 and warp_graphs.default_bound(1) is None


@pytest.mark.gpu
def test_bound_sets_every_registered_warp_call():
    """On Warp's own registry (warp-lang is installed with the GPU's wheels: the gpu set runs it)."""
    wp = pytest.importorskip("warp")

    def scale(x: wp.array(dtype=float), y: wp.array(dtype=float)):
        pass

    call = wp.jax_callable(scale, num_outputs=1)
    assert call.graph_cache_max == 32  # Warp's default, which the diagnostic replaces
    assert warp_graphs.bound(None) == 0 and call.graph_cache_max == 32
    assert warp_graphs.bound(0) >= 1 and call.graph_cache_max is None
    warp_graphs.bound(5)
    assert warp_graphs.held()[call.name] == {"graphs": 0, "bound": 5}


def test_scaling_launches_threads_or_one_process_per_gpu(tmp_path):
    """--launch processes: one process per GPU (its own CUDA_VISIBLE_DEVICES, jax.distributed ranks
    0..N-1 on one coordinator); threads: one process with the first N GPUs; both carry the switch
    interval and the sweep flags."""
    args = argparse.Namespace(repeats=2, switch_interval_ms=0.5, launch="processes")
    flags = ["--horizon", "1", "--warp-graph-cache", "0"]
    many = scaling.launch(4, tmp_path, flags, args)
    assert [gpus for _, gpus in many] == ["0", "1", "2", "3"]
    settings = [json.loads(cmd[4]) for cmd, _ in many]
    assert [s["distributed"]["process_id"] for s in settings] == [0, 1, 2, 3]
    assert {(s["distributed"]["coordinator"], s["distributed"]["num_processes"]) for s in settings} == {
        (settings[0]["distributed"]["coordinator"], 4)
    }
    assert all(s["switch_interval_ms"] == 0.5 and s["repeats"] == 2 for s in settings)
    assert all(cmd[3] == str(tmp_path) and cmd[5:] == flags for cmd, _ in many)
    for n, launch_kind in ((3, "threads"), (1, "processes")):  # one GPU is one process either way
        [(cmd, gpus)] = scaling.launch(n, tmp_path, flags, argparse.Namespace(**{**vars(args), "launch": launch_kind}))
        assert gpus == ",".join(str(i) for i in range(n)) and json.loads(cmd[4])["distributed"] is None


def test_scaling_refuses_a_bad_switch_interval_before_running(tmp_path):
    with pytest.raises(SystemExit, match=r"^scaling.py: error: --switch-interval-ms must be a number in \[0.01, 100\]"):
        scaling.main(["--out", str(tmp_path / "s"), "--switch-interval-ms", "0", "--", "--horizon", "1"])
    assert not pathlib.Path(tmp_path / "s").exists()


@pytest.mark.slow
def test_scaling_processes_report_the_failing_one(tmp_path, monkeypatch):
    """--launch processes for real (two jax.distributed processes on this CPU, 6 s here: nightly): a sweep
    flag both refuse ends the configuration with one error naming the process and its last line."""
    monkeypatch.setenv("JAX_PLATFORMS", "cpu")
    args = argparse.Namespace(launch="processes", repeats=2, switch_interval_ms=None, timeout=120)
    with pytest.raises(RuntimeError, match=r"^process 0 of 2: rc 2: wbc-jax push-sweep: error: argument --magnitudes"):
        scaling.run_configuration(2, tmp_path / "runs", ["--magnitudes", "-5", "--backend", "jax"], args)


@pytest.mark.gpu
def test_the_callback_cost_counts_the_steps_arguments_and_times_both_paths(tmp_path):
    """benchmarks/warp_callback_cost.py on warp-lang's own structures (the gpu set)."""
    pytest.importorskip("warp")
    cost = load_script("benchmarks/warp_callback_cost.py")
    assert cost.main(["--out", str(tmp_path / "c.json"), "--repeats", "10"]) == 0
    result = json.loads((tmp_path / "c.json").read_text())
    assert result["step_array_arguments"] >= 500  # mujoco-mjx 3.17's step: 559
    assert 0 < result["replay_key_s"] < result["wrap_buffers_s"]  # wrapping makes an object per buffer
