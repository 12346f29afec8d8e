"""benchmarks/trace_summary.py (issue 46): a profiler trace summed per op and attributed to the op's source
function, each op's time counted once (a CPU while loop's thunk holds its body's)."""

import sys
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
    sys.modules.setdefault("trace_summary", load_script("benchmarks/trace_summary.py"))
    sys.modules.setdefault("loop_timing", load_script("benchmarks/loop_timing.py"))
    pt = load_script("benchmarks/profile_tick.py")
    loop = types.SimpleNamespace(cfg=types.SimpleNamespace(matmul_precision="highest"))
    x = jnp.ones((4, 192, 192), jnp.float32) * 0.01
    summary = pt.trace_tick(pt.staged(loop, program), (x,), tmp_path, batch=4)
    assert summary["command_buffers"] == "n/a" and summary["calls"] == pt.TRACE_CALLS
    assert summary["by_function"][0]["name"].endswith("tests/test_trace_summary.py:heavy"), summary["by_function"]
