"""Time one push sweep several times in one process (issue: GPU throughput, "know what you measure").

    python benchmarks/sweep_timing.py --out runs/sweep_timing --repeats 2 -- [push-sweep flags]

Runs ``wbc-jax push-sweep`` with the given flags ``--repeats`` times, each into its own folder
(same compiled programs), and reports each run's compile and run seconds: the first run pays the
one-time costs (compilation, loading the programs onto the device); the later ones the sweep
alone. Writes timing.json and the first run's summary and plots into --out.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import shutil
import sys
import time

from wbc_jax import cli
from wbc_jax.core import io, provenance
from wbc_jax.jobs import sweep
from wbc_jax.sim import runner


def main(argv=None) -> dict:
    given = argv
    argv = sys.argv[1:] if argv is None else argv
    split = argv.index("--") if "--" in argv else len(argv)
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="runs/sweep_timing")
    p.add_argument("--repeats", type=int, default=2)
    args = p.parse_args(argv[:split])
    base = cli.push_sweep_config(argv[split + 1 :])
    runner.enable_compilation_cache()
    out = pathlib.Path(args.out)
    runs = []
    for k in range(args.repeats):
        target = out / f"run_{k}"
        shutil.rmtree(target, ignore_errors=True)
        t0 = time.perf_counter()
        s = sweep.run_sweep(dataclasses.replace(base, out=str(target)), progress=False)
        runs.append(
            {
                "repeat": k,
                "compile_s": s["compile_s"],
                "run_s": s["run_s"],
                "wall_s": round(time.perf_counter() - t0, 2),
                "physics_steps_per_s": s["physics_steps_per_s"],
                "survival_rate": s["survival_rate"],
                "physics_steps_simulated": s.get("physics_steps_simulated"),
                "upright_rate": s["upright_rate"],
            }
        )
        print(json.dumps(runs[-1]), flush=True)
    first = out / "run_0"
    for name in ("summary.json", "survival.png", "envelope.png"):
        shutil.copy(first / name, out / name)
    s = json.loads((first / "summary.json").read_text())
    result = {
        "runs": runs,
        "n_envs": s["n_envs"],
        "backend": s["backend"],
        "device": s["device"],
        "provenance": provenance.record(
            {"gains": base.gains, "tasks": base.controller.tasks}, argv=provenance.script_argv(__file__, given)
        ),
    }
    io.atomic_write_json(out / "timing.json", result)
    print(json.dumps(result), flush=True)
    return result


if __name__ == "__main__":
    main()
