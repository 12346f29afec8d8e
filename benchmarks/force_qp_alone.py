"""The tick's force QP alone, cold and warm-started, on one core (issue 46).

    taskset -c 1 python benchmarks/force_qp_alone.py --out runs/force_qp_alone.json [--ticks 1000] [--before REF]

The QPs are the 20 s sinusoid's own (``wbc-jax balance --task sinusoid``, C MuJoCo, recorded; the
first QP of each tick, the engaged feet's equality QP with the tick's momentum-rate reference): its
inputs ``(H, g, C, b)`` are computed once, then :func:`wbc_jax.control.qp.solve_qp` runs alone in
a ``lax.scan`` over them, from the cold start every tick and warm-started from the last tick's
``info.start`` (what ``ControllerConfig.qp_warm_start`` does), and with its iterations capped at
1 and 3 (the cost of a Newton step: the difference over the steps). CPU microseconds per QP, the
median of ``--repeats``, programs interleaved; Newton steps per QP; the warm solutions' distance
to the cold ones, relative to ``1 + max|y|``. One thread of XLA's CPU pool (``PJRT_NPROC=1``).
``--before REF``: the same programs of commit REF's solver on the same QPs, interleaved with these, and
the distance of this checkout's cold solutions to REF's; the XLA kernels of a Newton step (the
while loop's body) of each.
"""

from __future__ import annotations

import os

os.environ.setdefault("PJRT_NPROC", "1")

import importlib
import json
import pathlib
import statistics
import sys
import time
import types

ROOT = pathlib.Path(__file__).resolve().parent.parent


def qp_inputs(ticks: int):
    """(H, g, C, b) stacked over the sinusoid's ticks: the tick's first force QP (the feet's equality QP,
    :func:`wbc_jax.control.forces.equality_qp_data` on the force distribution's inputs of each tick,
    :func:`force_build.distribute_inputs`)."""
    import jax
    import jax.numpy as jnp
    from force_build import distribute_inputs

    from wbc_jax.control import forces

    (cset, settings), stacked, st = distribute_inputs(ticks)
    ones = jnp.ones(len(cset.contacts), st.dtype)

    def qp_of(activation, A, wrench, tt, W_R):
        data = forces.equality_qp_data(cset, ones, A, wrench, tt, W_R, settings)
        return data.H, data.g, data.C, data.b

    with jax.default_matmul_precision(st.loop.cfg.matmul_precision):
        return jax.jit(jax.vmap(qp_of))(*stacked)


def program(data, warm: bool, iterations: int, pkg: str = "wbc_jax"):
    """The compiled scan of solve_qp over the ticks: ``data -> (y (T, n), steps (T,))``, with the
    solver of package ``pkg`` (this checkout's or another commit's, :func:`controller_stages.import_commit`)."""
    import jax
    import jax.numpy as jnp

    qp = importlib.import_module(f"{pkg}.control.qp")

    def run(H, g, C, b):
        def tick(start, x):
            y, info = qp.solve_qp(*x, iterations=iterations, start=start if warm else None)
            return info.start, (y, info.iterations)

        start0 = jnp.full((2, C.shape[1]), jnp.nan, H.dtype)
        return jax.lax.scan(tick, start0, (H, g, C, b))[1]

    return jax.jit(run).lower(*data).compile()


def main(argv=None) -> dict:
    from controller_stages import parse_timing_args, result_header, timing_parser

    argv = list(sys.argv[1:] if argv is None else argv)
    p = timing_parser("force_qp_alone", __doc__, ticks=1000, repeats=15)
    p.add_argument("--before", default=None, help="also time this git commit's solver on the same QPs")
    args = parse_timing_args(p, argv)
    import jax
    import numpy as np

    from wbc_jax.control import qp
    from wbc_jax.core import io
    from wbc_jax.sim import runner

    packages = {"": "wbc_jax"}
    if args.before:  # a bad REF stops here, before anything compiles
        from controller_stages import import_commit

        packages[f"before ({args.before}), "] = import_commit(args.before)
    runner.enable_compilation_cache()
    data = qp_inputs(args.ticks)
    variants = {
        "cold": (False, qp.DEFAULT_ITERATIONS),
        "warm (qp_warm_start)": (True, qp.DEFAULT_ITERATIONS),
        "cold, 1 Newton step": (False, 1),
        "cold, 3 Newton steps": (False, 3),
    }
    variants = {prefix + name: (*v, pkg) for prefix, pkg in packages.items() for name, v in variants.items()}
    compiled = {name: program(data, *v) for name, v in variants.items()}
    results = {name: fn(*data) for name, fn in compiled.items()}
    cpu_us = {name: [] for name in variants}
    for _ in range(args.repeats):  # interleaved: the machine's load reaches every program alike
        for name, fn in compiled.items():
            t0 = time.process_time()
            jax.block_until_ready(fn(*data))
            cpu_us[name].append(1e6 * (time.process_time() - t0) / args.ticks)
    y_cold = np.asarray(results["cold"][0])
    scale = 1.0 + np.max(np.abs(y_cold), axis=1)
    warm_gap = np.max(np.abs(np.asarray(results["warm (qp_warm_start)"][0]) - y_cold), axis=1) / scale

    def per_step(prefix: str) -> float:
        three, one = (statistics.median(cpu_us[f"{prefix}cold, {k} Newton step{'s' * (k > 1)}"]) for k in (3, 1))
        return round((three - one) / 2, 2)

    result = {
        **result_header("force_qp_alone", argv, args, data[0].dtype),
        "qp_size": {"n": int(data[0].shape[1]), "m": int(data[2].shape[1])},
        "cpu_us_per_qp": {
            name: {"median": round(statistics.median(v), 1), "range": [round(min(v), 1), round(max(v), 1)]}
            for name, v in cpu_us.items()
        },
        "newton_steps": {
            name: {"mean": round(float(np.mean(r[1])), 2), "max": int(np.max(r[1]))}
            for name, r in results.items()
            if variants[name][1] == qp.DEFAULT_ITERATIONS
        },
        "cpu_us_per_newton_step": {prefix or "now": per_step(prefix) for prefix in packages},
        "warm_vs_cold_max_relative": float(f"{np.max(warm_gap):.3g}"),
        **(before_figures(results, compiled, packages, y_cold, scale) if args.before else {}),
    }
    io.atomic_write_json(pathlib.Path(args.out), result)
    print(json.dumps({k: v for k, v in result.items() if k != "provenance"}), flush=True)
    return result


def before_figures(results, compiled, packages, y_cold, scale) -> dict:
    """The cold solutions' distance to the ``--before`` commit's, and each solver's kernels a Newton step."""
    import re

    import numpy as np
    from controller_stages import op_counts

    (prefix,) = [p for p in packages if p]
    y_before = np.asarray(results[prefix + "cold"][0])
    gap = np.max(np.abs(y_before - y_cold), axis=1) / scale

    def step_ops(name: str) -> dict:
        # The Newton loop's body: the one computation that calls the LU (getrf).
        (body,) = [c for c in re.split(r"\n(?=\S)", compiled[name].as_text()) if "getrf" in c]
        return op_counts(types.SimpleNamespace(as_text=lambda: body))

    return {
        "cold_vs_before_max_relative": float(f"{np.max(gap):.3g}"),
        "cold_vs_before_median_relative": float(f"{np.median(gap):.3g}"),
        "newton_step_ops": {p or "now": step_ops(p + "cold, 3 Newton steps") for p in packages},
    }


if __name__ == "__main__":
    main()
