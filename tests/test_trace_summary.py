"""benchmarks/trace_summary.py (issue 46): a profiler trace summed per op and attributed to the op's source
function, each op's time counted once (a CPU while loop's thunk holds its body's)."""

import time
import types

import jax
import jax.numpy as jnp
import pytest
from conftest import load_script


def heavy(a):
    return ((a @ a) @ a) @ (a @ a)  # four (n, n) products: most of the program's time


def light(a):
    return a * 0.999 + 0.001  # one cheap elementwise fusion


def program(a):
    b = jax.lax.fori_loop(0, 3, lambda i, x: light(x), a)  # a while loop whose body's ops nest in its own event
    return heavy(b)


@pytest.fixture(scope="module")
def traced(tmp_path_factory):
    ts = load_script("benchmarks/trace_summary.py")
    fn = jax.jit(jax.vmap(program))
    x = jnp.ones((4, 192, 192), jnp.float32) * 0.01
    jax.block_until_ready(fn(x))
    where = tmp_path_factory.mktemp("trace")
    t0 = time.perf_counter()
    with jax.profiler.trace(str(where), create_perfetto_trace=True):
        for _ in range(3):
            jax.block_until_ready(fn(x))
    wall = time.perf_counter() - t0
    return ts.summarize(where, fn.lower(x).compile().as_text(), calls=3, batch=4), wall


def test_time_goes_to_the_function_that_spends_it(traced):
    summary, _ = traced
    assert summary["timeline"] == "cpu" and summary["ops_without_source"] == 0
    top = summary["by_function"][0]
    assert top["name"].endswith("tests/test_trace_summary.py:heavy")
    assert top["share"] > 0.5, summary["by_function"]
    assert any(f["name"].endswith(":light") for f in summary["by_function"])
    assert summary["by_opcode"][0]["name"] == "dot", summary["by_opcode"]


def test_each_op_counted_once(traced):
    summary, wall = traced
    total_s = summary["total_us_per_env"] * summary["calls"] * 4 * 1e-6
    assert 0 < total_s <= wall  # nested ops (the loop's body inside its while) not counted twice
    assert sum(f["us_per_env"] for f in summary["by_file"]) == pytest.approx(summary["total_us_per_env"], rel=1e-3)
    loop = [o for o in summary["by_opcode"] if o["name"] == "while"]
    assert not loop or loop[0]["share"] < 0.2  # the while's own time excludes its body


def test_profile_tick_traces_its_programs_own_ops(tmp_path):
    """profile_tick's --trace path (trace_tick): the program traced at the loop's precision, its ops attributed."""
    pt = load_script("benchmarks/profile_tick.py")
    loop = types.SimpleNamespace(cfg=types.SimpleNamespace(matmul_precision="highest"))
    x = jnp.ones((4, 192, 192), jnp.float32) * 0.01
    summary = pt.trace_tick(pt.staged(loop, program), (x,), tmp_path, batch=4)
    assert summary["command_buffers"] == "n/a" and summary["calls"] == pt.TRACE_CALLS
    assert 0 < summary["wall_us_per_env"] < 1e6  # the traced program timed untraced: four 192^3 products an env
    assert summary["by_function"][0]["name"].endswith("tests/test_trace_summary.py:heavy"), summary["by_function"]


def test_op_times_counts_a_gpu_kernel_whole_where_the_clock_overlaps_it_with_the_next(tmp_path):
    """GPU kernels on one stream run one after another, but the trace's rounded timestamps can start a kernel a
    fraction of a µs before the last one ends (results/gpu_h100/s58): that is not nesting, and each kernel keeps its
    whole time (counted as nested, the first lost the second's and the H100 tick's ops summed to half its busy time).
    A kernel wholly inside another's span still nests."""
    import gzip
    import json

    ts = load_script("benchmarks/trace_summary.py")

    def event(start, dur, op):
        return {
            "ph": "X",
            "pid": 7,
            "tid": 1,
            "ts": start,
            "dur": dur,
            "name": op,
            "args": {"hlo_op": op, "hlo_module": "jit_f"},
        }

    events = [
        {"ph": "M", "name": "process_name", "pid": 7, "args": {"name": "/device:GPU:0"}},
        event(0.0, 25.345, "a"),
        event(25.217, 7.584, "b"),  # starts 0.128 µs before a ends
        event(32.673, 40.0, "c"),  # and c 0.128 µs before b ends
        event(40.0, 5.0, "d"),  # wholly inside c: nested
    ]
    where = tmp_path / "plugins" / "profile" / "run"
    where.mkdir(parents=True)
    with gzip.open(where / "host.perfetto_trace.json.gz", "wt") as f:
        json.dump({"traceEvents": events}, f)
    timeline, times = ts.op_times(tmp_path, "jit_f")
    assert timeline == "gpu"
    assert times == pytest.approx({"a": 25.345, "b": 7.584, "c": 35.0, "d": 5.0})


