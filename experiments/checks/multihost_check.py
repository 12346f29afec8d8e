"""Several processes joined by jax.distributed give the one-process results table (issue 33).

    python experiments/checks/multihost_check.py --out runs/multihost [--processes 2] [--float32]

Runs a small push sweep (MJX 'jax' backend, one CPU device per process, Gloo collectives, a
coordinator on localhost) in one process and in --processes processes (:func:`compare_processes`:
``wbc-jax push-sweep FLAGS`` once in one process and once in several on this machine, each process
contributing its own device to the global mesh), and compares the tables: outcome columns equal,
the others within --rtol/--atol (different per-device batch shapes round differently; in float64
they agree to ~1e-8 on a falling robot). A failure of any process, or a time-out, is a failure of
the comparison, with the process's last lines of stderr. Exits 1 if a process fails or times out
or the tables differ; writes multihost.json (with provenance) into --out. On several hosts the same
sweep runs with ``wbc-jax --distributed push-sweep ...`` (docs/usage.md). tests/test_distributed.py runs
:func:`compare_processes` (a test harness, not a job: it lives with the checks).
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import shutil
import socket
import subprocess
import sys

import numpy as np

from wbc_jax.core import io, provenance

EXACT_COLUMNS = ("env", "gain_set", "survived", "upright", "fell", "nan", "qp_infeasible_ticks")


def free_port() -> int:
    """A TCP port on localhost that nothing listens on now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _env(extra: dict | None) -> dict:
    """The runs' environment: one CPU device per process (the distributed run's mesh is one device
    per process), plus ``extra``; ``extra["XLA_FLAGS"]`` is appended to the device flag."""
    extra = dict(extra or {})
    flags = " ".join(["--xla_force_host_platform_device_count=1", extra.pop("XLA_FLAGS", "")]).strip()
    return {**os.environ, "JAX_PLATFORMS": "cpu", **extra, "XLA_FLAGS": flags}


def _command(flags: list[str], out: pathlib.Path, dist: list[str]) -> list[str]:
    return [sys.executable, "-m", "wbc_jax.cli", *dist, "push-sweep", *flags, "--quiet", "--out", str(out)]


def _tail(text: str, lines: int = 6) -> str:
    return " | ".join(text.strip().splitlines()[-lines:])


def compare_tables(a, b, rtol: float, atol: float) -> list[str]:
    """Differences between two sweep tables (pandas): exact columns, then the others within
    ``|a - b| <= atol + rtol |a|``; one line per column that differs."""
    problems = []
    if list(a.columns) != list(b.columns) or len(a) != len(b):
        return [f"tables differ in shape: {a.shape} {list(a.columns)} vs {b.shape} {list(b.columns)}"]
    for col in a.columns:
        x, y = a[col].to_numpy(), b[col].to_numpy()
        if col in EXACT_COLUMNS or x.dtype.kind not in "fc":
            if not np.array_equal(x, y):
                problems.append(f"{col}: {int(np.sum(x != y))} of {len(x)} entries differ")
            continue
        bad = ~np.isclose(x, y, rtol=rtol, atol=atol, equal_nan=True)
        if bad.any():
            problems.append(
                f"{col}: {int(bad.sum())} entries beyond atol {atol:g} + rtol {rtol:g} "
                f"(largest difference {np.nanmax(np.abs(x - y)):.3g})"
            )
    return problems


