"""Are the survival islands of a push sweep numerical artefacts? Compare the same grid run with
different numerics (``bash experiments/gpu_run.sh islands``: float32 with 4 and 8 Newton
iterations, float64 with 4).

    python experiments/island_check.py SWEEP_DIR [SWEEP_DIR ...] --out FILE

For each sweep (default gain set): directions where survival is not monotone in magnitude, the
transition band per direction (last survived minus first failed magnitude, in grid steps), and the
cells whose outcome differs from the first sweep, with whether they lie inside the band (the
magnitudes between the lowest first failure and the highest survival over all the sweeps).
"""

from __future__ import annotations

import argparse
import json
import pathlib

import numpy as np
import pandas as pd

from wbc_jax.core import io


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sweeps", nargs="+")
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    tables = {}
    for path in args.sweeps:
        t = pd.read_parquet(pathlib.Path(path) / "results.parquet")
        tables[pathlib.Path(path).name] = (
            t[t.gain_set == 0].sort_values(["azimuth_deg", "magnitude_n"]).reset_index(drop=True)
        )
    mags = np.sort(next(iter(tables.values())).magnitude_n.unique())
    step = float(mags[1] - mags[0])
    per_sweep, bands = {}, {}
    for name, t in tables.items():
        band, islands = {}, 0
        for az, g in t.groupby("azimuth_deg"):
            s, m = g.survived.to_numpy(), g.magnitude_n.to_numpy()
            first_fail = m[np.argmax(~s)] if (~s).any() else np.inf
            last_survived = m[s].max() if s.any() else -np.inf
            band[float(az)] = (float(first_fail), float(last_survived))
            islands += int(s[m > first_fail].sum())
        bands[name] = band
        width = [(hi - lo) / step for lo, hi in band.values()]
        per_sweep[name] = {
            "survival_rate": float(t.survived.mean()),
            "directions_not_monotone": int(sum(w > 0 for w in width)),
            "island_cells": islands,  # survived cells above the first failure of their direction
            "max_band_steps": float(max(width)),
        }
    first = next(iter(tables))
    flips = {}
    for name, t in tables.items():
        if name == first:
            continue
        a = tables[first]
        diff = a[a.survived.to_numpy() != t.survived.to_numpy()]
        outside = 0
        for _, row in diff.iterrows():
            lo = min(b[float(row.azimuth_deg)][0] for b in bands.values())
            hi = max(b[float(row.azimuth_deg)][1] for b in bands.values())
            outside += not (lo - 1e-9 <= row.magnitude_n <= hi + 1e-9)
        flips[name] = {"cells_differing_from_" + first: int(len(diff)), "outside_the_transition_band": int(outside)}
    result = {"grid_step_n": step, "n_cells": int(len(tables[first])), "sweeps": per_sweep, "flips": flips,
              "command": "python experiments/island_check.py " + " ".join(args.sweeps) + f" --out {args.out}"}  # fmt: skip
    io.atomic_write_json(pathlib.Path(args.out), result)
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
