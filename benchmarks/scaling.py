"""One GPU against several: run time, speed-up and outcome agreement of the same push sweep (issue 33).

    python benchmarks/scaling.py --out results/scaling --gpus 1 2 --backends warp jax -- SWEEP FLAGS

For each backend and GPU count, one process (``CUDA_VISIBLE_DEVICES`` = the first N GPUs) runs
``wbc-jax push-sweep SWEEP FLAGS`` ``--repeats`` times (the last run is the steady-state timing;
the tables of one GPU give the engine's run-to-run floor: the most flips between any two) and the
tables of N GPUs are compared with one GPU's cell by cell (one GPU's runs may come from an earlier
call with the same flags and --out: a call too long for one limit is split by GPU count). Everything goes under ``--out``: the
runs in runs/<ID>/<backend>_<N>gpu/run<k>/ (ID: a hash of the sweep flags; each call redoes its
own runs, so the timings are measured) with each run's timeline.json (every device's compile,
dispatch, run, transfer and host seconds per chunk), and scaling.json, which keeps the rows of
earlier calls with other sweep flags (``calls``) and replaces those of the same flags. Exits 1
when the outcomes of N GPUs differ from one GPU's in more cells than the engine's own repeat
floor (the bar: outcomes equal within the repeat floor) or a run fails; the speed-up targets are
reported as met or not.

Diagnostics of issue 45 (why 4 GPUs of MJX-Warp ran slower than one; BENCHMARKS.md): ``--launch
processes`` runs N GPUs as N processes of one GPU each joined by jax.distributed (nothing of Python
or Warp shared between GPUs); ``--switch-interval-ms`` sets the runs' interpreter thread switch
interval; the sweep's own ``--warp-graph-cache`` (after ``--``) bounds Warp's CUDA graphs. Each row
records its launch, switch interval and the graphs each Warp call held after its last run.
"""

from __future__ import annotations

import argparse
import contextlib
import fcntl
import hashlib
import importlib.util
import json
import os
import pathlib
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np

from wbc_jax.core import io, provenance

OUTCOMES = ("survived", "upright")
TARGETS = {"warp": {2: 1.9, 4: 3.6}, "jax": {2: 1.9, 4: 3.6}}  # issue 45

# One process of a configuration: its settings (argv[2], JSON) before JAX starts, then the runs.
RUN = """
import json, sys
settings = json.loads(sys.argv[2])
if settings["switch_interval_ms"] is not None:  # the interpreter's thread switch interval, this process only
    sys.setswitchinterval(settings["switch_interval_ms"] / 1000)
if settings["distributed"] is not None:  # one of several processes, one GPU each (before JAX starts)
    from wbc_jax.core import processes
    processes.initialize(processes.DistributedConfig(**settings["distributed"]), "scaling.py")
from wbc_jax import cli
from wbc_jax.jobs import sweep
from wbc_jax.sim import runner, warp_graphs
runner.enable_compilation_cache()
out, flags = sys.argv[1], sys.argv[3:]
res = []
for k in range(settings["repeats"]):
    cfg = cli.push_sweep_config([*flags, "--out", f"{out}/run{k}"])
    s = sweep.run_sweep(cfg, progress=False)
    res.append({key: s[key] for key in ("run_s", "compile_s", "survival_rate", "n_devices", "device", "n_envs",
                                       "physics_steps_per_s")})
    res[-1]["timeline"] = json.load(open(f"{out}/run{k}/timeline.json"))["totals_by_device"]
    res[-1]["warp_graphs"] = warp_graphs.held()  # graphs held by each Warp call after the run, and their bound
    res[-1]["switch_interval_s"] = sys.getswitchinterval()
    if k == 0:  # foreign calls in the first device program's optimized HLO (an unrolled scan repeats them)
        import collections, re
        from wbc_jax.sim import loop as loop_lib
        hlo = [next(iter(p.compiled.values())).as_text() for p in loop_lib.PROGRAMS.values()
               if isinstance(getattr(p, "compiled", None), dict)]
        res[-1]["custom_calls"] = [dict(collections.Counter(re.findall(r'custom_call_target="([^"]+)"', t))) for t in hlo]
print("RESULT " + json.dumps(res))
"""
LAUNCHES = ("threads", "processes")


