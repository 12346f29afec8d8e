"""results/limit/limit.json and limit.png: the physical limit of push recovery per pushed body and
direction (``wbc-jax limit`` runs), the LIP bound and the strict envelopes of the default, hand-set
and tuned gain sets (``wbc-jax envelope`` runs in results/limit/envelopes), as fractions of the limit.

    python experiments/acceptance/limit_table.py --chest runs/limit_chest --root-link runs/limit_root_link \
        [--ddp-chest results/limit/ddp_chest.json ...] [--ddp-root-link results/limit/ddp_root_link.json ...]

A body without its limit run keeps its envelopes and LIP bound; ``missing`` in the file names the
command that fills its limit in.
"""

import argparse
import json
import pathlib
import sys

from wbc_jax.core import io
from wbc_jax.jobs import limit_table

ENVELOPES = pathlib.Path("results/limit/envelopes")
GAIN_SETS = {"default": "default", "hand-set": "com_critical_100", "tuned": "tuned_gradient"}
COMMANDS = {
    body: f"bash experiments/gpu_run.sh {job} (one H100), then python experiments/acceptance/limit_table.py "
    f"--{flag} $OUT/limit_{body}"
    for body, job, flag in (("chest", "limit", "chest"), ("root_link", "limit_root", "root-link"))
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--chest", help="output folder of the chest limit run (its summary.json)")
    parser.add_argument("--root-link", help="output folder of the root_link limit run")
    parser.add_argument(
        "--ddp-chest",
        nargs="+",
        default=(),
        help="the chest's crocoddyl cross-checks (experiments/acceptance/ddp_limit.py), one per setting",
    )
    parser.add_argument(
        "--ddp-root-link",
        nargs="+",
        default=(),
        help="root_link's crocoddyl cross-checks (ddp_limit.py --body root_link)",
    )
    parser.add_argument("--out", default="results/limit")
    args = parser.parse_args()
    bodies = {}
    for body, run, ddp in (("chest", args.chest, args.ddp_chest), ("root_link", args.root_link, args.ddp_root_link)):
        summary = None if run is None else pathlib.Path(run) / "summary.json"
        if summary is not None and not summary.exists():
            sys.exit(
                f"{run}: no summary.json (a call cut off mid-round?); write it from the rounds saved there with "
                f"the job's command of experiments/gpu_run.sh plus --time-limit 0 --out {run}"
            )
        if summary is not None:  # keep the run's summary beside the table
            kept = pathlib.Path(args.out) / f"limit_{body}.json"
            io.atomic_write_bytes(kept, summary.read_bytes())
            summary = kept
        bodies[body] = {
            "limit": summary,
            "envelopes": {label: ENVELOPES / f"{name}_{body}" / "summary.json" for label, name in GAIN_SETS.items()},
            "ddp": ddp,
        }
    try:
        result = limit_table.write(args.out, bodies, COMMANDS, "icub")
    except ValueError as err:
        sys.exit(str(err))
    medians = {body: b["medians"] for body, b in result["bodies"].items()}
    print(json.dumps({"medians": medians, "targets": result["targets"]}, indent=1))


if __name__ == "__main__":
    main()
