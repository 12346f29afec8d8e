"""Where the closed loop's time goes on a GPU, the physics included (issue 46): benchmark.py's loop traced.

benchmarks/profile_tick.py times the controller's stages alone; the settings that change the physics' side of a tick
(``--warp-terms step1``: the first step split into MuJoCo Warp's ``step1`` and ``step2`` around the controller) are
seen only in the loop itself. This runs benchmark.py's closed loop (the stand task, ``--horizon`` s, one 40 N push per
environment) once to compile, then once under the JAX profiler, and sums the trace's GPU kernels per JAX scope
(benchmarks/trace_summary.py ``by_scope``) and per kernel (``by_kernel``, with the device's busy time: copies on a copy
engine overlap the kernels, so the sums over-count them), in µs per environment and control tick:

    python benchmarks/loop_trace.py --batch 65536 --backend warp --qp-engine warp_active_set --warp-terms step1 \\
        --out runs/loop_trace

Writes ``loop_trace.json`` and keeps the Perfetto trace in ``--out``.
"""

import argparse
import json
import pathlib


def parse_args(argv=None) -> argparse.Namespace:
    from loop_timing import add_qp_arguments, add_warp_terms_argument, check_qp_arguments

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--batch", type=int, default=1024)
    p.add_argument("--backend", default="warp", choices=("jax", "warp"))
    p.add_argument("--horizon", type=float, default=0.5, help="simulated seconds")
    p.add_argument("--push-onset", type=float, default=0.2, help="s")
    p.add_argument("--push-duration", type=float, default=0.1, help="s")
    p.add_argument("--depth", type=int, default=3, help="scopes below the program's in each key (trace_summary)")
    p.add_argument("--out", default="runs/loop_trace")
    add_qp_arguments(p)
    add_warp_terms_argument(p)
    a = p.parse_args(argv)
    check_qp_arguments(p, a)
    if a.batch < 1 or a.depth < 1 or not a.horizon > 0:
        p.error(f"--batch and --depth must be >= 1 and --horizon > 0, got {a.batch}, {a.depth}, {a.horizon}")
    return a


def main(argv=None) -> dict:
    a = parse_args(argv)
    import jax
    from loop_timing import make_setup, push_batch
    from trace_summary import by_kernel, by_scope

    from wbc_jax.core import io, provenance
    from wbc_jax.sim import runner

    runner.enable_compilation_cache()
    st = make_setup(
        a.backend,
        a.horizon,
        None,
        qp_unrolled_steps=a.qp_unrolled_steps,
        qp_engine=a.qp_engine,
        warp_terms=a.warp_terms if a.backend == "warp" else "jax",
        mass_solve_engine=a.mass_solve_engine,
        ritz_engine=a.ritz_engine,
    )
    scen = push_batch(st, a.batch, a.push_onset, a.push_duration)
    first = runner.run(st, scen)  # compiled here
    out = pathlib.Path(a.out)
    trace_dir = out / "trace"
    with jax.profiler.trace(str(trace_dir), create_perfetto_trace=True):
        traced = runner.run(st, scen)
    ticks = st.loop.n_ticks
    summary = by_scope(trace_dir, "jit_one", calls=1, batch=a.batch, depth=a.depth)
    result = {
        "batch": a.batch,
        "backend": a.backend,
        "qp_engine": st.loop.controller.config.qp_engine,  # as resolved here
        "warp_terms": st.loop.warp_terms,
        "mass_solve_engine": st.loop.controller.config.mass_solve_engine,
        "ritz_engine": a.ritz_engine,
        "ticks": ticks,
        "physics_steps_per_tick": st.loop.n_sub,
        "run_s": {"untraced": round(first.run_s, 4), "traced": round(traced.run_s, 4)},
        "us_per_env_and_tick": {
            "total": round(summary["total_us_per_env"] / ticks, 5),
            "by_scope": {k: round(v / ticks, 5) for k, v in summary["by_scope"].items()},
        },
        "kernels_per_tick": round(summary["kernels_per_call"] / ticks, 1),
        # per kernel, µs per environment and tick (launches per tick); busy: the union of the device's events
        "by_kernel": _per_tick(by_kernel(trace_dir, "jit_one", calls=1, batch=a.batch), ticks),
        "device": provenance.device_label(),
        "provenance": provenance.record(argv=provenance.script_argv(__file__, argv)),
    }
    print(json.dumps(result, indent=1))
    io.atomic_write_json(out / "loop_trace.json", result)
    return result


def _per_tick(summary: dict, ticks: int) -> dict:
    """trace_summary.by_kernel's figures of one call divided into its ``ticks``."""
    return {
        "sum_us_per_env_and_tick": round(summary["sum_us_per_env"] / ticks, 5),
        "busy_us_per_env_and_tick": None
        if summary["busy_us_per_env"] is None
        else round(summary["busy_us_per_env"] / ticks, 5),
        "kernels": [
            {
                "name": k["name"],
                "us_per_env_and_tick": round(k["us_per_env"] / ticks, 5),
                "per_tick": k["launches"] / ticks,
            }
            for k in summary["kernels"]
        ],
    }


if __name__ == "__main__":
    main()
