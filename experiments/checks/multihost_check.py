"""Several processes joined by jax.distributed give the one-process results table (issue 33).

    python experiments/checks/multihost_check.py --out runs/multihost [--processes 2] [--float32]

Runs a small push sweep (MJX 'jax' backend, one CPU device per process, Gloo collectives, a
coordinator on localhost) in one process and in --processes processes
(:func:`wbc_jax.jobs.distributed.compare_processes`), and compares the tables: outcome columns
equal, the others within --rtol/--atol. Exits 1 if a process fails or times out or the tables
differ; writes multihost.json (with provenance) into --out. On several hosts the same sweep runs
with ``wbc-jax --distributed push-sweep ...`` (README).
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

from wbc_jax.core import io, provenance
from wbc_jax.jobs import distributed

SWEEP = ["--magnitudes", "20", "300", "4", "--directions", "2", "--horizon", "0.6", "--push-onset", "0.1",
         "--chunk-size", "8", "--backend", "jax"]  # fmt: skip


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="runs/multihost")
    p.add_argument("--processes", type=int, default=2)
    p.add_argument("--float32", action="store_true", help="float32 (default float64: rounding of the per-device "
                   "batch shapes stays ~1e-8 on the falling robots)")  # fmt: skip
    p.add_argument("--rtol", type=float, default=1e-6, help="bar: relative tolerance of the continuous columns")
    p.add_argument("--atol", type=float, default=1e-6, help="bar: absolute tolerance of the continuous columns")
    p.add_argument("--timeout", type=float, default=1800.0, help="seconds each run may take (bar: no hang)")
    args = p.parse_args(argv)
    if args.processes < 2:
        p.error("--processes must be at least 2")
    env = {} if args.float32 else {"JAX_ENABLE_X64": "1"}
    result = distributed.compare_processes(SWEEP, args.out, processes=args.processes, timeout_s=args.timeout,
                                           rtol=args.rtol, atol=args.atol, env=env)  # fmt: skip
    result["provenance"] = provenance.record(argv=["experiments/checks/multihost_check.py", *(argv or sys.argv[1:])])
    io.atomic_write_json(pathlib.Path(args.out) / "multihost.json", result)
    print(json.dumps({"failures": result["failures"], "envs": result.get("envs")}), flush=True)
    return 1 if result["failures"] else 0


if __name__ == "__main__":
    sys.exit(main())