def compare_processes(
    sweep_flags: list[str],
    out,
    *,
    processes: int = 2,
    timeout_s: float = 1200.0,
    rtol: float = 1e-6,
    atol: float = 1e-6,
    env: dict | None = None,
) -> dict:
    """Run the sweep in one process and in ``processes`` processes and compare the tables.

    Args:
      sweep_flags: flags of ``wbc-jax push-sweep`` (an MJX backend; without ``--out``).
      out: folder; ``one/`` and ``many/`` hold the two runs.
      processes: processes of the distributed run (each one CPU device).
      timeout_s: each run's limit (a hung collective becomes a failure, not a hang).
      rtol, atol: tolerance of the continuous columns.
      env: extra environment of the runs (e.g. ``JAX_ENABLE_X64``).

    Returns:
      ``{"failures": [...], "one": {rc, stderr}, "many": [{rc, stderr}...], "envs": n, "one_ran_on",
      "many_ran_on": {n_devices, processes}}`` (the last three when both runs finished); no
      failures means equal tables.
    """
    import pandas as pd

    out = pathlib.Path(out)
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    failures = []
    one = subprocess.run(
        _command(sweep_flags, out / "one", []), env=_env(env), capture_output=True, text=True, timeout=timeout_s
    )
    result = {"one": {"rc": one.returncode, "stderr": _tail(one.stderr)}, "processes": processes}
    if one.returncode != 0:
        failures.append(f"the one-process run failed (rc {one.returncode}): {_tail(one.stderr)}")
    port = free_port()
    procs = []
    for rank in range(processes):
        dist = [
            "--distributed",
            "--coordinator",
            f"localhost:{port}",
            "--num-processes",
            str(processes),
            "--process-id",
            str(rank),
        ]
        procs.append(
            subprocess.Popen(
                _command(sweep_flags, out / "many", dist),
                env=_env(env),
                text=True,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
            )
        )
    many = []
    for rank, proc in enumerate(procs):
        try:
            _, err = proc.communicate(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            for p in procs:
                p.kill()
            _, err = proc.communicate()
            failures.append(f"process {rank} of {processes} timed out after {timeout_s:g} s")
        many.append({"rc": proc.returncode, "stderr": _tail(err)})
        if proc.returncode != 0:
            failures.append(f"process {rank} of {processes} failed (rc {proc.returncode}): {_tail(err)}")
    result["many"] = many
    if not failures:
        a = pd.read_parquet(out / "one" / "results.parquet")
        b = pd.read_parquet(out / "many" / "results.parquet")
        result["envs"] = len(a)
        failures += compare_tables(a, b, rtol, atol)
        # What each run says it ran on: the distributed one must span every process's device.
        for name in ("one", "many"):
            summary = json.loads((out / name / "summary.json").read_text())
            device = summary["provenance"]["device"]
            result[f"{name}_ran_on"] = {"n_devices": summary["n_devices"], "processes": device["processes"]}
    result["failures"] = failures
    return result


SWEEP = [
    "--magnitudes",
    "20",
    "300",
    "4",
    "--directions",
    "2",
    "--horizon",
    "0.6",
    "--push-onset",
    "0.1",
    "--chunk-size",
    "8",
    "--backend",
    "jax",
]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="runs/multihost")
    p.add_argument("--processes", type=int, default=2)
    p.add_argument(
        "--float32",
        action="store_true",
        help="float32 (default float64: rounding of the per-device batch shapes stays ~1e-8 on the falling robots)",
    )
    p.add_argument("--rtol", type=float, default=1e-6, help="bar: relative tolerance of the continuous columns")
    p.add_argument("--atol", type=float, default=1e-6, help="bar: absolute tolerance of the continuous columns")
    p.add_argument("--timeout", type=float, default=1800.0, help="seconds each run may take (bar: no hang)")
    args = p.parse_args(argv)
    if args.processes < 2:
        p.error("--processes must be at least 2")
    env = {} if args.float32 else {"JAX_ENABLE_X64": "1"}
    result = compare_processes(
        SWEEP, args.out, processes=args.processes, timeout_s=args.timeout, rtol=args.rtol, atol=args.atol, env=env
    )
    result["provenance"] = provenance.record(argv=["experiments/checks/multihost_check.py", *(argv or sys.argv[1:])])
    io.atomic_write_json(pathlib.Path(args.out) / "multihost.json", result)
    print(json.dumps({"failures": result["failures"], "envs": result.get("envs")}), flush=True)
    return 1 if result["failures"] else 0


if __name__ == "__main__":
    sys.exit(main())
