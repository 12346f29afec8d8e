"""What the queue's machinery costs by itself (issue: GPU throughput, retire-and-refill).

    python benchmarks/queue_overhead.py --out runs/queue_overhead -- [push-sweep flags]

Runs the sweep's scenarios as one batch three ways in one process, each timed twice after its
compile: the plain program, and the queue program (``runner._run_mjx_queue``) with one
scenario per slot, checking every 25 ticks and every 100: no robot is refilled there, so any
difference from the plain program is the queue's own cost (segments, hand-ins, resets). Writes
queue_overhead.json.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

import numpy as np

from wbc_jax import cli
from wbc_jax.core import io, provenance
from wbc_jax.jobs import sweep
from wbc_jax.robot import model
from wbc_jax.sim import runner, scenario


def main(argv=None) -> dict:
    given = argv
    argv = sys.argv[1:] if argv is None else argv
    split = argv.index("--") if "--" in argv else len(argv)
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="runs/queue_overhead")
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--variants", nargs="+", default=["plain", "queue1_check25", "queue1_check100"])
    args = p.parse_args(argv[:split])
    cfg = cli.push_sweep_config(argv[split + 1 :])
    runner.enable_compilation_cache()
    dtype = scenario.float_dtype()
    n = model.load_robot("icub").index.n  # the robot run_sweep loads
    base = sweep.base_gains(cfg, n, dtype)  # the sweep's own: --gains or the defaults
    st = sweep.make_setup(cfg, base)
    scen, _ = sweep.build_scenarios(cfg, base, n, dtype)
    variants = {
        "plain": lambda: runner.run(st, scen),
        "queue1_check25": lambda: runner._run_mjx_queue(st, scen, 1, 25),
        "queue1_check100": lambda: runner._run_mjx_queue(st, scen, 1, 100),
    }
    result = {
        "n_envs": cfg.size,
        "backend": st.loop.backend,
        "device": provenance.device_label(),
        "provenance": provenance.record(
            {"gains": cfg.gains, "tasks": cfg.controller.tasks}, argv=provenance.script_argv(__file__, given)
        ),
    }
    for name in args.variants:
        fn = variants[name]
        runs = [fn() for _ in range(args.repeats + 1)]
        survived = [float(np.mean(~np.asarray(r.metrics.fell) & ~np.asarray(r.metrics.nan))) for r in runs]
        result[name] = {"compile_s": runs[0].compile_s, "run_s": [r.run_s for r in runs], "upright_rate": survived}
        print(name, json.dumps(result[name]), flush=True)
    out = pathlib.Path(args.out)
    io.atomic_write_json(out / "queue_overhead.json", result)
    return result


if __name__ == "__main__":
    main()