def test_device_idle_splits_calls_and_sums_the_pauses_between_kernels(tmp_path):
    """device_idle on a GPU timeline written by hand: two calls of kernels a and b (a copy without an HLO op after
    b in the first) a long host pause apart; the device's idle time is the pauses within the calls."""
    import gzip
    import json

    ts = load_script("benchmarks/trace_summary.py")

    def kernel(start, dur, op=None, name="k", tid=1):
        args = {"hlo_op": op, "hlo_module": "jit_f"} if op else {}
        return {"ph": "X", "pid": 7, "tid": tid, "ts": start, "dur": dur, "name": name, "args": args}

    events = [
        {"ph": "M", "name": "process_name", "pid": 7, "args": {"name": "/device:GPU:0"}},
        {"ph": "M", "name": "process_name", "pid": 1, "args": {"name": "/host:CPU"}},
        {"ph": "X", "pid": 1, "tid": 1, "ts": 0, "dur": 5000, "name": "host work", "args": {}},
        kernel(0, 10, "a"),
        kernel(15, 10, "b"),
        kernel(20, 2, "c", tid=2),  # on another stream, inside b: no pause of its own
        kernel(25, 2, name="MemcpyDtoH"),
        kernel(1030, 10, "a"),
        kernel(1050, 10, "b"),
    ]
    where = tmp_path / "plugins" / "profile" / "run"
    where.mkdir(parents=True)
    with gzip.open(where / "host.perfetto_trace.json.gz", "wt") as f:
        json.dump({"traceEvents": events}, f)
    idle = ts.device_idle(tmp_path, calls=2, label=str.upper)
    assert idle["calls_found"] == 2 and idle["pauses_per_call"] == 1.0
    assert idle["span_us_per_call"] == pytest.approx((27 + 30) / 2)
    assert idle["busy_us_per_call"] == pytest.approx((22 + 20) / 2)
    assert idle["idle_us_per_call"] == pytest.approx((5 + 10) / 2)
    assert idle["largest_idle"] == [{"between": "A -> B", "us_per_call": 7.5}]
    assert idle["events_without_op"] == [{"name": "MemcpyDtoH", "us_per_call": 1.0}]
    assert ts.device_idle(tmp_path, calls=1, label=str)["idle_us_per_call"] == pytest.approx(5 + 1003 + 10)


def test_device_idle_finds_calls_by_the_programs_first_op_where_the_gpu_waits_longer_inside_a_call(tmp_path):
    """A pause inside a call (a while loop's predicate read on the host) longer than the host's pause between two
    calls: the calls are split where the first op (a) runs again, not at the longest pause."""
    import gzip
    import json

    ts = load_script("benchmarks/trace_summary.py")
    gpu = {"ph": "M", "name": "process_name", "pid": 7, "args": {"name": "/device:GPU:0"}}

    def kernel(start, op):
        return {"ph": "X", "pid": 7, "tid": 1, "ts": start, "dur": 10, "name": "k", "args": {"hlo_op": op}}

    events = [gpu, kernel(0, "a"), kernel(500, "b"), kernel(520, "a"), kernel(1000, "b")]
    where = tmp_path / "t"
    where.mkdir()
    with gzip.open(where / "x.perfetto_trace.json.gz", "wt") as f:
        json.dump({"traceEvents": events}, f)
    idle = ts.device_idle(tmp_path, calls=2)
    assert idle["calls_found"] == 2 and idle["idle_us_per_call"] == pytest.approx((490 + 470) / 2)
    assert idle["largest_idle"] == [{"between": "a -> b", "us_per_call": 480.0}]


def test_device_idle_is_none_without_a_gpu_timeline(traced, tmp_path):
    summary, _ = traced
    assert summary["device_idle"] is None  # the CPU's threads overlap: no single device timeline to find pauses in


def test_a_module_is_matched_by_its_name_or_xlas_suffixes_of_it():
    ts = load_script("benchmarks/trace_summary.py")
    assert ts.same_module("jit_tick", "jit_tick") and ts.same_module("jit_tick.1", "jit_tick")
    assert ts.same_module("jit_tick(3)", "jit_tick")
    assert not ts.same_module("jit_ticker", "jit_tick") and not ts.same_module("jit_other", "jit_tick")


def test_by_scope_sums_a_kept_trace_per_jax_scope_without_the_hlo_text(tmp_path):
    """A trace kept from a GPU run (gpu_run.sh keep_trace) read back on its own: each op's time under the JAX scope
    that named it, XLA's own fusions apart, µs per environment and call; the total is every op's time once."""
    import gzip
    import json

    ts = load_script("benchmarks/trace_summary.py")

    def kernel(start, dur, op, name=None):
        args = {"hlo_op": op, "hlo_module": "jit_tick", **({"name": name} if name else {})}
        return {"ph": "X", "pid": 7, "tid": 1, "ts": start, "dur": dur, "name": op, "args": args}

    events = [
        {"ph": "M", "name": "process_name", "pid": 7, "args": {"name": "/device:GPU:0"}},
        kernel(0, 30, "lu.1", "jit(tick)/vmap(force_distribution)/lu"),
        kernel(29.9, 10, "trsm.2", "jit(tick)/vmap(torque_law)/jit(_cho_solve)/triangular_solve"),
        kernel(40, 20, "loop_fusion.3"),
        kernel(100, 30, "lu.1", "jit(tick)/vmap(force_distribution)/lu"),
    ]
    where = tmp_path / "plugins" / "profile" / "run"
    where.mkdir(parents=True)
    with gzip.open(where / "host.perfetto_trace.json.gz", "wt") as f:
        json.dump({"traceEvents": events}, f)
    summary = ts.by_scope(tmp_path, "jit_tick", calls=2, batch=5)
    assert summary["by_scope"] == pytest.approx(
        {"vmap(force_distribution)": 6.0, "vmap(torque_law)": 1.0, "(fusion)": 2.0}
    )
    assert summary["total_us_per_env"] == pytest.approx(9.0)
    assert summary["kernels_per_call"] == 2.0
    ops = ts.by_scope(tmp_path, "jit_tick", calls=2, batch=5, depth=3)["by_scope"]
    assert ops == pytest.approx(
        {"vmap(force_distribution)/lu": 6.0, "vmap(torque_law)/jit(_cho_solve)/triangular_solve": 1.0, "(fusion)": 2.0}
    )
