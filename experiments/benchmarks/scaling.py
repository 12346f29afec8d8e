"""One GPU against several: run time, speed-up and outcome agreement of the same push sweep (issue 33).

    python experiments/benchmarks/scaling.py --out docs/scaling --gpus 1 2 --backends warp jax -- SWEEP FLAGS

For each backend and GPU count, one process (``CUDA_VISIBLE_DEVICES`` = the first N GPUs) runs
``wbc-jax push-sweep SWEEP FLAGS`` twice (the second run is the steady-state timing; the two
tables give the engine's run-to-run floor) and the tables of N GPUs are compared with one GPU's
cell by cell. Writes scaling.json (backend, devices, run s, speed-up, outcome agreement, device
names, commands, provenance). Exits 1 when the outcomes of N GPUs differ from one GPU's in more
cells than the engine's own repeat floor (the bar: outcomes equal within the repeat floor) or a
run fails; the speed-up targets (Warp 1.8x, JAX 1.9x on 2 GPUs) are reported as met or not.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import shutil
import subprocess
import sys

import numpy as np

from wbc_jax.core import io, provenance

OUTCOMES = ("survived", "upright")
TARGETS = {"warp": {2: 1.8, 4: 3.5}, "jax": {2: 1.9}}

RUN = """
import json, sys, time
from wbc_jax import cli
from wbc_jax.jobs import sweep
out, flags = sys.argv[1], sys.argv[2:]
res = []
for k in range(2):
    cfg = cli.push_sweep_config([*flags, "--out", f"{out}/run{k}"])
    s = sweep.run_sweep(cfg, progress=False)
    res.append({key: s[key] for key in ("run_s", "compile_s", "survival_rate", "n_devices", "device", "n_envs",
                                       "physics_steps_per_s")})
print("RESULT " + json.dumps(res))
"""


def _outcomes(folder: pathlib.Path):
    import pandas as pd

    t = pd.read_parquet(folder / "results.parquet")
    return {k: t[k].to_numpy() for k in OUTCOMES}


def flips(a: dict, b: dict) -> int:
    """Cells whose strict survival differs between two tables."""
    return int(np.sum(a["survived"] != b["survived"]))


def check(rows: list[dict]) -> list[str]:
    """The bar: every run finished, and each multi-GPU table's survival flips against one GPU are at
    most the engine's repeat floor (flips between two one-GPU runs), plus one cell of slack."""
    failures = []
    for r in rows:
        if r.get("error"):
            failures.append(f"{r['backend']} on {r['gpus']} GPU(s): {r['error']}")
        elif r["gpus"] > 1 and r["flips_vs_one_gpu"] > r["repeat_floor_one_gpu"] + 1:
            failures.append(f"{r['backend']} on {r['gpus']} GPUs: {r['flips_vs_one_gpu']} survival flips vs one GPU, "
                            f"repeat floor {r['repeat_floor_one_gpu']}")  # fmt: skip
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
    p.add_argument("--backends", nargs="+", default=["warp", "jax"], choices=["warp", "jax"])
    p.add_argument("--timeout", type=float, default=1500.0)
    args = p.parse_args(own)
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for backend in args.backends:
        tables = {}
        for n in sorted(args.gpus):
            env = {**os.environ, "CUDA_VISIBLE_DEVICES": ",".join(str(i) for i in range(n))}
            folder = pathlib.Path("/tmp/wbc_scaling") / f"{backend}_{n}"
            cmd = [sys.executable, "-c", RUN, str(folder), *flags, "--backend", backend]
            row = {"backend": backend, "gpus": n}
            try:
                proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=args.timeout)
                line = [x for x in proc.stdout.splitlines() if x.startswith("RESULT ")]
                if proc.returncode != 0 or not line:
                    raise RuntimeError(f"rc {proc.returncode}: {' | '.join(proc.stderr.strip().splitlines()[-4:])}")
                runs = json.loads(line[-1][len("RESULT ") :])
                tables[n] = [_outcomes(folder / f"run{k}") for k in range(2)]
                # The tables come back with the results (the device machine keeps nothing).
                shutil.copy(folder / "run1" / "results.parquet", out / f"{backend}_{n}gpu_results.parquet")
                row.update({"run_s": runs[1]["run_s"], "first_run_s": runs[0]["run_s"], "compile_s": runs[0]["compile_s"],
                            "survival_rate": runs[1]["survival_rate"], "n_devices": runs[1]["n_devices"],
                            "device": runs[1]["device"], "envs": runs[1]["n_envs"],
                            "physics_steps_per_s": runs[1]["physics_steps_per_s"],
                            "repeat_flips": flips(*tables[n])})  # fmt: skip
            except (RuntimeError, subprocess.TimeoutExpired) as err:
                row["error"] = str(err)
            rows.append(row)
        one = next((r for r in rows if r["backend"] == backend and r["gpus"] == 1 and "error" not in r), None)
        for r in rows:
            if r["backend"] != backend or "error" in r or one is None:
                continue
            r["speed_up"] = round(one["run_s"] / r["run_s"], 3)
            r["repeat_floor_one_gpu"] = one["repeat_flips"]
            r["flips_vs_one_gpu"] = flips(tables[1][1], tables[r["gpus"]][1])
            target = TARGETS.get(backend, {}).get(r["gpus"])
            if target is not None:
                r["speed_up_target"] = target
                r["speed_up_met"] = r["speed_up"] >= target
        print(json.dumps([r for r in rows if r["backend"] == backend]), flush=True)
    failures = check(rows)
    result = {"rows": rows, "failures": failures, "sweep_flags": flags,
              "provenance": provenance.record(argv=["experiments/benchmarks/scaling.py", *argv])}  # fmt: skip
    io.atomic_write_json(out / "scaling.json", result)
    print(json.dumps({"failures": failures}), flush=True)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
