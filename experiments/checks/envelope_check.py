"""The bisection envelope against a grid sweep's (issue: GPU throughput, adaptive envelope mode).

    python experiments/checks/envelope_check.py --grid SWEEP_DIR --out runs/envelope_check -- [sweep flags]

Runs ``wbc_jax.jobs.envelope.search`` on the grid's settings (its magnitudes, directions, horizon...;
the sweep flags after ``--`` change them, e.g. the backend; gain set 0 unless --gain-sets is
given) to 0.25 N s and compares each direction with the grid's monotone envelope: the largest
difference, the grid step, the directions where the search's grid bracket is the grid's, and the
rollouts of each. Writes envelope_check.json and bisection.json. The check (:func:`failures`): the
search within one grid step of the grid's monotone envelope in every direction; exit status 1
otherwise.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import sys

import numpy as np
import pandas as pd

from wbc_jax import cli
from wbc_jax.core import checks, io, provenance
from wbc_jax.jobs import envelope, sweep
from wbc_jax.sim import runner

BAR = "the bisection's envelope within one grid step of the grid's monotone envelope in every direction"


def failures(result: dict) -> list[str]:
    """The directions where the search and the grid's monotone envelope differ by more than one
    grid step (recomputed from each direction, not read from ``within_one_grid_step``)."""
    step = result["grid_step_ns"]
    out = [
        f"{az} deg: bisection {r['bisection_ns']:.3f} N s, grid {r['grid_monotone_ns']:.3f} N s: "
        f"{abs(r['difference_ns']):.3f} N s apart > one grid step {step:.3f} N s"
        for az, r in result["directions"].items()
        if not abs(r["bisection_ns"] - r["grid_monotone_ns"]) <= step + 1e-9
    ]
    return out if result["directions"] else ["no direction compared"]


def main(argv=None) -> dict:
    given = argv
    argv = sys.argv[1:] if argv is None else argv
    split = argv.index("--") if "--" in argv else len(argv)
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog=f"Check: {BAR}; exit status 1 otherwise.")
    p.add_argument("--grid", required=True, help="a finished push sweep of the same settings")
    p.add_argument("--resolution", type=float, default=0.25)
    p.add_argument("--out", default="runs/envelope_check")
    args = p.parse_args(argv[:split])
    grid_cfg, grid_summary = sweep.load_sweep(args.grid)
    parsed = cli.build_parser().parse_args(["push-sweep", *argv[split + 1 :]])
    cfg = dataclasses.replace(cli.config_from_args(parsed, dataclasses.replace(grid_cfg, gain_sets=1)), out=None)
    cfg.check()
    table = pd.read_parquet(pathlib.Path(args.grid) / "results.parquet")
    grid_rollouts = int((table["gain_set"] == 0).sum())
    impulses = np.sort(table["impulse_ns"].unique())
    step = float(np.median(np.diff(impulses)))
    runner.enable_compilation_cache()
    found = envelope.search(cfg, resolution=args.resolution, progress=False)
    comparison = envelope.compare_with_grid(found, grid_summary, step)
    result = {
        **comparison,
        "bisection_rollouts": found["rollouts"],
        "grid_rollouts": grid_rollouts,
        "rollout_ratio": grid_rollouts * cfg.gain_sets / found["rollouts"],
        "rounds": found["rounds"],
        "run_s": found["run_s"],
        "compile_s": found["compile_s"],
        "backend": found["backend"],
        "device": provenance.device_label(),
        "provenance": provenance.record(
            {"grid": pathlib.Path(args.grid) / "results.parquet", "gains": cfg.gains, "tasks": cfg.controller.tasks},
            argv=provenance.script_argv(__file__, given),
        ),
    }
    result["check"] = checks.verdict(failures(result), BAR)
    out = pathlib.Path(args.out)
    io.atomic_write_json(out / "envelope_check.json", result)
    io.atomic_write_json(out / "bisection.json", found)
    print(json.dumps({k: v for k, v in result.items() if k != "directions"}), flush=True)
    return result


if __name__ == "__main__":
    sys.exit(checks.exit_status(main()))
