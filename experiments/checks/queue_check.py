"""Does a queued sweep (``--queue L``: fallen robots retired, their slots refilled) give the plain
sweep's outcomes? Compare sweeps of the same grid, environment by environment.

    python experiments/checks/queue_check.py PLAIN_DIR QUEUED_DIR [QUEUED_DIR ...] --out FILE

Each folder is a push-sweep output (results.parquet, summary.json), or a sweep_timing.py output
(outcomes from its ``run_0``, run seconds from its last repeat, which pays no one-time costs).
For each other sweep: the environments whose outcome (survived, upright, fell, nan) differs from
the plain sweep's, and whether each lies inside its (gain set, direction) transition band of the
plain sweep (the magnitudes between the lowest one that failed and the highest one that held); the
run seconds and the physics steps simulated against the plain sweep's. The floors to read the
differences against: the plain sweep's own repeat (same program: the device's nondeterminism),
and a plain sweep compiled at another chunk size passed as one of the others (another program:
float32 rounding alone, amplified where the closed loop is chaotic).

The check (:func:`failures`): against the plain sweep, no other sweep (nor the plain sweep's own
repeat) has a NaN outcome that differs, and none has more than ``--max-differ`` (default 1.5 %) of its
environments with a survived or upright outcome that differs: the floor measured on the H200 (Warp,
float32) is 0.9-1.2 % (BENCHMARKS.md, 2026-11-24). Exit status 1 otherwise.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

import numpy as np
import pandas as pd

from wbc_jax.core import checks, io, provenance

OUTCOMES = ("survived", "upright", "fell", "nan")
MAX_DIFFER = 0.015  # of the environments: a survived or upright outcome that differs from the plain sweep's


def bar(max_differ: float = MAX_DIFFER) -> str:
    return (
        f"no NaN outcome differs from the plain sweep's, and at most {100 * max_differ:g} % of the environments' "
        "survived or upright outcomes do (each other sweep, and the plain sweep's repeat)"
    )


def failures(result: dict, max_differ: float = MAX_DIFFER) -> list[str]:
    """Each comparison with the plain sweep (its repeat, each other sweep) over the bar."""
    n = result["plain"]["n_envs"]
    compared = (
        [("the plain sweep's repeat", result["plain"]["repeat_outcomes"])]
        if "repeat_outcomes" in result["plain"]
        else []
    )
    compared += [(q["dir"], q["outcomes"]) for q in result["queued"]]
    out = []
    for name, outcomes in compared:
        if outcomes["nan"]["differ"]:
            out.append(f"{name}: {outcomes['nan']['differ']} environments differ in NaN outcome")
        for column in ("survived", "upright"):
            rate = outcomes[column]["differ"] / n
            if not rate <= max_differ:
                out.append(
                    f"{name}: {outcomes[column]['differ']} of {n} {column} outcomes differ "
                    f"({100 * rate:.2f} % > {100 * max_differ:g} %)"
                )
    return out


def load(path: str, repeat: int = 0) -> tuple[pd.DataFrame, dict]:
    """(results sorted by env, summary with ``run_s`` of the last repeat) of a sweep folder."""
    d = pathlib.Path(path)
    summary = json.loads(((d / "run_0" if (d / "run_0").exists() else d) / "summary.json").read_text())
    if (d / "timing.json").exists():
        summary["run_s"] = json.loads((d / "timing.json").read_text())["runs"][-1]["run_s"]
    return pd.read_parquet(results_path(d, repeat)).sort_values("env"), summary


def results_path(path, repeat: int = 0) -> pathlib.Path:
    """The results table of a sweep folder (a sweep_timing.py folder: its repeat's)."""
    d = pathlib.Path(path)
    return (d / f"run_{repeat}" if (d / f"run_{repeat}" / "results.parquet").exists() else d) / "results.parquet"


def in_band(plain: pd.DataFrame, row, column: str) -> bool:
    """Is ``row``'s magnitude inside its group's transition band for ``column`` in the plain sweep?"""
    g = plain[(plain.gain_set == row.gain_set) & (plain.azimuth_deg == row.azimuth_deg)]
    held, failed = g.magnitude_n[g[column]], g.magnitude_n[~g[column]]
    if held.empty or failed.empty:
        return False
    return bool(failed.min() <= row.magnitude_n <= held.max())


def compare(plain: pd.DataFrame, queued: pd.DataFrame) -> dict:
    if not np.array_equal(plain.env.to_numpy(), queued.env.to_numpy()):
        raise ValueError("the sweeps do not cover the same environments")
    out = {}
    for column in OUTCOMES:
        differ = plain[column].to_numpy() != queued[column].to_numpy()
        rows = plain[differ]
        inside = [in_band(plain, r, column) for r in rows.itertuples()] if column in ("survived", "upright") else []
        out[column] = {
            "differ": int(differ.sum()),
            "inside_band": int(sum(inside)),
            "rate_plain": float(plain[column].mean()),
            "rate_queued": float(queued[column].mean()),
        }
    return out


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=f"Check: {bar()} (--max-differ); exit status 1 otherwise.",
    )
    parser.add_argument("plain")
    parser.add_argument("queued", nargs="+")
    parser.add_argument("--max-differ", type=float, default=MAX_DIFFER, help="the bar, a fraction of the environments")
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    if not 0 <= args.max_differ < 1:
        parser.error(f"--max-differ must lie in [0, 1), got {args.max_differ}")
    plain, ps = load(args.plain)
    result = {
        "plain": {
            "dir": args.plain,
            "queue": ps["config"].get("queue", 1),
            "run_s": ps["run_s"],
            "chunk_size": ps["config"]["chunk_size"],
            "physics_steps_simulated": ps.get("physics_steps_simulated"),
            "n_envs": ps["n_envs"],
            "backend": ps["backend"],
            "device": ps["device"],
        },
        "queued": [],
    }
    if (pathlib.Path(args.plain) / "run_1" / "results.parquet").exists():
        result["plain"]["repeat_outcomes"] = compare(plain, load(args.plain, repeat=1)[0])
    for path in args.queued:
        table, s = load(path)
        result["queued"].append(
            {
                "dir": path,
                "queue": s["config"].get("queue", 1),
                "chunk_size": s["config"]["chunk_size"],
                "run_s": s["run_s"],
                "physics_steps_simulated": s.get("physics_steps_simulated"),
                "speedup_run": ps["run_s"] / s["run_s"] if s["run_s"] else None,
                "outcomes": compare(plain, table),
            }
        )
    inputs = {f"sweep:{i}": results_path(d) for i, d in enumerate([args.plain, *args.queued])}
    result["provenance"] = provenance.record(inputs, argv=provenance.script_argv(__file__, argv), with_device=False)
    result["check"] = checks.verdict(failures(result, args.max_differ), bar(args.max_differ))
    io.atomic_write_json(pathlib.Path(args.out), result)
    print(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    sys.exit(checks.exit_status(main()))
