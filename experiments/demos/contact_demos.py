"""Non-coplanar contacts (issue: general task hierarchy, demonstration 3; Nori et al. 2015).

1. Both feet on the floor and the left hand on a table (experiments/tasks/hand_on_table.yaml),
   desired normal hand force 5 N: the measured (MuJoCo) hand force against the desired one, the
   QP constraints at every contact, the CoM.
2. Push envelope with and without the hand: the same push sweep (chest pushes, 0.1 s) with the
   hand contact and with the feet alone (experiments/tasks/feet_contacts.yaml: same posture, same
   force distribution); the envelope gain per direction is the ratio of the largest impulses
   survived below the first failure.

    python experiments/demos/contact_demos.py --out results/contacts            # GPU: a few minutes
    python experiments/demos/contact_demos.py --duration 2 --magnitudes 100 300 2 --directions 1  # CPU check

Writes OUT/demos.json, OUT/hand_on_table/ (balance run: metrics, trajectory, plots) and
OUT/sweep_hand/, OUT/sweep_feet/ (push sweeps).
"""

from __future__ import annotations

import argparse
import json
import pathlib

import numpy as np

from wbc_jax.core import io, options, provenance
from wbc_jax.jobs import balance, sweep, sweep_config

EXPERIMENTS = pathlib.Path(__file__).resolve().parents[1]
HAND = EXPERIMENTS / "tasks" / "hand_on_table.yaml"
FEET = EXPERIMENTS / "tasks" / "feet_contacts.yaml"


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="runs/contacts")
    p.add_argument("--duration", type=float, default=10.0, help="s of the hand-on-table balance run")
    p.add_argument("--magnitudes", type=float, nargs=3, default=[20.0, 600.0, 30], metavar=("LO", "HI", "N"))
    p.add_argument("--directions", type=int, default=8, help="number of azimuths over 360 deg")
    p.add_argument("--horizon", type=float, default=3.0)
    args = p.parse_args(argv)
    out = pathlib.Path(args.out)

    run = balance.run(task="stand", duration=args.duration, tasks=str(HAND), out=str(out / "hand_on_table"))
    print(json.dumps(run["contacts"]), flush=True)

    lo, hi, n = args.magnitudes
    grid = dict(
        magnitudes=tuple(float(x) for x in np.linspace(lo, hi, int(n))),
        directions=tuple(float(x) for x in np.arange(args.directions) * 360.0 / args.directions),
        horizon=args.horizon,
        push_onset=0.5,
        push_duration=0.1,
        chunk_size=512,
    )
    sweeps = {}
    for name, spec in (("hand", HAND), ("feet", FEET)):
        cfg = options.replace(sweep_config.SweepConfig(**grid, out=str(out / f"sweep_{name}")), tasks=str(spec))
        sweeps[name] = sweep.run_sweep(cfg)
    envelope = {}
    for az in sweeps["feet"]["envelope"]:
        feet = sweeps["feet"]["envelope"][az]["monotone_impulse_ns"]
        hand = sweeps["hand"]["envelope"][az]["monotone_impulse_ns"]
        envelope[az] = {"feet_impulse_ns": feet, "hand_impulse_ns": hand, "gain": hand / feet if feet > 0 else None}
    result = {
        "device": provenance.device_label(),
        "provenance": provenance.record({"hand": HAND, "feet": FEET}, argv=provenance.script_argv(__file__, argv)),
        "hand_on_table": {
            k: run[k]
            for k in (
                "fell",
                "com_rmse_m",
                "max_constraint_violation",
                "qp_infeasible_ticks",
                "max_foot_slip_m",
                "force_rel_err_median",
                "contacts",
                "duration_s",
                "device",
            )
        },
        "push_envelope": envelope,
        "survival_rate": {k: v["survival_rate"] for k, v in sweeps.items()},
        "max_qp_violation_hand_sweep": None,
        "grid": grid,
    }
    import pandas as pd

    table = pd.read_parquet(out / "sweep_hand" / "results.parquet")
    result["max_qp_violation_hand_sweep"] = float(table["max_constraint_violation"].max())
    io.atomic_write_json(out / "demos.json", result)
    print(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
