"""Are the survival islands of a push sweep numerical artefacts? Compare the same grid run with
different numerics or engines (the ``agree`` and ``regrid`` jobs of ``experiments/gpu_run.sh``; on
2026-11-23 float32 with 4 and 8 Newton iterations and float64 with 4, results/sweep_h100/islands/).

    python experiments/checks/island_check.py SWEEP_DIR [SWEEP_DIR ...] --out FILE

For each sweep (default gain set): directions where survival is not monotone in magnitude, the
transition band per direction (last survived minus first failed magnitude, in grid steps), and the
cells whose outcome differs from the first sweep (the reference) with their distance, in grid
steps, from the reference's transition band in their direction: the magnitudes from its first
failure to its last survival (either order: in a monotone direction they are one step apart).

The check (:func:`failures`): every cell that differs from the reference lies within
``--max-steps`` (default 1) grid steps of the reference's transition band (numerics may move
outcomes near the fall boundary, nowhere else); exit status 1 otherwise. (Until 2026-11-25 the
band was the union over all the sweeps compared, which holds every differing cell by
construction: the "outside_the_transition_band" of earlier records is 0 whatever the sweeps.)
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

import numpy as np
import pandas as pd

from wbc_jax.core import checks, io, provenance

MAX_STEPS = 1.0


def bar(max_steps: float = MAX_STEPS) -> str:
    return f"every cell that differs from the first sweep within {max_steps:g} x the grid step of its transition band"


def failures(result: dict, max_steps: float = MAX_STEPS) -> list[str]:
    """The sweeps with a differing cell further than ``max_steps`` from the reference's band."""
    out = [
        f"{name}: {f['outside_the_first_sweeps_band']} differing cells outside the first sweep's transition band, "
        f"the furthest {f['max_steps_from_the_first_sweeps_band']:g} grid steps from it (> {max_steps:g})"
        for name, f in result["flips"].items()
        if not f["max_steps_from_the_first_sweeps_band"] <= max_steps
    ]
    return out if result["flips"] else ["one sweep only: nothing compared (give two or more)"]


def transition(t: pd.DataFrame, step: float) -> tuple[dict, dict]:
    """({azimuth: (first failed, last survived) magnitude}, statistics) of one sweep's table."""
    band, islands = {}, 0
    for az, g in t.groupby("azimuth_deg"):
        s, m = g.survived.to_numpy(), g.magnitude_n.to_numpy()
        first_fail = m[np.argmax(~s)] if (~s).any() else np.inf
        last_survived = m[s].max() if s.any() else -np.inf
        band[float(az)] = (float(first_fail), float(last_survived))
        islands += int(s[m > first_fail].sum())
    width = [(hi - lo) / step for lo, hi in band.values()]
    stats = {
        "survival_rate": float(t.survived.mean()),
        "directions_not_monotone": int(sum(w > 0 for w in width)),
        "island_cells": islands,  # survived cells above the first failure of their direction
        "max_band_steps": float(max(width)),
    }
    return band, stats


def steps_from_band(magnitude: float, first_fail: float, last_survived: float, step: float) -> float:
    """Grid steps from ``magnitude`` to the band between a direction's first failure and last
    survival (0 inside; a direction that never fails or never survives: its one edge)."""
    edges = [e for e in (first_fail, last_survived) if np.isfinite(e)]
    lo, hi = min(edges), max(edges)
    return max(lo - magnitude, magnitude - hi, 0.0) / step


def compare(reference: pd.DataFrame, other: pd.DataFrame, band: dict, step: float) -> dict:
    """The cells of ``other`` whose outcome differs from ``reference`` (same grid, same order), and
    how far from the reference's transition band they lie."""
    if not (
        np.array_equal(reference.azimuth_deg, other.azimuth_deg)
        and np.allclose(reference.magnitude_n, other.magnitude_n)
    ):
        raise ValueError("the sweeps do not cover the same grid (directions and magnitudes)")
    diff = reference[reference.survived.to_numpy() != other.survived.to_numpy()]
    steps = [steps_from_band(r.magnitude_n, *band[float(r.azimuth_deg)], step) for r in diff.itertuples()]
    return {
        "cells_differing": int(len(diff)),
        "outside_the_first_sweeps_band": int(sum(d > 1e-9 for d in steps)),
        "max_steps_from_the_first_sweeps_band": float(max(steps, default=0.0)),
    }


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=f"Check: {bar()} (--max-steps); exit status 1 otherwise.",
    )
    parser.add_argument("sweeps", nargs="+")
    parser.add_argument("--max-steps", type=float, default=MAX_STEPS, help="the bar, in grid steps")
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    if not args.max_steps >= 0:
        parser.error(f"--max-steps must be >= 0, got {args.max_steps}")
    tables = {}
    for path in args.sweeps:
        if pathlib.Path(path).name in tables:
            parser.error(f"two sweeps named {pathlib.Path(path).name!r}: their folders must have different names")
        t = pd.read_parquet(pathlib.Path(path) / "results.parquet")
        tables[pathlib.Path(path).name] = (
            t[t.gain_set == 0].sort_values(["azimuth_deg", "magnitude_n"]).reset_index(drop=True)
        )
    mags = np.sort(next(iter(tables.values())).magnitude_n.unique())
    step = float(mags[1] - mags[0])
    per_sweep, bands = {}, {}
    for name, t in tables.items():
        bands[name], per_sweep[name] = transition(t, step)
    first = next(iter(tables))
    flips = {name: compare(tables[first], t, bands[first], step) for name, t in tables.items() if name != first}
    inputs = {f"sweep:{pathlib.Path(path).name}": pathlib.Path(path) / "results.parquet" for path in args.sweeps}
    result = {
        "grid_step_n": step,
        "n_cells": int(len(tables[first])),
        "reference": first,
        "sweeps": per_sweep,
        "flips": flips,
        "provenance": provenance.record(inputs, argv=provenance.script_argv(__file__, argv), with_device=False),
    }
    result["check"] = checks.verdict(failures(result, args.max_steps), bar(args.max_steps))
    io.atomic_write_json(pathlib.Path(args.out), result)
    print(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    sys.exit(checks.exit_status(main()))
