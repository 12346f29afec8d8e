"""Closed-loop throughput of wbc_jax vs the C MuJoCo + NumPy baseline, side by side in one run.

    python benchmarks/benchmark.py --out runs/bench [--batches 1 1024 16384] [--horizon 1.0]
        [--backends jax warp mujoco] [--iterations 4 2 1] [--cpu-baseline-envs 64]
        [--cpu-workers 16] [--json results/benchmarks.json]

For each physics backend (``jax``: MJX's JAX implementation, ``warp``: MJX-Warp on a CUDA GPU,
``mujoco``: C MuJoCo on the host with the jitted JAX controller), solver iteration count and batch
size: compile time, closed-loop physics steps/s and control ticks/s (``runner.run`` on a batch of
40 N pushes spread over 360 deg; 1 kHz physics, 100 Hz control), the same physics with the torques
held fixed (physics only), the controller's share of the time (1 - closed loop / physics only),
peak device memory. Then the CPU baseline (benchmarks/baseline_cpu/: C MuJoCo + the controller in
NumPy, one worker process per core) on the same task, and the ratio of each closed loop to it
(for ``mujoco`` also steps/s per core on both sides). The trajectory check: the MJX closed loop and
the baseline on one 1 s stand with a 40 N lateral chest push, CoM difference.

Writes bench.json (everything) into --out and prints it; ``--json FILE`` also appends/updates one
row per measured setting (backend, iterations, batch, device) in FILE (results/benchmarks.json).
The check (:func:`failures`): the trajectory check's CoM within ``EQUIVALENCE_BAR_M`` (1 mm) over
the second at every iteration count measured (none with --skip-equivalence); exit status 1
otherwise, after bench.json is written.

Heavy imports (JAX, wbc_jax) stay inside functions: run_parallel's worker processes (``spawn``)
re-import this script, and stay JAX-free that way.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import sys
import traceback

ROOT = pathlib.Path(__file__).resolve().parent.parent
# baseline_cpu and loop_timing are imported from this script's folder: Python puts it first on
# sys.path when the script runs (and spawn's workers inherit that path).

BACKENDS = ("jax", "warp", "mujoco")
EQUIVALENCE_BAR_M = 1e-3  # the MJX closed loop against the C MuJoCo + NumPy baseline, CoM over 1 s
BAR = (
    f"the MJX closed loop's CoM within {EQUIVALENCE_BAR_M * 1e3:g} mm of the C MuJoCo + NumPy baseline's over "
    "1 s (the trajectory check; skipped with --skip-equivalence)"
)
JSON_KEYS = (
    "device",
    "date",
    "backend",
    "solver_iterations",
    "batch",
    "closed_loop_steps_per_s",
    "physics_only_steps_per_s",
    "cpu_baseline_steps_per_s",
    "cpu_baseline_workers",
    "ratio",
    "n_devices",
    "command",
    "sweep_name",
    "sweep_run_s",
    "sweep_envs",
)
# qp_warm_start, qp_unrolled_steps, qp_engine, warp_terms, mass_solve_engine, ritz_engine, xla_flags: only in the row of a run that set them (the rows
# before, at the defaults, have no such key)
JSON_ROW_KEY = (
    "device",
    "backend",
    "solver_iterations",
    "batch",
    "n_devices",
    "sweep_name",
    "qp_warm_start",
    "qp_unrolled_steps",
    "qp_engine",
    "warp_terms",
    "mass_solve_engine",
    "ritz_engine",
    "xla_flags",
)


# ---------------------------------------------------------------------------------------------
# Trajectory equivalence


def equivalence_check(horizon: float = 1.0, iterations: int | None = None) -> dict:
    """Same scenario, both simulators: the MJX closed loop (JAX physics, this device, its dtype)
    and the C MuJoCo + NumPy baseline (float64), stand task with a 40 N lateral chest push at
    0.3 s for 0.1 s. The bar: CoM within 1 mm over 1 s."""
    import baseline_cpu
    import numpy as np
    from loop_timing import make_setup

    from wbc_jax.sim import runner, scenario

    st = make_setup("jax", horizon, iterations, record=True)
    push = scenario.make_push([0.0, 40.0, 0.0], 0.3, 0.1, st.dtype)
    run = runner.run(st, scenario.single(st, push))
    spec = baseline_cpu.spec_from_setup(st)
    base = baseline_cpu.simulate(spec, st.gains, push)
    com_mjx, com_cpu = np.asarray(run.records.com[0], float), base["com"][0]
    diff = np.linalg.norm(com_mjx - com_cpu, axis=1)
    return {
        "horizon_s": horizon,
        "mjx_backend": "jax",
        "mjx_dtype": str(st.dtype),
        "solver_iterations": int(spec.mj_model.opt.iterations),
        "com_max_diff_m": float(diff.max()),
        "com_excursion_m": float(np.abs(com_cpu - com_cpu[0]).max()),
        "same_within_1mm": bool(diff.max() < EQUIVALENCE_BAR_M),
    }


def failures(result: dict) -> list[str]:
    """The trajectory checks whose CoM differs by EQUIVALENCE_BAR_M or more (or not finitely)."""
    return [
        f"trajectory check at {eq['solver_iterations']} solver iterations: the CoM differs by "
        f"{eq['com_max_diff_m']:.3g} m from the baseline's (bar {EQUIVALENCE_BAR_M:g} m)"
        for eq in result.get("equivalence", [])
        if not eq["com_max_diff_m"] < EQUIVALENCE_BAR_M
    ]


# ---------------------------------------------------------------------------------------------
# Output


def device_description(backend: str) -> str:
    """What ran the closed loop (``provenance.device_label``): JAX's device; for C MuJoCo the host's
    CPU, with the accelerator that ran the controller if any."""
    from wbc_jax.core import provenance

    info = provenance.device()
    if backend != "mujoco" or info["platform"] == "cpu":
        return provenance.device_label(info)
    return f"{provenance.device_label(dict(info, platform='cpu', kind=provenance.cpu_name()))} + {provenance.device_label(info)}"


def json_rows(result: dict) -> list[dict]:
    """One row (JSON_KEYS) per measured closed-loop setting of a result; the sweep fields are
    null here (sweeps add their own rows)."""
    rows = []
    for row in result["runs"]:
        if "closed_loop_steps_per_s" not in row:
            continue  # a batch that failed (out of memory)
        entry = {k: row.get(k) for k in JSON_KEYS}
        entry.update(date=result["date"], command=result["command"], sweep_name=None, sweep_run_s=None, sweep_envs=None)
        if row.get("qp_warm_start"):
            entry["qp_warm_start"] = True
        if row.get("qp_unrolled_steps"):
            entry["qp_unrolled_steps"] = row["qp_unrolled_steps"]
        if row.get("qp_engine", "jax") != "jax":  # the force QP in a Warp kernel: a setting of its own
            entry["qp_engine"] = row["qp_engine"]
        if row.get("warp_terms", "jax") != "jax":  # the controller's terms off the physics' step1: a setting of its own
            entry["warp_terms"] = row["warp_terms"]
        if row.get("mass_solve_engine", "jax") != "jax":  # the torque law's M solve in a Warp kernel
            entry["mass_solve_engine"] = row["mass_solve_engine"]
        if row.get("ritz_engine", "jax") != "jax":  # the postural projector's Ritz decomposition in a Warp kernel
            entry["ritz_engine"] = row["ritz_engine"]
        if row.get("xla_flags"):  # XLA's flags of the run (command buffers, say): a setting of its own
            entry["xla_flags"] = row["xla_flags"]
        rows.append(entry)
    return rows


def update_json_rows(path: pathlib.Path, rows: list[dict]) -> list[dict]:
    """Append the rows to the JSON list in ``path``, replacing those of the same setting
    (JSON_ROW_KEY); written atomically."""
    from wbc_jax.core import io

    existing = []
    if path.exists():
        existing = json.loads(path.read_text() or "[]")
        if not isinstance(existing, list):
            raise ValueError(f"{path} must hold a JSON list of rows")
    for row in rows:
        key = tuple(row.get(k) for k in JSON_ROW_KEY)
        same = [i for i, r in enumerate(existing) if tuple(r.get(k) for k in JSON_ROW_KEY) == key]
        if same:  # updated in place; any duplicates of it dropped
            existing[same[0]] = row
            existing = [r for i, r in enumerate(existing) if i not in same[1:]]
        else:
            existing.append(row)
    io.atomic_write_json(path, existing)
    return existing


def parse_args(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=f"Check: {BAR}; exit status 1 otherwise.",
    )
    parser.add_argument("--out", default=str(ROOT / "runs" / "bench"), help="folder of bench.json")
    parser.add_argument(
        "--qp-warm-start",
        action="store_true",
        help="the closed loops' force QP warm-started from the last tick (ControllerConfig.qp_warm_start)",
    )
    from loop_timing import add_qp_arguments, add_warp_terms_argument, check_qp_arguments

    add_qp_arguments(parser)
    add_warp_terms_argument(parser)
    parser.add_argument(
        "--json",
        default=None,
        metavar="FILE",
        help="also append/update one row per setting in FILE (e.g. results/benchmarks.json)",
    )
    parser.add_argument(
        "--backends",
        nargs="+",
        choices=BACKENDS,
        default=None,
        help="closed-loop physics backends (default: warp on a CUDA GPU with warp-lang, else jax)",
    )
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 64])
    parser.add_argument("--horizon", type=float, default=1.0, help="simulated seconds per run")
    parser.add_argument(
        "--iterations",
        type=int,
        nargs="+",
        default=[None],
        help="contact solver Newton iterations (default: the model's)",
    )
    parser.add_argument(
        "--cpu-baseline-envs", type=int, default=0, help="environments per CPU worker (0: no CPU baseline)"
    )
    parser.add_argument(
        "--cpu-workers",
        type=int,
        nargs="+",
        default=[os.cpu_count()],
        help="worker counts to time (scaling over cores); the largest is the baseline",
    )
    parser.add_argument("--push-onset", type=float, default=0.2, help="s")
    parser.add_argument("--push-duration", type=float, default=0.1, help="s")
    parser.add_argument(
        "--repeats",
        type=int,
        default=1,
        help="timed runs per measurement after the first (compiling) one; the fastest counts",
    )
    parser.add_argument("--skip-physics-only", action="store_true")
    parser.add_argument("--skip-equivalence", action="store_true", help="skip the MJX vs C MuJoCo trajectory check")
    parser.add_argument(
        "--find-largest",
        type=int,
        default=0,
        metavar="K",
        help="after --batches, up to K doublings of the largest, until one fails",
    )
    args = parser.parse_args(argv)
    check_qp_arguments(parser, args)
    if args.repeats < 1:
        parser.error("--repeats must be >= 1")
    for name in ("batches", "cpu_workers"):
        if any(v < 1 for v in getattr(args, name)):
            parser.error(f"--{name.replace('_', '-')} must be >= 1")
    if args.cpu_baseline_envs < 0 or not args.horizon > 0:
        parser.error("--cpu-baseline-envs must be >= 0 and --horizon > 0")
    if any(it is not None and it < 1 for it in args.iterations):
        parser.error("--iterations must be >= 1")
    return args


def main(argv=None) -> dict:
    args = parse_args(argv)

    import baseline_cpu
    import jax
    from loop_timing import (
        PUSH_MAGNITUDE,
        hold_torques,
        make_setup,
        peak_memory,
        push_batch,
        time_closed_loop,
        time_physics_only,
    )

    from wbc_jax.core import checks, io, provenance
    from wbc_jax.sim import physics

    backends = args.backends or ["warp" if physics.has_cuda() and physics.has_warp() else "jax"]
    for b in backends:
        physics.resolve_backend(b)  # a clear error (no GPU, no warp-lang) before any work
    out = pathlib.Path(args.out)
    push_end = args.push_onset + args.push_duration
    record = provenance.record(argv=provenance.script_argv(__file__, argv))
    result = {
        "command": record["command"],
        "date": record["date"],
        "device": record["device"]["label"],
        "provenance": record,
        "jax": jax.__version__,
        "jax_devices": [str(d) for d in jax.devices()],
        "n_devices": len(jax.devices()),
        "host_cpu": baseline_cpu.cpu_name(),
        "cpu_count": os.cpu_count(),
        "push": {
            "magnitude_n": PUSH_MAGNITUDE,
            "onset_s": args.push_onset,
            "duration_s": args.push_duration,
            "within_horizon": args.push_onset < args.horizon,
        },
        "runs": [],
    }
    if args.push_onset >= args.horizon:
        print(
            f"note: the push (onset {args.push_onset} s) starts after the horizon ({args.horizon} s): "
            "the closed loops run without it",
            file=sys.stderr,
        )

    def save():
        io.atomic_write_json(out / "bench.json", result)

    def emit(row):
        print(json.dumps(row), flush=True)

    if not args.skip_equivalence:
        for it in args.iterations:
            eq = equivalence_check(1.0, it)
            emit(eq)
            result.setdefault("equivalence", []).append(eq)
            save()

    for backend in backends:
        for it in args.iterations:
            batches = list(args.batches)
            if args.find_largest:  # doublings past the last requested size, until one fails
                batches += [max(args.batches) * 2**k for k in range(1, args.find_largest + 1)]
            st = make_setup(
                backend,
                args.horizon,
                it,
                qp_warm_start=args.qp_warm_start,
                qp_unrolled_steps=args.qp_unrolled_steps,
                qp_engine=args.qp_engine,
                warp_terms=args.warp_terms if backend == "warp" else "jax",
                mass_solve_engine=args.mass_solve_engine,
                ritz_engine=args.ritz_engine,
            )
            iterations = int(physics.solver_mj_model(st.robot.mj_model, st.loop.cfg.physics).opt.iterations)
            tau = None if args.skip_physics_only else hold_torques(st)
            for batch in batches:
                row = {
                    "backend": backend,
                    "qp_warm_start": args.qp_warm_start,
                    "qp_unrolled_steps": args.qp_unrolled_steps,
                    # the engines as resolved here (an "auto" recorded as what it names)
                    "qp_engine": st.loop.controller.config.qp_engine,
                    "warp_terms": st.loop.warp_terms,
                    "mass_solve_engine": st.loop.controller.config.mass_solve_engine,
                    "ritz_engine": args.ritz_engine,
                    "xla_flags": os.environ.get("XLA_FLAGS") or None,
                    "device": device_description(backend),
                    "batch": batch,
                    "solver_iterations": iterations,
                    "horizon_s": args.horizon,
                    "n_devices": 1 if backend == "mujoco" else len(jax.devices()),
                }
                try:
                    row.update(
                        time_closed_loop(
                            st, push_batch(st, batch, args.push_onset, args.push_duration), push_end, args.repeats
                        )
                    )
                    row["peak_memory_bytes"] = peak_memory()
                    row["memory_per_env_bytes"] = row["peak_memory_bytes"] / batch if row["peak_memory_bytes"] else None
                    if backend == "mujoco":  # C threads and XLA's controller share the host's cores
                        row["cpu_cores"] = os.cpu_count()
                        row["closed_loop_steps_per_s_per_core"] = row["closed_loop_steps_per_s"] / os.cpu_count()
                    if tau is not None:
                        row.update(time_physics_only(st, batch, tau, args.repeats))
                        row["controller_share"] = 1.0 - row["closed_loop_steps_per_s"] / row["physics_only_steps_per_s"]
                except Exception as err:  # out of memory: report the size that failed
                    traceback.print_exc()
                    row["error"] = repr(err)[:400]
                emit(row)
                result["runs"].append(row)
                save()
                if "error" in row and batch > max(args.batches):
                    break  # the largest batch that fits is the one before

    if args.cpu_baseline_envs:
        # The baseline runs the same solver settings as the closed loops: once per iteration
        # count (the worker scaling only for the first).
        for k, it in enumerate(args.iterations):
            workers_list = sorted(set(args.cpu_workers)) if k == 0 else [max(args.cpu_workers)]
            for workers in workers_list:
                base = baseline_cpu.benchmark(
                    n_envs=args.cpu_baseline_envs * workers,
                    n_workers=workers,
                    horizon=args.horizon,
                    push_onset=args.push_onset,
                    push_duration=args.push_duration,
                    solver_iterations=it,
                )
                base["steps_per_s_per_core"] = base["physics_steps_per_s"] / base["n_workers"]
                emit(base)
                result.setdefault("cpu_baseline", []).append(base)
            save()
            ref = base  # the largest worker count
            for row in result["runs"]:
                if row.get("solver_iterations") == ref["solver_iterations"] and "closed_loop_steps_per_s" in row:
                    row["cpu_baseline_steps_per_s"] = ref["physics_steps_per_s"]
                    row["cpu_baseline_workers"] = ref["n_workers"]
                    row["cpu_baseline_steps_per_s_per_core"] = ref["steps_per_s_per_core"]
                    row["ratio"] = row["closed_loop_steps_per_s"] / ref["physics_steps_per_s"]
                    if "closed_loop_steps_per_s_per_core" in row:
                        row["ratio_per_core"] = row["closed_loop_steps_per_s_per_core"] / ref["steps_per_s_per_core"]
                    emit(
                        {
                            k: row[k]
                            for k in (
                                "backend",
                                "batch",
                                "solver_iterations",
                                "closed_loop_steps_per_s",
                                "cpu_baseline_steps_per_s",
                                "cpu_baseline_workers",
                                "ratio",
                            )
                            if k in row
                        }
                    )
            save()

    if args.json:
        rows = json_rows(result)
        update_json_rows(pathlib.Path(args.json), rows)
        result["json_rows"] = rows
    result["check"] = checks.verdict(failures(result), BAR)
    save()
    print(json.dumps(result, indent=1, default=str), flush=True)
    return result


if __name__ == "__main__":
    from wbc_jax.core import checks

    sys.exit(checks.exit_status(main()))