def _outcomes(folder: pathlib.Path):
    import pandas as pd

    t = pd.read_parquet(folder / "results.parquet")
    return {k: t[k].to_numpy() for k in OUTCOMES}


def flips(a: dict, b: dict) -> int:
    """Cells whose strict survival differs between two tables."""
    return int(np.sum(a["survived"] != b["survived"]))


def repeat_floor(tables: list[dict]) -> int:
    """The most survival flips between any two of one configuration's repeated tables."""
    return max(flips(a, b) for i, a in enumerate(tables) for b in tables[i + 1 :])


def call_id(flags: list[str]) -> str:
    """The folder name of a call's runs: its sweep flags' hash (another call with them redoes them)."""
    return hashlib.sha256(json.dumps(flags).encode()).hexdigest()[:12]


def earlier_calls(path: pathlib.Path) -> dict:
    """The calls recorded in an earlier scaling.json at ``path`` ({} when there is none); a file
    that scaling.py did not write is refused, naming it, before anything runs."""
    if not path.exists():
        return {}
    try:
        calls = json.loads(path.read_text()).get("calls")
    except (OSError, ValueError, AttributeError):
        calls = None
    if not isinstance(calls, dict):
        raise SystemExit(
            f"scaling.py: error: --out {path.parent}: its scaling.json was not written by scaling.py "
            "(no 'calls'); give another --out"
        )
    return calls


def visible_gpus(n: int) -> list[str]:
    """The first ``n`` GPUs this process may use: ``CUDA_VISIBLE_DEVICES``'s (so calls on disjoint
    GPUs of one host can run at once), else 0..n-1; too few named is refused in one line."""
    visible = os.environ.get("CUDA_VISIBLE_DEVICES", "").strip()
    ids = [g.strip() for g in visible.split(",") if g.strip()] if visible else [str(i) for i in range(n)]
    if len(ids) < n:
        raise SystemExit(
            f"scaling.py: error: --gpus {n}: CUDA_VISIBLE_DEVICES={visible} names {len(ids)} GPU(s); "
            f"name {n} or more, or leave it unset (GPUs 0..{n - 1})"
        )
    return ids[:n]


