"""docs/limit/ddp_chest.json: the crocoddyl cross-check of the chest limit (issue 43), on the CPU.

Per direction, a bisection over the impulse (:func:`wbc_jax.jobs.limit_ddp.bisect`): crocoddyl's
BoxFDDP from the C MuJoCo post-push state, tracked in C MuJoCo by the tuned controller with
feedforward torques and judged by the limit's strict criterion. It starts at the tuned controller's
envelope and is capped at the flywheel bound (both from docs/limit/limit.json). The file is
rewritten after every bisection step, so a cut-off run keeps what it measured.

    python experiments/acceptance/ddp_chest.py [--tests 4] [--max-iterations 40]
"""

import argparse
import json
import pathlib
import sys
import time

import numpy as np

from wbc_jax.core import io, provenance
from wbc_jax.jobs import limit, limit_ddp

LIMIT_JSON = pathlib.Path("docs/limit/limit.json")
GAINS = "experiments/gains/tuned_gradient.json"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--directions", type=float, nargs="+", default=[0.0, 90.0, 180.0, 270.0])
    parser.add_argument("--tests", type=int, default=4, help="impulses tested per direction")
    parser.add_argument("--max-iterations", type=int, default=40, help="DDP iterations per solve")
    parser.add_argument("--out", default="docs/limit/ddp_chest.json")
    args = parser.parse_args()
    table = json.loads(LIMIT_JSON.read_text())["bodies"]["chest"]["directions"]
    missing = [a for a in args.directions if str(float(a)) not in table]
    if missing:
        sys.exit(
            f"--directions {missing}: not in {LIMIT_JSON} (its chest directions: {sorted(map(float, table))[:8]}...)"
        )
    cfg = limit_ddp.DdpConfig(directions=tuple(args.directions), body="chest", gains=GAINS, tests=args.tests,
                              max_iterations=args.max_iterations)  # fmt: skip
    cfg.check()
    rows = [table[str(float(a))] for a in args.directions]
    start = np.array([r["envelopes"]["tuned"]["impulse_ns"] for r in rows])
    cap = np.array([r["flywheel_bound_ns"] for r in rows])
    t0 = time.perf_counter()
    check = limit_ddp.CrossCheck(cfg)
    command = "python experiments/acceptance/ddp_chest.py " + " ".join(sys.argv[1:])

    def write(tested):
        directions = {}
        for a, row, tests in zip(args.directions, rows, tested, strict=True):
            lo, hi = limit.bracket([(r["impulse_ns"], r["verified"]) for r in tests])
            directions[str(float(a))] = {
                "limit_ns": lo, "bracket_ns": [lo, None if np.isinf(hi) else hi],
                "controller_envelopes_ns": {k: v["impulse_ns"] for k, v in row["envelopes"].items()},
                "mjx_limit_ns": row["limit_ns"], "flywheel_bound_ns": row["flywheel_bound_ns"],
                "lip_bound_ns": row["lip_bound_ns"],
                "tests": [{k: v for k, v in r.items()} for r in tests],
            }  # fmt: skip
        io.atomic_write_json(pathlib.Path(args.out), {
            "what": "crocoddyl BoxFDDP from the C MuJoCo post-push state, tracked in C MuJoCo by the tuned controller "
                    "with feedforward torques, strict criterion; limit_ns: the largest impulse whose tracked DDP "
                    "trajectory passed (0: none did); bracket_ns: [limit, smallest failed impulse above it]",
            "command": command, "config": {k: getattr(cfg, k) for k in cfg.__dataclass_fields__},
            "directions": directions, "wall_s": round(time.perf_counter() - t0, 1),
            "steps_done": min(len(t) for t in tested), "provenance": provenance.record({"gains": GAINS}),
        })  # fmt: skip
        print(f"{time.perf_counter() - t0:.0f} s:", {a: (t[-1]["impulse_ns"], t[-1]["verified"])
                                                    for a, t in zip(args.directions, tested, strict=True)}, flush=True)  # fmt: skip

    limit_ddp.bisect(check, start, cap, on_test=write)


if __name__ == "__main__":
    main()
