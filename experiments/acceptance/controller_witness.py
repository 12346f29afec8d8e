"""results/limit/controller_<body>.json: the tracking controller's own trajectory as a witness of the limit (issue 43).

The limit is the largest impulse from which some torque trajectory recovers; the controller's own (zero feedforward)
is one. Where a controller envelope (results/limit/envelopes, judged by the envelope job) lies above every optimiser's
limit in results/limit/limit.json, this replays that controller alone at its envelope impulse through the limit's own
judge (C MuJoCo, float64, the strict criterion, a batch of its own: ``limit_ddp.CrossCheck.replay_alone`` with zero
feedforward). A pass is a witness like any other: the file has the cross-check files' format, its optimiser named
``"<gain set> controller (u = 0)"`` (``limit_table.ddp_label``); its bracket's upper end is the envelope's own first
failed impulse. Directions where an optimiser already reached the envelope are not replayed. limit.json only picks
the directions (the replay reads none of its limits), so it is no input of the result; it is refolded with it.

    python experiments/acceptance/controller_witness.py --body root_link
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

import numpy as np

from wbc_jax.core import io, loader, provenance
from wbc_jax.jobs import limit_ddp

LIMIT_JSON = pathlib.Path("results/limit/limit.json")
ENVELOPES = pathlib.Path("results/limit/envelopes")
OWN = " controller (u = 0)"  # the optimiser's name of a controller witness, after its gain set
GAIN_SETS = {
    "tuned": ("tuned_gradient", "experiments/gains/tuned_gradient.json")
}  # the gain sets whose trajectory is replayed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--body", default="chest", choices=("chest", "root_link"))
    parser.add_argument("--gain-set", default="tuned", choices=sorted(GAIN_SETS))
    parser.add_argument("--out", help="default: results/limit/controller_<body>.json")
    args = parser.parse_args()
    out = pathlib.Path(args.out or f"results/limit/controller_{args.body}.json")
    name, gains = GAIN_SETS[args.gain_set]
    table = loader.read_json(LIMIT_JSON, "limit table")["bodies"][args.body]["directions"]
    envelope_file = ENVELOPES / f"{name}_{args.body}" / "summary.json"
    envelope = loader.read_json(envelope_file, "envelope summary")["envelope"]["0"]

    def optimisers_best(row: dict) -> float:  # the optimisers' limit, not a controller witness of an earlier run
        found = {k: v for k, v in (row.get("limit_by_optimiser_ns") or {}).items() if not k.endswith(OWN)}
        return max(found.values(), default=0.0)

    above = sorted(float(a) for a, r in table.items() if envelope[a]["impulse_ns"] > optimisers_best(r) + 1e-9)
    if not above:
        sys.exit(
            f"{args.body}: every limit in {LIMIT_JSON} is at or above the {args.gain_set} envelope; nothing to replay"
        )
    cfg = limit_ddp.DdpConfig(directions=tuple(above), body=args.body, gains=gains)
    cfg.check()
    check = limit_ddp.CrossCheck(cfg)
    zero = np.zeros((check.k1 - check.k0 + check.T, len(check.map.joints)))
    t0, directions = time.perf_counter(), {}
    for i, az in enumerate(above):
        impulse, upper = envelope[str(az)]["impulse_ns"], envelope[str(az)]["bracket_ns"][1]
        replay = {
            "impulse_ns": impulse,
            "how": "controller alone (zero feedforward)",
            **check.replay_alone(i, impulse, zero),
        }
        print(az, impulse, replay["verified"], replay["failed"], flush=True)
        directions[str(az)] = {
            "limit_ns": impulse if replay["verified"] else 0.0,
            "bracket_ns": [impulse, upper] if replay["verified"] else [0.0, impulse],
            "controller_envelopes_ns": {k: v["impulse_ns"] for k, v in table[str(az)]["envelopes"].items()},
            "limit_replayed_alone": replay,
        }
    io.atomic_write_json(
        out,
        {
            "what": f"the {args.gain_set} controller's own trajectory (zero feedforward) replayed alone through the limit's "
            "C MuJoCo judge at its envelope impulse, where that envelope lies above every optimiser's limit; "
            "limit_ns: the impulse if it passed (0: it did not); bracket_ns: [limit, the envelope's first failed impulse]",
            "optimiser": f"{args.gain_set}{OWN}",
            "commands": ["python experiments/acceptance/controller_witness.py " + " ".join(sys.argv[1:])],
            "config": json.loads(json.dumps({k: getattr(cfg, k) for k in cfg.__dataclass_fields__})),
            "directions": directions,
            "wall_s": round(time.perf_counter() - t0, 1),
            "provenance": provenance.record({"gains": gains, "envelope": str(envelope_file)}),
        },
    )
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
