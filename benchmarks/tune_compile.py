"""Where the gradient program's build time goes: trace (Python: jaxpr of value_and_grad(vmap(
closed loop))), lowering (StableHLO) and XLA compilation, then two timed steps.

    python benchmarks/tune_compile.py --batch 4 --horizon 1.0 [--no-seed-carry] [--checkpoint none]
        [--solver-iterations 2] [--mode grad|forward] [--no-compile] [--cache DIR] [--out FILE]

Prints one JSON line (appended to --out): trace_s, lower_s, stablehlo_lines, compile_s, hlo_lines,
hlo_while_loops, step1_s, step2_s, physics_steps_per_s (with gradient, second step), the machine
load. On a 2-core CPU, run it with XLA_FLAGS="--xla_backend_optimization_level=0
--xla_llvm_disable_expensive_passes=true".
"""

from __future__ import annotations

import argparse
import json
import os
import time


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--batch", type=int, default=4)
    p.add_argument("--horizon", type=float, default=1.0)
    p.add_argument("--no-seed-carry", action="store_true", help="the closed loop's own rollout (no seeded carry)")
    p.add_argument("--checkpoint", default="tick", choices=("tick", "none"))
    p.add_argument("--solver-iterations", type=int, default=None)
    p.add_argument("--mode", default="grad", choices=("grad", "forward"))
    p.add_argument("--no-compile", action="store_true", help="trace and lower only")
    p.add_argument("--cache", default=None, help="persistent compilation cache folder (a second run reads it)")
    p.add_argument("--out", default=None, help="append the JSON line to this file")
    args = p.parse_args()
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")
    import jax
    import numpy as np
    from jax.sharding import Mesh

    from wbc_jax.core import provenance
    from wbc_jax.sim import runner
    from wbc_jax.tuning import config
    from wbc_jax.tuning.algorithms import estimators, gradient, objectives
    from wbc_jax.tuning.algorithms import problem as tp

    if args.cache:
        runner.enable_compilation_cache(args.cache)
    tp.SEED_CARRY = not args.no_seed_carry
    short = args.horizon < 0.6
    tc = config.TuneConfig(
        batch=args.batch,
        horizon=args.horizon,
        push_onset=0.0 if short else 0.2,
        duration_range=(0.02, 0.05) if short else (0.05, 0.3),
        eval_horizon=max(args.horizon, 0.6),
        checkpoint=args.checkpoint,
        solver_iterations=args.solver_iterations,
    )
    problem = tp.make_problem(tc)
    p0 = problem.init_params()
    scen = jax.device_put(objectives.cast_batch(gradient.training_batch(problem, 0)[0], problem.setup.dtype))
    if args.mode == "grad":  # the training's gradient program on one device: per-rollout value and gradient
        one_device = Mesh(np.asarray(jax.devices()[:1]), ("batch",))
        f = objectives.make_rollout_grads(problem, one_device).program
        fargs = (estimators.repeated(p0, tc.batch), scen)
    else:
        loss = tp.make_batched_loss(problem, fixed_solver=False)
        f, fargs = jax.jit(lambda q, s: loss(*problem.controls(q), s)[0]), (p0, scen)
    res = {
        "mode": args.mode,
        "batch": args.batch,
        "horizon_s": args.horizon,
        "seed_carry": tp.SEED_CARRY,
        "checkpoint": args.checkpoint,
        "solver_iterations": problem.iterations,
        "device": provenance.device_label(),
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "cache": args.cache,
    }
    t0 = time.perf_counter()
    traced = f.trace(*fargs)
    res["trace_s"] = round(time.perf_counter() - t0, 1)
    t0 = time.perf_counter()
    lowered = traced.lower()
    res["lower_s"] = round(time.perf_counter() - t0, 1)
    res["stablehlo_lines"] = lowered.as_text().count("\n")
    if not args.no_compile:
        t0 = time.perf_counter()
        compiled = lowered.compile()
        res["compile_s"] = round(time.perf_counter() - t0, 1)
        text = compiled.as_text()
        res["hlo_lines"], res["hlo_while_loops"] = text.count("\n"), text.count(" while(")
        for k in (1, 2):
            t0 = time.perf_counter()
            jax.block_until_ready(compiled(*fargs))
            res[f"step{k}_s"] = round(time.perf_counter() - t0, 2)
        res["physics_steps_per_s"] = round(args.batch * problem.steps_per_rollout / res["step2_s"], 1)
    res["load_avg"] = round(os.getloadavg()[0], 2)
    res["provenance"] = provenance.record()
    line = json.dumps(res)
    print(line, flush=True)
    if args.out:
        with open(args.out, "a") as fh:
            fh.write(line + "\n")


if __name__ == "__main__":
    main()
