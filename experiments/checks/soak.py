"""Soak test of the batched closed loop on hostile scenarios (issue: reliability).

    python experiments/checks/soak.py --envs 1000000 --chunk 65536 --horizon 0.5 --out runs/soak   # GPU
    python experiments/checks/soak.py --quick --out runs/soak_cpu                                   # CPU, minutes

Random scenarios, every one valid but extreme: a push of 0-5,000 N in any 3-D direction on any body,
lasting 0.001-1 s from 0.05-0.3 s; floor friction 0.05-2; plant masses x0.5-1.5; initial joint noise
(0.05 rad, inside the joint limits); every gain group scaled by 0.1-10 (inside its stated range).
Each chunk runs under a watchdog thread: a chunk that does not return in --chunk-timeout s is a
hang, recorded in chunks.jsonl before the process exits with status 3 (a signal handler could not
run while the main thread waits inside XLA). Counted: environments, hangs, NaN leaks (a metric that
should be finite but is not, for an environment not flagged as diverged; or a non-finite
aggregate), flagged divergences, falls. Chunk c's scenarios come from the seed (--seed, c), and each
finished chunk is appended to --out/chunks.jsonl, so a stopped soak resumes where it stopped with
the same scenarios. Writes soak.json into --out and the soak keys of results/reliability.json with
--record.

The check (:func:`failures`): no hang, no NaN leak, every environment run; exit status 1
otherwise (a flagged divergence or a fall is an outcome, not a failure).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import pathlib
import sys
import threading
import time

import numpy as np

from wbc_jax.control.gains import Gains
from wbc_jax.core import checks, constants, io, provenance
from wbc_jax.sim import metrics as metrics_lib
from wbc_jax.sim import physics, runner, scenario
from wbc_jax.sim.state import Push, Scenario, SimConfig

ROOT = pathlib.Path(__file__).resolve().parents[2]
BAR = "no hang, no NaN leak (a non-finite metric of an environment not flagged as diverged), every environment run"


def failures(result: dict) -> list[str]:
    """Hangs, NaN leaks, environments not run."""
    out = []
    if result["soak_hangs"]:
        out.append(f"{result['soak_hangs']} chunks hung (no return within {result.get('soak_chunk_timeout_s')} s)")
    if result["soak_nan_leaks"]:
        out.append(f"{result['soak_nan_leaks']} NaN leaks, by metric: {result.get('soak_nan_leaks_by_column')}")
    asked = result.get("soak_envs_requested", result["soak_envs"])  # not recorded before 2026-11-25
    if result["soak_envs"] != asked:
        out.append(f"{result['soak_envs']} environments run of the {asked} asked")
    return out


def random_scenarios(rng: np.random.Generator, n: int, robot, dtype) -> Scenario:
    """n hostile but valid scenarios (module docstring)."""
    idx = robot.index
    m = robot.mj_model
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    force = direction * rng.uniform(0.0, 5000.0, size=(n, 1))
    duration = np.exp(rng.uniform(np.log(0.001), np.log(1.0), n))
    body = rng.integers(1, m.nbody, n)
    base = idx.description.default_gain_values(idx.n)
    gains = {}
    for name, value in base.items():
        lo, hi = constants.GAIN_RANGES[name]
        scale = np.exp(rng.uniform(np.log(0.1), np.log(10.0), (n, 1)))
        gains[name] = np.clip(value[None] * scale, lo, hi)
    lo_lim, hi_lim = m.jnt_range[m.dof_jntid[idx.dof_joints]].T
    home = robot.home_qpos()[idx.qpos_joints]
    offset = np.clip(home + rng.normal(scale=0.05, size=(n, idx.n)), lo_lim, hi_lim) - home
    return Scenario(
        push=Push(
            force=force[:, None].astype(dtype),
            onset=rng.uniform(0.05, 0.3, (n, 1)).astype(dtype),
            duration=duration[:, None].astype(dtype),
            body=body[:, None].astype(np.int32),
        ),
        gains=Gains(**{k: v.astype(dtype) for k, v in gains.items()}),
        joint_offset=offset.astype(dtype),
        friction=rng.uniform(0.05, 2.0, n).astype(dtype),
        mass_scale=rng.uniform(0.5, 1.5, n).astype(dtype),
    )


FINITE = (
    "com_rmse_m",
    "com_max_err_m",
    "max_constraint_violation",
    "max_foot_slip_m",
    "max_foot_tilt_deg",
    "max_abs_torque_nm",
    "min_com_height_m",
    "end_com_speed_mps",
    "end_com_support_margin_m",
)


def _records(log: pathlib.Path) -> list[dict]:
    """The lines of chunks.jsonl; a line cut by a kill is skipped (its chunk runs again)."""
    out = []
    for line in log.read_text().splitlines() if log.exists() else []:
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return out


def _same_soak(rec: dict, args) -> bool:
    return rec.get("seed") == args.seed and rec.get("chunk_size") == args.chunk and rec.get("horizon") == args.horizon


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog=f"Check: {BAR}; exit status 1 otherwise.")
    p.add_argument("--envs", type=int, default=1_000_000)
    p.add_argument("--chunk", type=int, default=65_536)
    p.add_argument("--horizon", type=float, default=0.5)
    p.add_argument("--backend", default="auto", choices=physics.BACKENDS)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--chunk-timeout", type=float, default=1800.0, help="s; a chunk slower than this is a hang")
    p.add_argument("--quick", action="store_true", help="256 envs in chunks of 64 (a CPU check)")
    p.add_argument("--out", default="runs/soak")
    p.add_argument("--record", action="store_true", help="also merge the figures into results/reliability.json")
    args = p.parse_args(argv)
    if args.quick:
        args.envs, args.chunk = 256, 64
    runner.enable_compilation_cache()
    sim = SimConfig(record=False, perturb_plant=True, physics=physics.PhysicsConfig(backend=args.backend))
    st = scenario.setup("stand", duration=args.horizon, sim=sim)
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    log = out / "chunks.jsonl"
    done = {rec["chunk"]: rec for rec in _records(log) if _same_soak(rec, args)}
    n_chunks = math.ceil(args.envs / args.chunk)
    for c in range(n_chunks):
        n = min(args.chunk, args.envs - c * args.chunk)
        if c in done and done[c].get("envs") == n:
            continue
        scen = random_scenarios(np.random.default_rng((args.seed, c)), n, st.robot, st.dtype)
        t0 = time.perf_counter()
        key = dict(chunk=c, seed=args.seed, chunk_size=args.chunk, horizon=args.horizon)

        def hang(key=key):  # runs on the watchdog thread
            with open(log, "a") as f:
                f.write(json.dumps(dict(key, hang=True)) + "\n")
            print(json.dumps(dict(key, hang=True)), flush=True)
            os._exit(3)

        watchdog = threading.Timer(args.chunk_timeout, hang)
        watchdog.daemon = True
        watchdog.start()
        try:
            run = runner.run(st, scen, batch_size=args.chunk)
            cols = metrics_lib.summarize(run.metrics, 0.0)
        finally:
            watchdog.cancel()
        flagged = np.asarray(cols["nan"], bool)
        by_column = {}
        for name in FINITE:
            bad = int(np.sum(~np.isfinite(np.asarray(cols[name], float)) & ~flagged))
            if bad:
                by_column[name] = bad
        rec = dict(
            key,
            envs=n,
            nan_leaks=sum(by_column.values()),
            by_column=by_column,
            flagged=int(flagged.sum()),
            fell=int(np.sum(cols["fell"])),
            upright=int(np.sum(cols["upright"])),
            compile_s=round(run.compile_s, 2),
            run_s=round(run.run_s, 3),
            chunk_s=round(time.perf_counter() - t0, 2),
        )
        with open(log, "a") as f:
            f.write(json.dumps(rec) + "\n")
        done[c] = rec
        print(json.dumps(rec), flush=True)
    totals = {
        "envs": 0,
        "hangs": 0,
        "nan_leaks": 0,
        "diverged_flagged": 0,
        "fell": 0,
        "upright": 0,
        "compile_s": 0.0,
        "run_s": 0.0,
        "max_chunk_s": 0.0,
        "leaks_by_column": {},
    }
    for rec in (done[c] for c in range(n_chunks)):  # this soak's chunks (a longer earlier one may have logged more)
        for k in ("envs", "nan_leaks", "fell", "upright", "compile_s", "run_s"):
            totals[k] += rec[k]
        totals["diverged_flagged"] += rec["flagged"]
        totals["max_chunk_s"] = max(totals["max_chunk_s"], rec["chunk_s"])
        for name, bad in rec["by_column"].items():
            totals["leaks_by_column"][name] = totals["leaks_by_column"].get(name, 0) + bad
    # Hangs: every line of this soak's key that records one, also from an earlier, killed process.
    totals["hangs"] = sum(1 for rec in _records(log) if rec.get("hang") and _same_soak(rec, args))
    rates = {k: totals[k] / max(totals["envs"], 1) for k in ("fell", "upright", "diverged_flagged")}
    aggregate_ok = all(math.isfinite(v) for v in rates.values())

    result = {
        "soak_envs": totals["envs"],
        "soak_envs_requested": args.envs,
        "soak_hangs": totals["hangs"],
        "soak_nan_leaks": totals["nan_leaks"] + (0 if aggregate_ok else 1),
        "soak_diverged_flagged": totals["diverged_flagged"],
        "soak_rates": rates,
        "soak_nan_leaks_by_column": totals["leaks_by_column"],
        "soak_horizon_s": args.horizon,
        "soak_backend": st.backend,
        "soak_compile_s": round(totals["compile_s"], 1),
        "soak_run_s": round(totals["run_s"], 1),
        "soak_max_chunk_s": totals["max_chunk_s"],
        "soak_chunk_timeout_s": args.chunk_timeout,
        "soak_physics_steps_per_s": totals["envs"] * st.loop.n_ticks * st.loop.n_sub / max(totals["run_s"], 1e-9),
        "device": provenance.device_label(),
        "provenance": provenance.record(argv=provenance.script_argv(__file__, argv)),
    }
    result["check"] = checks.verdict(failures(result), BAR)
    io.atomic_write_json(out / "soak.json", result)
    if args.record:
        path = ROOT / "results" / "reliability.json"
        current = json.loads(path.read_text()) if path.exists() else {}
        current["soak"] = result
        io.atomic_write_json(path, current)
    print(json.dumps(result), flush=True)
    return result


if __name__ == "__main__":
    sys.exit(checks.exit_status(main()))
