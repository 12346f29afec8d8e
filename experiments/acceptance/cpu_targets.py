"""The CPU targets of the CPU-path issue, measured in one run on this machine (no GPU).

    python experiments/acceptance/cpu_targets.py --out results/cpu_targets [--skip notebooks]

Each figure comes from the command a user types, run in a subprocess with a fresh compilation
cache where the target is about a first run:

* ``main_job``: the README's main job (``wbc-jax push-sweep``) with an empty compilation cache,
  then again with the cache it filled (targets: <= 90 s, then <= 30 s, from the command to its
  last line; the install is not included).
* ``sinusoid``: one robot, ``wbc-jax balance --task sinusoid --duration 20`` (target: the loop at
  >= 2x real time, CoM RMSE 1.00 mm).
* ``sweep64``: ``benchmarks/benchmark.py`` with the C MuJoCo engine, 64 environments, against the
  C MuJoCo + NumPy baseline on the same cores in the same run (target: >= 50 % of the baseline's
  steps/s per core).
* ``notebooks``: each notebook of notebooks/ executed alone (target: <= 90 s each), with the
  compilation cache the jobs above filled (as a user who ran the main job first).

Writes ``cpu_targets.json`` into ``--out``: the figures, their targets, whether each is met, the
command of each and the machine. The check (:func:`failures`): every target measured is met; exit
status 1 otherwise (after the file is written).
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import subprocess
import sys
import tempfile
import time

from wbc_jax.core import checks, provenance

ROOT = pathlib.Path(__file__).resolve().parents[2]
PARTS = ("main_job", "sinusoid", "sweep64", "notebooks")
BAR = "every target measured (each part's 'target') met"


def failures(result: dict) -> list[str]:
    """The parts measured whose target is not met."""
    return [f"{part}: {result[part]['target']} not met" for part in PARTS if part in result and not result[part]["met"]]


def timed(cmd: list[str], env: dict, cwd: pathlib.Path) -> tuple[float, str]:
    """Run ``cmd``; (wall seconds, stdout). A failure raises with its stderr."""
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=cwd, timeout=1800)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    return wall, proc.stdout


def last_json(stdout: str) -> dict:
    return json.loads([line for line in stdout.splitlines() if line.startswith("{")][-1])


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], epilog=f"Check: {BAR}; exit status 1 otherwise."
    )
    parser.add_argument("--out", default=str(ROOT / "runs" / "cpu_targets"))
    parser.add_argument("--skip", nargs="*", default=[], choices=PARTS)
    args = parser.parse_args(argv)
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    work = pathlib.Path(tempfile.mkdtemp(prefix="wbc_cpu_targets_"))
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "WBC_JAX_CACHE": str(work / "xla")}
    cli = [sys.executable, "-m", "wbc_jax.cli"]
    record = provenance.record(argv=provenance.script_argv(__file__, argv))
    result: dict = {
        "date": record["date"],
        "device": record["device"]["label"],
        "machine": {"python": platform.python_version(), "xla_flags": os.environ.get("XLA_FLAGS", "")},
        "provenance": record,
    }

    def save():
        from wbc_jax.core import io

        result["check"] = checks.verdict(failures(result), BAR)
        io.atomic_write_json(out / "cpu_targets.json", result)

    if "main_job" not in args.skip:
        first, stdout = timed([*cli, "push-sweep", "--out", str(work / "sweep1")], env, ROOT)
        s1 = last_json(stdout)
        second, stdout = timed([*cli, "push-sweep", "--out", str(work / "sweep2")], env, ROOT)
        s2 = last_json(stdout)
        result["main_job"] = {
            "command": "wbc-jax push-sweep (empty compilation cache, then the same again with a new --out)",
            "first_run_s": round(first, 1),
            "second_run_s": round(second, 1),
            "compile_s": [s1.get("compile_s"), s2.get("compile_s")],
            "run_s": [s1.get("run_s"), s2.get("run_s")],
            "physics_steps_per_s": [s1.get("physics_steps_per_s"), s2.get("physics_steps_per_s")],
            "target": "first <= 90 s, second <= 30 s",
            "met": first <= 90 and second <= 30,
        }
        print(json.dumps({"main_job": result["main_job"]}), flush=True)
        save()

    if "sinusoid" not in args.skip:
        wall, stdout = timed(
            [*cli, "balance", "--task", "sinusoid", "--duration", "20", "--out", str(work / "sinusoid")], env, ROOT
        )
        s = last_json(stdout)
        rtf = s.get("real_time_factor")
        rmse_mm = 1e3 * s["com_rmse_m"]
        result["sinusoid"] = {
            "command": "wbc-jax balance --task sinusoid --duration 20",
            "loop_s": s.get("loop_s"),
            "real_time_factor": rtf,
            "wall_s": round(wall, 1),
            "com_rmse_mm": round(rmse_mm, 5),
            "backend": s.get("backend"),
            "target": ">= 2x real time (loop <= 10 s), CoM RMSE 1.00 mm",
            "met": bool(rtf is not None and rtf >= 2.0 and abs(rmse_mm - 1.00) < 0.01),
        }
        print(json.dumps({"sinusoid": result["sinusoid"]}), flush=True)
        save()

    if "sweep64" not in args.skip:
        workers = [str(w) for w in sorted({1, os.cpu_count() or 1})]
        cmd = [
            sys.executable,
            str(ROOT / "benchmarks" / "benchmark.py"),
            "--out",
            str(work / "bench"),
            "--backends",
            "mujoco",
            "--batches",
            "64",
            "--horizon",
            "1.0",
            "--cpu-baseline-envs",
            "32",
            "--cpu-workers",
            *workers,
            "--repeats",
            "2",
            "--skip-equivalence",
        ]
        wall, _ = timed(cmd, env, ROOT)
        bench = json.loads((work / "bench" / "bench.json").read_text())
        row = bench["runs"][0]
        share = row["ratio_per_core"]
        result["sweep64"] = {
            "command": "python benchmarks/benchmark.py --backends mujoco --batches 64 --horizon 1.0 "
            f"--cpu-baseline-envs 32 --cpu-workers {' '.join(workers)} --repeats 2 --skip-equivalence",
            "closed_loop_steps_per_s": row["closed_loop_steps_per_s"],
            "closed_loop_steps_per_s_per_core": row["closed_loop_steps_per_s_per_core"],
            "cpu_baseline_steps_per_s_per_core": row["cpu_baseline_steps_per_s_per_core"],
            "cpu_baseline_workers": row["cpu_baseline_workers"],
            "share_of_baseline_per_core": round(share, 3),
            "wall_s": round(wall, 1),
            "target": ">= 50 % of the baseline's steps/s per core",
            "met": share >= 0.5,
        }
        print(json.dumps({"sweep64": result["sweep64"]}), flush=True)
        save()

    if "notebooks" not in args.skip:
        nbs = {}
        for nb in sorted((ROOT / "notebooks").glob("*.ipynb")):
            # nbclient (what tests/test_notebooks.py uses): the notebook executed top to bottom.
            code = (
                "import sys, nbformat, nbclient; nb = nbformat.read(sys.argv[1], as_version=4); "
                "nbclient.NotebookClient(nb, timeout=1200, resources={'metadata': {'path': sys.argv[2]}})"
                ".execute()"
            )
            wall, _ = timed([sys.executable, "-c", code, str(nb), str(ROOT / "notebooks")], env, ROOT)
            nbs[nb.stem] = round(wall, 1)
            print(json.dumps({"notebook": nb.stem, "wall_s": nbs[nb.stem]}), flush=True)
        result["notebooks"] = {
            "command": "each notebook executed alone with nbclient (as tests/test_notebooks.py), warm cache",
            "wall_s": nbs,
            "target": "<= 90 s each",
            "met": all(v <= 90 for v in nbs.values()),
        }
        save()
    save()
    print(json.dumps(result, indent=1), flush=True)
    return result


if __name__ == "__main__":
    sys.exit(checks.exit_status(main()))
