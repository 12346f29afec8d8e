"""Which test of strict survival ends each direction's envelope (issue: gradient tuning, the 0.8 target).

    python experiments/campaigns/envelope_limits.py NAME=SWEEP_DIR ... --out results/tuning/envelope_limits.json

For each finished push sweep (gain set 0): per direction, the monotone envelope (largest impulse
below the first failure, as a fraction of the LIP bound m w d) under the strict criterion, under
the lax one (upright: no fall, no NaN), and under "upright plus one test" for each test of the
strict criterion (slip, tilt, end speed, end support margin); and which tests fail at the first
strict failure above the envelope. The median / min over directions of each, per sweep.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

import numpy as np
import pandas as pd

from wbc_jax.core import constants, io, provenance
from wbc_jax.jobs import sweep, sweep_table
from wbc_jax.sim import metrics

TESTS = ("slip", "tilt", "end_speed", "end_support_margin")


def limits(run_dir: pathlib.Path) -> dict:
    _, summary = sweep.load_sweep(run_dir)
    table = pd.read_parquet(run_dir / "results.parquet")
    table = table[table["gain_set"] == 0].copy()
    failed = metrics.failed_tests({c: table[c].to_numpy() for c in table.columns})
    for name in TESTS:
        table[f"upright_and_{name}"] = table["upright"].to_numpy() & ~failed[name]
    criteria = ["survived", "upright", *[f"upright_and_{n}" for n in TESTS]]
    per_direction, first_failures = {}, {name: 0 for name in (*TESTS, "not_upright")}
    for az, group in table.groupby("azimuth_deg"):
        bound = summary["envelope"][str(float(az))]["bound_impulse_ns"]
        row = {c: sweep_table.envelope_of(group, c)[1] / bound for c in criteria}
        group = group.sort_values("impulse_ns")
        over = group[~group["survived"].to_numpy()]
        if len(over):
            k = over.index[0]
            row["first_failure_impulse_ns"] = float(over["impulse_ns"].iloc[0])
            row["failed_tests"] = [n for n, f in failed.items() if f[table.index.get_loc(k)]]
            for n in row["failed_tests"]:
                first_failures[n] += 1
        per_direction[float(az)] = row
    fractions = {
        c: {
            "median": float(np.median([r[c] for r in per_direction.values()])),
            "min": float(np.min([r[c] for r in per_direction.values()])),
        }
        for c in criteria
    }
    return {
        "envelope_fraction_of_lip_bound": fractions,
        "tests_failing_at_the_boundary": first_failures,
        "directions": per_direction,
        "survival_rate": float(table["survived"].mean()),
        "upright_rate": float(table["upright"].mean()),
    }


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("sweeps", nargs="+", help="NAME=SWEEP_DIR")
    p.add_argument("--out", default="runs/envelope_limits.json")
    args = p.parse_args(argv)
    result = {"survival_criterion": constants.SURVIVAL_CRITERION, "sweeps": {}}
    for spec in args.sweeps:
        name, _, path = spec.partition("=")
        if not path:
            raise ValueError(f"give sweeps as NAME=SWEEP_DIR, got {spec!r}")
        result["sweeps"][name] = limits(pathlib.Path(path))
    inputs = {
        f"sweep:{name}": pathlib.Path(path) / "results.parquet"
        for name, _, path in (x.partition("=") for x in args.sweeps)
    }
    result["provenance"] = provenance.record(inputs, argv=provenance.script_argv(__file__, argv), with_device=False)
    io.atomic_write_json(pathlib.Path(args.out), result)
    brief = {
        n: {**s["envelope_fraction_of_lip_bound"], "at_boundary": s["tests_failing_at_the_boundary"]}
        for n, s in result["sweeps"].items()
    }
    print(json.dumps(brief, indent=1))
    return result


if __name__ == "__main__":
    try:
        main()
    except (ValueError, FileNotFoundError) as err:
        sys.exit(f"error: {err}")
