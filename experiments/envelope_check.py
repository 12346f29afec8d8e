"""The bisection envelope against a grid sweep's (issue: GPU throughput, adaptive envelope mode).

    python experiments/envelope_check.py --grid SWEEP_DIR --out runs/envelope_check -- [sweep flags]

Runs ``wbc_jax.jobs.envelope.search`` on the grid's settings (its magnitudes, directions, horizon...;
the sweep flags after ``--`` change them, e.g. the backend; gain set 0 unless --gain-sets is
given) to 0.25 N s and compares each direction with the grid's monotone envelope: the largest
difference, the grid step, the directions where the search's grid bracket is the grid's, and the
rollouts of each. Writes envelope_check.json and bisection.json.
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
from wbc_jax.core import io
from wbc_jax.jobs import envelope, sweep
from wbc_jax.sim import runner

ROOT = pathlib.Path(__file__).resolve().parent.parent


def main(argv=None) -> dict:
    argv = sys.argv[1:] if argv is None else argv
    split = argv.index("--") if "--" in argv else len(argv)
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
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
    result = {**comparison, "bisection_rollouts": found["rollouts"], "grid_rollouts": grid_rollouts,
              "rollout_ratio": grid_rollouts * cfg.gain_sets / found["rollouts"], "rounds": found["rounds"],
              "run_s": found["run_s"], "compile_s": found["compile_s"], "backend": found["backend"],
              "command": "python experiments/envelope_check.py " + " ".join(argv)}  # fmt: skip
    out = pathlib.Path(args.out)
    io.atomic_write_json(out / "envelope_check.json", result)
    io.atomic_write_json(out / "bisection.json", found)
    print(json.dumps({k: v for k, v in result.items() if k != "directions"}), flush=True)
    return result


if __name__ == "__main__":
    main()
