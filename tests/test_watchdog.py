"""The watchdog (wbc_jax/sim/watchdog.py): a device that does not finish its share of a chunk is an
error naming the device and the chunk within the bound; each device's waits are timed. The sweep's
own stall and timeline: tests/test_reliability_runs.py."""

import json
import os
import subprocess
import sys
import textwrap

import pytest

from wbc_jax.sim import watchdog

FOUR_DEVICES = textwrap.dedent(
    """
    import json, time
    import jax, numpy as np
    from jax.sharding import Mesh, NamedSharding, PartitionSpec
    from wbc_jax.sim import per_device, watchdog
    devices = jax.devices()
    assert len(devices) == 4, devices
    mesh = Mesh(np.asarray(devices), ("batch",))
    run = per_device.PerDevice(lambda x: x * 2.0 + 1.0, mesh, (True,))
    x = jax.device_put(np.arange(8.0), NamedSharding(mesh, PartitionSpec("batch")))
    run.compile(x)
    out = {}
    watch = watchdog.Watchdog(chunk=5, bound_s=1.5, simulate_stall=(5, 2))
    t0 = time.perf_counter()
    try:
        run(x, watch=watch)
    except watchdog.DeviceStalled as err:
        out["error"], out["error_after_s"] = str(err), time.perf_counter() - t0
    out["stalled_rows"] = watch.rows
    watch = watchdog.Watchdog(chunk=6, bound_s=60.0, simulate_stall=(5, 2))  # another chunk: no stall
    t0 = time.perf_counter()
    out["values"] = run(x, watch=watch, to_host=True).tolist()
    out["wall_s"], out["rows"] = time.perf_counter() - t0, watch.rows
    out["timeline"] = watchdog.timeline_rows(watch, host_s=0.0, wall_s=out["wall_s"])
    print(json.dumps(out))
    """
)


def test_the_default_bound_follows_the_slowest_finished_chunk():
    """max(60 s, 10x the slowest finished chunk); 30 min before any finished; the flag's value as given."""
    assert watchdog.stall_bound(None, []) == watchdog.FIRST_CHUNK_STALL_S == 1800.0
    assert watchdog.stall_bound(None, [1.0, 2.0]) == 60.0
    assert watchdog.stall_bound(None, [2.0, 30.0, 7.0]) == 300.0
    assert watchdog.stall_bound(5.0, [100.0]) == 5.0
    watch = watchdog.Watchdog(chunk=0, bound_s=5.0)
    assert watch.bound("run") == 5.0 and watch.bound("compile") == watch.bound("run", compiles=True) == 1800.0


def test_a_stalled_device_of_four_is_an_error_naming_it_and_the_chunk():
    """Four host CPU devices, one program each (per_device.PerDevice): device 2 blocked in chunk 5 (the
    test hook) gives DeviceStalled naming cpu:2 and chunk 5 after the 1.5 s bound, not a hang; the
    other devices' rows say they finished. Another chunk runs on all four, its values the program's,
    each device's row of waits non-negative and within the call's wall time."""
    env = {
        **os.environ,
        "JAX_PLATFORMS": "cpu",
        "XLA_FLAGS": f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=4",
    }
    proc = subprocess.run([sys.executable, "-c", FOUR_DEVICES], capture_output=True, text=True, timeout=120, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["error"].startswith("chunk 5: device cpu:2 did not finish its run within 1.5 s"), out["error"]
    assert "\n" not in out["error"] and "3 of 4 device(s) did" in out["error"]
    assert 1.5 <= out["error_after_s"] < 5.0, out["error_after_s"]
    assert [(r["device"], r["finished"]) for r in out["stalled_rows"]] == [
        ("cpu:0", True),
        ("cpu:1", True),
        ("cpu:2", False),
        ("cpu:3", True),
    ]
    assert out["values"] == [2.0 * k + 1.0 for k in range(8)]
    assert [r["device"] for r in out["timeline"]] == ["cpu:0", "cpu:1", "cpu:2", "cpu:3"]
    for row in out["timeline"]:
        times = [row[k] for k in watchdog.TIMED]
        assert row["chunk"] == 6 and row["finished"] and min(times) >= 0.0
        assert sum(times) <= out["wall_s"] + 1e-3, row


def test_a_phase_that_is_not_one_is_refused():
    with pytest.raises(ValueError, match=r"phase must be one of \['compile', 'run'\], got 'load'"):
        watchdog.run_watched([("cpu:0", lambda t: 1)], watchdog.Watchdog(chunk=0, bound_s=1.0), "load")
