"""kill -9 at random moments of a long sweep and of a tuning run; the resumed results must equal
an uninterrupted run's (issue: reliability).

    python experiments/checks/kill_trials.py --job sweep --trials 10 --out runs/kill
    python experiments/checks/kill_trials.py --job tune --trials 10 --out runs/kill --record

Each trial starts the job in a subprocess on the same --out, sends SIGKILL after a random delay
(uniform in --kill-after), and starts it again until it exits 0; then the result files are
compared with a reference run that was never interrupted: the sweep's results.parquet (every
column, every env, exactly), the tuning run's gradient/history.csv (losses and gradient norms) and
gains/gradient.json. Writes kill_<job>.json into --out (and the kill keys of results/reliability.json
with --record).

The check (:func:`failures`): every trial's resumed results equal the reference's, and at least
one trial was killed (a trial that finished before its kill tests nothing); exit status 1
otherwise.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import pathlib
import random
import shutil
import signal
import subprocess
import sys
import time

from wbc_jax.core import checks, provenance

ROOT = pathlib.Path(__file__).resolve().parents[2]
BAR = "every resumed run's results equal the uninterrupted reference's, and at least one trial was killed"

JOBS = {
    "sweep": [
        "push-sweep",
        "--magnitudes",
        "20",
        "120",
        "6",
        "--directions",
        "8",
        "--horizon",
        "1.0",
        "--push-onset",
        "0.3",
        "--chunk-size",
        "4",
        "--joint-noise",
        "0.01",
        "--friction",
        "0.7",
        "1.0",
        "--quiet",
    ],
    "tune": [
        "tune",
        "--phases",
        "train",
        "--steps",
        "6",
        "--batch",
        "2",
        "--horizon",
        "0.4",
        "--push-onset",
        "0.1",
        "--duration-range",
        "0.05",
        "0.1",
        "--quality-pushes",
        "2",
        "--eval-horizon",
        "0.4",
        "--quiet",
    ],
}


def run_job(job: str, out: pathlib.Path, kill_after: float | None, env: dict) -> tuple[int, float]:
    """Start the job; SIGKILL it after ``kill_after`` s (None: let it finish). (exit code, seconds)."""
    cmd = [sys.executable, "-m", "wbc_jax.cli", *JOBS[job], "--out", str(out)]
    t0 = time.time()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env, start_new_session=True)
    try:
        proc.wait(timeout=kill_after)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    return proc.returncode, time.time() - t0


def _deterministic_columns(text: str) -> list:
    """The rows of a history.csv without the columns that measure time or memory."""
    rows = list(csv.reader(text.splitlines()))
    keep = [i for i, name in enumerate(rows[0]) if name not in ("step_s", "wall_s", "rss_mb")]
    return [[r[i] for i in keep] for r in rows]


def compare(job: str, ref: pathlib.Path, got: pathlib.Path) -> list[str]:
    """Differences between two finished runs' result files (empty: identical)."""
    if job == "sweep":
        import pandas as pd

        a, b = pd.read_parquet(ref / "results.parquet"), pd.read_parquet(got / "results.parquet")
        if list(a.columns) != list(b.columns) or len(a) != len(b):
            return [f"shape {a.shape} vs {b.shape}"]
        return [c for c in a.columns if not a[c].equals(b[c])]
    diffs = []
    for name in ("gradient/history.csv", "gains/gradient.json"):
        ra, rb = (ref / name).read_text(), (got / name).read_text()
        if name.endswith("history.csv"):  # the per-step wall time and memory columns differ by nature
            ra, rb = _deterministic_columns(ra), _deterministic_columns(rb)
        if ra != rb:
            diffs.append(name)
    return diffs


def failures(result: dict) -> list[str]:
    """Trials whose resumed results differ from the reference (or did not finish); no trial killed.
    From the trials when recorded (the counts alone in records before 2026-11-25)."""
    trials = result.get("trials")
    if trials is None:
        differ, killed = result["kill_mismatches"], result["kill_killed"]
        out = [f"{differ} of {result['kill_trials']} trials differ from the reference"] if differ else []
    else:
        killed = sum(bool(t["killed"]) for t in trials)
        out = [
            f"trial {t['trial']}: differs from the reference in {t['differences']}" for t in trials if t["differences"]
        ]
    if not killed:
        out.append(f"none of the {result['kill_trials']} trials was killed: raise --trials or lower --kill-after")
    return out


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog=f"Check: {BAR}; exit status 1 otherwise.")
    p.add_argument("--job", choices=sorted(JOBS), required=True)
    p.add_argument("--trials", type=int, default=10)
    p.add_argument("--kill-after", type=float, nargs=2, default=[15.0, 60.0], metavar=("LO", "HI"))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="runs/kill")
    p.add_argument("--record", action="store_true")
    args = p.parse_args(argv)
    out = pathlib.Path(args.out) / args.job
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    rng = random.Random(args.seed)
    ref = out / "reference"
    if not (ref / ("results.parquet" if args.job == "sweep" else "gains/gradient.json")).exists():
        shutil.rmtree(ref, ignore_errors=True)
        code, secs = run_job(args.job, ref, None, env)
        if code != 0:
            raise SystemExit(f"the reference {args.job} run failed (exit {code})")
        print(json.dumps({"reference_s": round(secs, 1)}), flush=True)
    trials = []
    for k in range(args.trials):
        target = out / f"trial_{k}"
        shutil.rmtree(target, ignore_errors=True)
        kills, code, starts = 0, None, 0
        delay = rng.uniform(*args.kill_after)
        code, _ = run_job(args.job, target, delay, env)
        starts += 1
        kills += int(code == -signal.SIGKILL)
        while code != 0:  # resume until it finishes
            code, _ = run_job(args.job, target, None, env)
            starts += 1
            if code not in (0, -signal.SIGKILL):
                break
        diffs = compare(args.job, ref, target) if code == 0 else [f"exit {code}"]
        trials.append(
            {"trial": k, "kill_after_s": round(delay, 2), "killed": bool(kills), "starts": starts, "differences": diffs}
        )
        print(json.dumps(trials[-1]), flush=True)
    result = {
        "kill_job": args.job,
        "kill_trials": len(trials),
        "kill_killed": sum(t["killed"] for t in trials),
        "kill_mismatches": sum(bool(t["differences"]) for t in trials),
        "trials": trials,
        "device": provenance.device_label(),
        "provenance": provenance.record(argv=provenance.script_argv(__file__, argv)),
    }
    result["check"] = checks.verdict(failures(result), BAR)
    from wbc_jax.core import io

    io.atomic_write_json(out / f"kill_{args.job}.json", result)
    if args.record:
        path = ROOT / "results" / "reliability.json"
        current = json.loads(path.read_text()) if path.exists() else {}
        current[f"kill_{args.job}"] = result
        io.atomic_write_json(path, current)
    print(json.dumps({k: v for k, v in result.items() if k != "trials"}), flush=True)
    return result


if __name__ == "__main__":
    sys.exit(checks.exit_status(main()))
