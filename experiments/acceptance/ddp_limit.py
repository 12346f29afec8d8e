"""results/limit/ddp_<body>.json: the crocoddyl cross-check of the limit (issue 43), on the CPU.

Per direction, a bisection over the impulse (:func:`wbc_jax.jobs.limit_ddp.bisect`): crocoddyl's
BoxFDDP from the C MuJoCo post-push state, tracked in C MuJoCo by the tuned controller with
feedforward torques and judged by the limit's strict criterion. It starts at the best impulse known
to pass there (every controller envelope and the limit in results/limit/limit.json: a test below it
cannot raise the limit) and is capped at the flywheel bound. Directions run ``--batch`` at a time;
the file is rewritten atomically after every bisection step, and a rerun with the same ``--out``
resumes: directions already tested keep their tests (and continue if ``--tests`` grew), new
``--directions`` are added.

    nice -n 15 python experiments/acceptance/ddp_limit.py --body chest --directions 157.5 191.25 [--tests 4]
"""

import argparse
import io as io_
import json
import pathlib
import sys
import time

import numpy as np

from wbc_jax.core import io, loader, provenance
from wbc_jax.jobs import limit, limit_ddp

LIMIT_JSON = pathlib.Path("results/limit/limit.json")
GAINS = "experiments/gains/tuned_gradient.json"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--body", default="chest", choices=("chest", "root_link"))
    parser.add_argument("--directions", type=float, nargs="+", required=True, help="azimuths [deg] of limit.json")
    parser.add_argument("--tests", type=int, default=4, help="impulses tested per direction")
    parser.add_argument("--max-iterations", type=int, default=40, help="DDP iterations per solve")
    parser.add_argument("--cop-scale", type=float, default=1.0, help="the DDP's CoP rectangle / the controller's")
    parser.add_argument("--batch", type=int, default=4, help="directions per batch (one C MuJoCo replay batch)")
    parser.add_argument("--out", help="default: results/limit/ddp_<body>.json")
    parser.add_argument(
        "--recheck",
        nargs="*",
        type=float,
        metavar="AZ",
        help="each direction's limit again in a batch of its own (these azimuths; none: all): the "
        "stored witness replayed, or (none stored) solved and replayed anew",
    )
    args = parser.parse_args()
    out = pathlib.Path(args.out or f"results/limit/ddp_{args.body}.json")
    if args.batch < 1:
        sys.exit(f"--batch must be >= 1, got {args.batch}")
    table = json.loads(LIMIT_JSON.read_text())["bodies"][args.body]["directions"]
    missing = [a for a in args.directions if str(float(a)) not in table]
    if missing:
        sys.exit(
            f"--directions {missing}: not in {LIMIT_JSON} (its {args.body} directions: "
            f"{', '.join(sorted(table, key=float))})"
        )
    previous = loader.read_json(out, "crocoddyl cross-check") if out.exists() else None
    try:
        settings = dict(
            body=args.body, gains=GAINS, tests=args.tests, max_iterations=args.max_iterations, cop_scale=args.cop_scale
        )
        done = limit_ddp.resumed_tests(previous, limit_ddp.DdpConfig(**settings), out)
        azimuths = sorted(set(done) | {float(a) for a in args.directions})
        cfg = limit_ddp.DdpConfig(directions=tuple(azimuths), **settings)
        cfg.check()
    except ValueError as err:
        sys.exit(str(err))
    rows = {a: table[str(a)] for a in azimuths}
    witness_path = limit_ddp.witness_path(out)  # the verified tests' replayed torques
    witnesses = dict(np.load(witness_path)) if witness_path.exists() else {}
    alone = {
        float(a): r["limit_replayed_alone"]
        for a, r in (previous or {}).get("directions", {}).items()
        if r.get("limit_replayed_alone")
    }
    tested = {a: list(done.get(a, [])) for a in azimuths}
    command = "python experiments/acceptance/ddp_limit.py " + " ".join(sys.argv[1:])
    commands = (previous or {}).get("commands", [(previous or {}).get("command")] if previous else [])
    wall0, t0 = (previous or {}).get("wall_s", 0.0), time.perf_counter()
    parts = (previous or {}).get("parts")  # a merged file (ddp_merge.py): this run becomes one more part

    def write() -> None:
        directions = {}
        for a in azimuths:
            if not tested[a]:
                continue
            row = rows[a]
            lo, hi = limit.bracket([(r["impulse_ns"], r["verified"]) for r in tested[a]])
            directions[str(a)] = {
                "limit_ns": lo,
                "bracket_ns": [lo, None if np.isinf(hi) else hi],
                "controller_envelopes_ns": {k: v["impulse_ns"] for k, v in row["envelopes"].items()},
                "mjx_limit_ns": (row.get("limit_by_optimiser_ns") or {}).get("mjx"),
                "flywheel_bound_ns": row["flywheel_bound_ns"],
                "lip_bound_ns": row["lip_bound_ns"],
                "tests": tested[a],
            }
            if a in alone and alone[a]["impulse_ns"] == lo:
                directions[str(a)]["limit_replayed_alone"] = alone[a]
        record, run_s = provenance.record({"gains": GAINS}), round(time.perf_counter() - t0, 1)
        doc = {
            "what": "crocoddyl BoxFDDP from the C MuJoCo post-push state, tracked in C MuJoCo by the tuned controller "
            "with feedforward torques, strict criterion; limit_ns: the largest impulse whose tracked DDP "
            "trajectory passed (0: none did); bracket_ns: [limit, smallest failed impulse above it]",
            "commands": commands + [command],
            "config": {k: getattr(cfg, k) for k in cfg.__dataclass_fields__},
            "directions": directions,
            "wall_s": round(wall0 + run_s, 1),
        }
        if parts is not None:
            this_run = {"file": out.name, "wall_s": run_s, "device": record["device"]["label"], "provenance": record}
            doc["parts"] = [*parts, this_run]
        io.atomic_write_json(out, {**doc, "provenance": record})

    order = list(dict.fromkeys([float(a) for a in args.directions] + azimuths))  # as given first, then the file's
    if args.recheck is not None:
        check = limit_ddp.CrossCheck(cfg)
        for i, a in enumerate(azimuths):
            lo = limit.bracket([(r["impulse_ns"], r["verified"]) for r in tested[a]])[0]
            if lo == 0.0 or (args.recheck and a not in args.recheck):
                continue
            key = f"{a}:{lo!r}"
            if key in witnesses:
                alone[a] = {"impulse_ns": lo, "how": "witness replayed", **check.replay_alone(i, lo, witnesses[key])}
            else:
                rec = check.run(np.array([i]), np.array([lo]))[0]
                rec.pop("feedforward")
                alone[a] = {"how": "solved and replayed", **rec}
            print(a, lo, alone[a]["how"], alone[a]["verified"], alone[a]["failed"], flush=True)
            write()
        return
    todo = [a for a in order if len(tested[a]) < cfg.tests]
    print(f"{out}: {len(azimuths) - len(todo)} of {len(azimuths)} directions done; next {todo}", flush=True)
    for i in range(0, len(todo), args.batch):
        part = todo[i : i + args.batch]
        check = limit_ddp.CrossCheck(limit_ddp.DdpConfig(directions=tuple(part), **settings))
        start = np.array(
            [max([rows[a]["limit_ns"] or 0.0] + [e["impulse_ns"] for e in rows[a]["envelopes"].values()]) for a in part]
        )
        cap = np.array([rows[a]["flywheel_bound_ns"] for a in part])

        def on_test(batch_tests, part=part):
            for a, tests in zip(part, batch_tests, strict=True):
                tested[a] = tests
                u = tests[-1].pop("feedforward", None)
                if u is not None and tests[-1]["verified"]:
                    witnesses[f"{a}:{tests[-1]['impulse_ns']!r}"] = u
            buffer = io_.BytesIO()
            np.savez_compressed(buffer, **witnesses)
            io.atomic_write_bytes(witness_path, buffer.getvalue())
            write()
            print(
                f"{time.perf_counter() - t0:.0f} s:",
                {a: (round(tested[a][-1]["impulse_ns"], 2), tested[a][-1]["verified"]) for a in part},
                flush=True,
            )

        limit_ddp.bisect(check, start, cap, [tested[a] for a in part], on_test=on_test)


if __name__ == "__main__":
    main()