@contextlib.contextmanager
def locked(folder: pathlib.Path):
    """Hold an exclusive lock on ``folder`` (flock on the folder itself: no file beside the results),
    so calls sharing an --out merge their rows one after the other."""
    fd = os.open(folder, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # closing releases the lock


def compare(rows: list[dict], out: pathlib.Path) -> list[dict]:
    """Each row of a backend against that backend's one-GPU row, whichever call measured either (the
    runs are read back from ``out``): speed-up, the one-GPU repeat floor, survival flips of the last
    tables, and the target of issue 45. Rows with no one-GPU row to compare with carry none of these."""
    derived = ("speed_up", "repeat_floor_one_gpu", "flips_vs_one_gpu", "speed_up_target", "speed_up_met")
    rows = [{k: v for k, v in r.items() if k not in derived} for r in rows]

    def last_table(r: dict) -> dict:
        return _outcomes(out / r["runs"] / f"run{r['repeats'] - 1}")

    for backend in sorted({r["backend"] for r in rows}):
        one = next((r for r in rows if r["backend"] == backend and r["gpus"] == 1 and "error" not in r), None)
        if one is None:
            continue
        base = last_table(one)
        for r in rows:
            if r["backend"] != backend or "error" in r:
                continue
            r["speed_up"] = round(one["run_s"] / r["run_s"], 3)
            r["repeat_floor_one_gpu"] = one["repeat_flips"]
            r["flips_vs_one_gpu"] = flips(base, last_table(r))
            target = TARGETS.get(backend, {}).get(r["gpus"])
            if target is not None:
                r["speed_up_target"] = target
                r["speed_up_met"] = r["speed_up"] >= target
    return rows


def _free_port() -> int:
    """A free TCP port on localhost (experiments/checks/multihost_check.py's)."""
    path = pathlib.Path(__file__).resolve().parents[1] / "experiments" / "checks" / "multihost_check.py"
    spec = importlib.util.spec_from_file_location("multihost_check", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.free_port()


def launch(n: int, folder: pathlib.Path, flags: list[str], args: argparse.Namespace) -> list[tuple[list[str], str]]:
    """The commands (each with its CUDA_VISIBLE_DEVICES) that run a configuration on ``n`` GPUs:
    one process with the first ``n`` GPUs this process may use (:func:`visible_gpus`; ``--launch threads``: one host thread per GPU inside it,
    wbc_jax.sim.per_device), or ``n`` processes of one GPU each joined by jax.distributed
    (``--launch processes``: no interpreter lock, Warp lock or Warp graph cache shared between GPUs)."""
    settings = {"repeats": args.repeats, "switch_interval_ms": args.switch_interval_ms, "distributed": None}
    gpus = visible_gpus(n)
    if args.launch == "threads" or n == 1:
        cmd = [sys.executable, "-c", RUN, str(folder), json.dumps(settings), *flags]
        return [(cmd, ",".join(gpus))]
    port = _free_port()
    out = []
    for rank in range(n):
        dist = {"distributed": True, "coordinator": f"localhost:{port}", "num_processes": n, "process_id": rank}
        cmd = [sys.executable, "-c", RUN, str(folder), json.dumps({**settings, "distributed": dist}), *flags]
        out.append((cmd, gpus[rank]))
    return out


def run_configuration(n: int, folder: pathlib.Path, flags: list[str], args: argparse.Namespace) -> list[dict]:
    """Run one configuration (:func:`launch`) within ``--timeout`` s; the first process's runs (the
    one that writes the tables). A failed or timed-out process raises RuntimeError naming it."""
    commands = launch(n, folder, flags, args)
    # Each process's output goes to a file of its own: pipes read one after the other would fill.
    logs = [(tempfile.TemporaryFile("w+"), tempfile.TemporaryFile("w+")) for _ in commands]
    procs = [
        subprocess.Popen(cmd, env={**os.environ, "CUDA_VISIBLE_DEVICES": gpus}, stdout=out, stderr=err, text=True)
        for (cmd, gpus), (out, err) in zip(commands, logs, strict=True)
    ]

    def read(f) -> str:
        f.seek(0)
        return f.read()

    deadline = time.monotonic() + args.timeout
    try:
        for rank, proc in enumerate(procs):
            try:
                proc.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                raise RuntimeError(f"process {rank} of {len(procs)} ran past --timeout {args.timeout:g} s") from None
            if proc.returncode != 0:
                err = " | ".join(read(logs[rank][1]).strip().splitlines()[-4:])
                raise RuntimeError(f"process {rank} of {len(procs)}: rc {proc.returncode}: {err}")
        stdout, stderr = read(logs[0][0]), read(logs[0][1])
    finally:  # a failed process leaves its peers waiting on it: end them
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        for out, err in logs:
            out.close()
            err.close()
    line = [x for x in stdout.splitlines() if x.startswith("RESULT ")]
    if not line:
        raise RuntimeError(f"no result line: {' | '.join(stderr.strip().splitlines()[-4:])}")
    return json.loads(line[-1][len("RESULT ") :])


def check(rows: list[dict]) -> list[str]:
    """The bar: every run finished, and each multi-GPU table's survival flips against one GPU are at
    most the engine's repeat floor (flips between two one-GPU runs), plus one cell of slack."""
    failures = []
    for r in rows:
        if r.get("error"):
            failures.append(f"{r['backend']} on {r['gpus']} GPU(s): {r['error']}")
        elif r["gpus"] > 1 and "flips_vs_one_gpu" not in r:
            failures.append(f"{r['backend']} on {r['gpus']} GPUs: no one-GPU run in this --out to compare with")
        elif r["gpus"] > 1 and r["flips_vs_one_gpu"] > r["repeat_floor_one_gpu"] + 1:
            failures.append(
                f"{r['backend']} on {r['gpus']} GPUs: {r['flips_vs_one_gpu']} survival flips vs one GPU, "
                f"repeat floor {r['repeat_floor_one_gpu']}"
            )
    return failures


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if "--" in argv:
        k = argv.index("--")
        own, flags = argv[:k], argv[k + 1 :]
    else:
        own, flags = argv, []
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="runs/scaling")
    p.add_argument("--gpus", type=int, nargs="+", default=[1, 2])
    # mujoco: C MuJoCo on the host (one device), for a check of the script on a CPU
    p.add_argument("--backends", nargs="+", default=["warp", "jax"], choices=["warp", "jax", "mujoco"])
    p.add_argument(
        "--repeats",
        type=int,
        default=3,
        choices=range(2, 11),
        metavar="2..10",
        help="runs of each configuration in its process (the repeat floor needs two or more)",
    )
    p.add_argument("--timeout", type=float, default=1500.0)
    p.add_argument(
        "--launch",
        default="threads",
        choices=LAUNCHES,
        help="several GPUs as one process with a host thread per GPU (threads), or as one process per GPU "
        "joined by jax.distributed (processes)",
    )
    p.add_argument(
        "--switch-interval-ms",
        type=float,
        default=None,
        metavar="0.01..100",
        help="the runs' interpreter thread switch interval (sys.setswitchinterval; default: Python's 5 ms)",
    )
    args = p.parse_args(own)
    if args.switch_interval_ms is not None and not 0.01 <= args.switch_interval_ms <= 100:
        raise SystemExit(
            f"scaling.py: error: --switch-interval-ms must be a number in [0.01, 100] ms, got {args.switch_interval_ms:g}"
        )
    if args.backends != ["mujoco"]:
        visible_gpus(max(args.gpus))  # too few GPUs named: refused before anything runs
    out = pathlib.Path(args.out)
    calls = earlier_calls(out / "scaling.json")  # refused before anything runs; read again under the lock
    ident = call_id(flags)
    rows = []
    for backend in args.backends:
        tables = {}
        for n in sorted(args.gpus):
            folder = out / "runs" / ident / f"{backend}_{n}gpu"
            shutil.rmtree(folder, ignore_errors=True)  # this call's own runs, redone: measured, not resumed
            row = {
                "backend": backend,
                "gpus": n,
                "runs": folder.relative_to(out).as_posix(),
                "launch": "threads" if n == 1 else args.launch,
                "switch_interval_ms": args.switch_interval_ms,
            }
            try:
                runs = run_configuration(n, folder, [*flags, "--backend", backend], args)
                tables[n] = [_outcomes(folder / f"run{k}") for k in range(args.repeats)]
                last = runs[-1]
                row.update(
                    {
                        "run_s": last["run_s"],
                        "run_s_each": [r["run_s"] for r in runs],
                        "compile_s": runs[0]["compile_s"],
                        "survival_rate": last["survival_rate"],
                        "n_devices": last["n_devices"],
                        "device": last["device"],
                        "envs": last["n_envs"],
                        "physics_steps_per_s": last["physics_steps_per_s"],
                        "timeline_last_run": last["timeline"],
                        "warp_graphs_last_run": last["warp_graphs"],
                        "custom_calls_per_program": runs[0].get("custom_calls", []),
                        "switch_interval_s": last["switch_interval_s"],
                        "repeats": args.repeats,
                        "repeat_flips": repeat_floor(tables[n]),
                    }
                )
            except RuntimeError as err:
                row["error"] = str(err)
            rows.append(row)
        print(json.dumps([r for r in rows if r["backend"] == backend]), flush=True)
    out.mkdir(parents=True, exist_ok=True)
    with locked(out):  # another call on other GPUs may have written since this one started: merge with it
        calls = earlier_calls(out / "scaling.json")
        # Rows of an earlier call with these flags stay unless this call measured their backend and GPUs again.
        done = {(r["backend"], r["gpus"]) for r in rows}
        kept = [r for r in calls.get(ident, {}).get("rows", []) if (r["backend"], r["gpus"]) not in done]
        rows = compare(sorted(kept + rows, key=lambda r: (r["backend"], r["gpus"])), out)
        failures = check(rows)
        calls[ident] = {
            "sweep_flags": flags,
            "rows": rows,
            "failures": failures,
            "provenance": provenance.record(argv=["benchmarks/scaling.py", *argv]),
        }
        every = list(calls.values())
        result = {
            "calls": calls,
            "rows": [{**r, "sweep_flags": c["sweep_flags"]} for c in every for r in c["rows"]],
            "failures": [f for c in every for f in c["failures"]],
        }
        io.atomic_write_json(out / "scaling.json", result)
    print(json.dumps({"failures": failures}), flush=True)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
