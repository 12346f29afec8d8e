"""Our controller measured as the TSID peer is (``benchmarks/tsid_peer.py``, branch tsid), per gain set.

    python benchmarks/wbc_peer.py --cpu 1 --gains default experiments/gains/tuned_gradient.json \\
        --out results/peers/wbc_jax.json [--parts timing envelope grid]

For each gain set (``default``: the WBC gains; or a gains file), on C MuJoCo 3.17.0 with the same
MJCF, 1 kHz physics, 10 ms ticks and chest pushes through ``xfrc_applied``:

1. ``timing`` (a child process pinned to the core ``--cpu``, BLAS/OpenMP threads 1): the 20 s
   sinusoid of ``wbc-jax balance --task sinusoid`` (trajectories recorded, as the job does) run
   ``--timing-repeats`` times by the compiled loop (one XLA program, C MuJoCo called from it:
   :mod:`wbc_jax.sim.host_scan`): wall and CPU time of the loop per 10 ms tick, the CPU time of
   the physics (C MuJoCo's steps, timed inside the program by the native step) and the rest
   (controller, metrics, records: the loop's CPU time less the physics'); medians of the repeats.
   Then the sinusoid's CoM tracking (the metrics of ``constants.METRIC_NAMES``) and the 10 s stand
   task's CoM drift;
2. ``envelope``: the strict recovery envelope by ``wbc-jax envelope``'s bisection over the 64 x 32
   chest-push grid (10-400 N for 0.1 s from 0.5 s, 3 s horizon; 0.25 N s resolution), as a fraction
   of the feet-in-place LIP bound m omega d;
3. ``grid``: every push of that grid (``wbc-jax push-sweep``): strict and lax survival rates and
   each direction's monotone envelope.

The envelope and the grid use every core (the Python loop of ticks, two pipelined halves); only
the timing is on one core. Writes ``--out`` (merged: parts run later update their keys) with the
command, CPU, date, load average and versions; the keys of each gain set follow tsid.json's.
``benchmarks/peers_table.py`` puts both files side by side.
"""

from __future__ import annotations

import os
import sys

if __name__ == "__main__" and "--timing-worker" in sys.argv:  # pin before JAX starts its threads
    for _name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "PJRT_NPROC"):
        os.environ[_name] = "1"  # PJRT_NPROC: XLA's CPU pool, one thread (as wbc-jax balance)
    _cpu = sys.argv[sys.argv.index("--cpu") + 1] if "--cpu" in sys.argv else None
    if _cpu is not None:
        os.sched_setaffinity(0, {int(_cpu)})

import argparse
import datetime
import json
import pathlib
import shlex
import subprocess
import time

ROOT = pathlib.Path(__file__).resolve().parent.parent

PARTS = ("timing", "envelope", "grid")
MAGNITUDES = (10.0, 400.0, 64)  # N: the grid of wbc_jax.jobs.envelope and tsid_peer.py
DIRECTIONS, PUSH_ONSET, PUSH_DURATION, HORIZON, RESOLUTION = 32, 0.5, 0.1, 3.0, 0.25


def gain_label(gains: str) -> str:
    return "default" if gains == "default" else pathlib.Path(gains).stem


def _summary(metrics) -> dict:
    import jax

    from wbc_jax.sim import metrics as metrics_lib

    s = metrics_lib.summarize(jax.tree_util.tree_map(lambda x: x[0], metrics))
    s = {k: v.item() if hasattr(v, "item") else v for k, v in s.items()}  # numpy scalars
    return {k: (round(v, 9) if isinstance(v, float) else v) for k, v in s.items()}


def timing(gains: str, repeats: int, robot: str) -> dict:
    """Part 1 in this (pinned) process: the sinusoid's loop timing and tracking, the stand's drift."""
    import numpy as np

    from wbc_jax.jobs import balance
    from wbc_jax.sim import host_loop, native, runner, scenario

    runner.enable_compilation_cache()
    file = None if gains == "default" else gains
    st = balance.make_setup(
        balance.BalanceConfig(robot=robot, task="sinusoid", duration=20.0, gains=file, backend="mujoco")
    )
    driver = host_loop.driver(st.loop)
    runner.run(st, scenario.single(st))  # compile (or load) and warm up
    rows = []
    for _ in range(repeats):
        native.physics_cpu(reset=True)
        wall, cpu = time.perf_counter(), time.process_time()
        run = runner.run(st, scenario.single(st))
        cpu = time.process_time() - cpu
        physics_s, ticks = native.physics_cpu()
        if ticks != st.loop.n_ticks:
            raise RuntimeError(f"{ticks} physics ticks counted for {st.loop.n_ticks}: not the compiled loop")
        rows.append(
            {"loop_s": run.run_s, "cpu_s": cpu, "physics_cpu_s": physics_s, "wall_s": time.perf_counter() - wall}
        )
    T = st.loop.n_ticks
    per_tick = {
        "loop_us_per_tick": [1e6 * r["loop_s"] / T for r in rows],
        "loop_cpu_us_per_tick": [1e6 * r["cpu_s"] / T for r in rows],
        "physics_cpu_us_per_tick": [1e6 * r["physics_cpu_s"] / T for r in rows],
        "controller_cpu_us_per_tick": [1e6 * (r["cpu_s"] - r["physics_cpu_s"]) / T for r in rows],
    }
    out = {k: round(float(np.median(v)), 3) for k, v in per_tick.items()}
    out["physics_cpu_us_per_mj_step"] = round(out["physics_cpu_us_per_tick"] / st.loop.n_sub, 3)
    out["real_time_factor"] = round(1e6 * st.loop.cfg.control_dt / out["loop_us_per_tick"], 2)
    out["real_time_factor_cpu"] = round(1e6 * st.loop.cfg.control_dt / out["loop_cpu_us_per_tick"], 2)
    out["repeats"] = {k: [round(x, 3) for x in v] for k, v in per_tick.items()}
    out["ticks"] = T
    out["driver"] = driver
    out["what"] = (
        "the 20 s sinusoid of `wbc-jax balance --task sinusoid` (trajectories recorded) by the compiled "
        "loop, one core; controller = the loop's process CPU time less the physics' (controller, metrics, "
        f"records and the program's own work); medians of {repeats} runs after a warm-up"
    )
    sinusoid = {"duration_s": 20.0, **_summary(run.metrics)}
    stand_st = balance.make_setup(
        balance.BalanceConfig(robot=robot, task="stand", duration=10.0, gains=file, backend="mujoco")
    )
    stand = runner.run(stand_st, scenario.single(stand_st))
    com, ref = stand.records.com[0], stand.records.com_ref[0]
    stand_row = {"duration_s": 10.0, "com_drift_m": float(np.linalg.norm(com[-1] - ref[-1])), **_summary(stand.metrics)}
    return {
        "timing": out,
        "sinusoid": sinusoid,
        "stand": stand_row,
        "affinity": sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "robot": robot,
    }


def _sweep_config(gains: str, out: str | None, robot: str):
    """The grid of the peer comparison as a sweep (and envelope) config."""
    import dataclasses

    import numpy as np

    from wbc_jax.jobs import envelope

    return dataclasses.replace(
        envelope.default_config(),
        robot=robot,
        magnitudes=tuple(float(x) for x in np.linspace(*MAGNITUDES[:2], MAGNITUDES[2])),
        directions=tuple(k * 360.0 / DIRECTIONS for k in range(DIRECTIONS)),
        push_onset=PUSH_ONSET,
        push_duration=PUSH_DURATION,
        horizon=HORIZON,
        body="trunk",
        gains=None if gains == "default" else gains,
        backend="mujoco",
        out=out,
        chunk_size=512,
    )


def envelope_part(gains: str, robot: str) -> dict:
    """Part 2: the bisection envelope (``wbc-jax envelope``)."""
    import numpy as np

    from wbc_jax.jobs import envelope
    from wbc_jax.sim import runner

    runner.enable_compilation_cache()
    t0 = time.perf_counter()
    found = envelope.search(_sweep_config(gains, None, robot), resolution=RESOLUTION, progress=False)
    rows = {f"{az:g}": e for az, e in found["envelope"][0].items()}
    frac = np.array([r["fraction_of_bound"] for r in rows.values()])
    imp = np.array([r["impulse_ns"] for r in rows.values()])
    azimuths = list(found["envelope"][0])
    return {
        "fraction_of_bound_median": float(np.median(frac)),
        "fraction_of_bound_min": float(np.min(frac)),
        "impulse_ns_median": float(np.median(imp)),
        "impulse_ns_min": float(np.min(imp)),
        "min_at_azimuth_deg": float(azimuths[int(np.argmin(frac))]),
        "rollouts": found["rollouts"],
        "rounds": found["rounds"],
        "grid_rollouts": found["grid_rollouts"],
        "run_s": round(time.perf_counter() - t0, 2),
        "compile_s": found["compile_s"],
        "grid_impulses": found["grid_impulses"],
        "resolution_ns": RESOLUTION,
        "backend": found["backend"],
        "directions": rows,
    }


def grid_part(gains: str, out: pathlib.Path, robot: str) -> dict:
    """Part 3: every push of the grid (``wbc-jax push-sweep``, resumable in ``out``)."""
    import numpy as np
    import pandas as pd

    from wbc_jax.jobs import sweep
    from wbc_jax.sim import runner

    runner.enable_compilation_cache()
    t0 = time.perf_counter()
    summary = sweep.run_sweep(_sweep_config(gains, str(out), robot), progress=False)
    table = pd.read_parquet(out / "results.parquet")
    survived = table.pivot_table(index="magnitude_n", columns="azimuth_deg", values="survived", aggfunc="max")
    rows = {}
    for az, e in summary["envelope"].items():
        rows[f"{float(az):g}"] = {
            "largest_survived_impulse_ns": e["largest_survived_impulse_ns"],
            "monotone_impulse_ns": e["monotone_impulse_ns"],
            "islands": e["survival_islands"],
            "bound_impulse_ns": e["bound_impulse_ns"],
            "monotone_fraction_of_bound": e["fraction_of_bound_monotone"],
        }
    frac = np.array([r["monotone_fraction_of_bound"] for r in rows.values()])
    return {
        "survival_rate": summary["survival_rate"],
        "upright_rate": summary["upright_rate"],
        "monotone_fraction_of_bound_median": float(np.median(frac)),
        "monotone_fraction_of_bound_min": float(np.min(frac)),
        "rollouts": summary["n_envs"],
        "run_s": round(time.perf_counter() - t0, 2),
        "sweep_run_s": summary["run_s"],
        "compile_s": summary["compile_s"],
        "backend": summary["backend"],
        "directions": rows,
        "survived": survived.to_numpy().astype(int).tolist(),
        "magnitudes_n": survived.index.tolist(),
        "azimuths_deg": [float(a) for a in survived.columns],
    }


def _versions() -> dict:
    import platform
    from importlib import metadata

    return {
        "python": platform.python_version(),
        **{n: metadata.version(n) for n in ("jax", "jaxlib", "mujoco", "mujoco-mjx", "numpy", "icub-models")},
        "wbc_jax": __import__("wbc_jax").__version__,
    }


def _code() -> dict:
    def git(*cmd):
        return subprocess.run(["git", *cmd], cwd=ROOT, capture_output=True, text=True, check=True).stdout.strip()

    try:
        return {
            "commit": git("rev-parse", "HEAD"),
            "dirty": bool(git("status", "--porcelain", "--", "wbc_jax", "benchmarks")),
        }
    except (OSError, subprocess.CalledProcessError):
        return {"commit": None, "dirty": None}


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument(
        "--gains",
        nargs="+",
        default=["default", "experiments/gains/tuned_gradient.json"],
        help="gain sets: 'default' (the WBC gains) or gains JSON files",
    )
    p.add_argument("--parts", nargs="+", default=list(PARTS), choices=PARTS)
    from wbc_jax.robot.robots import DEFAULT_ROBOT, ROBOT_NAMES  # JAX-free

    p.add_argument("--robot", default=DEFAULT_ROBOT, choices=ROBOT_NAMES, help="the robot (wbc_jax/robot/<name>.py)")
    p.add_argument("--cpu", type=int, default=None, help="the core the timing runs on (default: no pinning)")
    p.add_argument("--timing-repeats", type=int, default=5)
    p.add_argument("--out", default=str(ROOT / "results" / "peers" / "wbc_jax.json"))
    p.add_argument("--work", default=str(ROOT / "runs" / "peers"), help="sweep folders (resumable)")
    p.add_argument("--timing-worker", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    for g in args.gains:
        if g != "default" and not pathlib.Path(g).is_file():
            p.error(f"--gains: no such file {g!r} (or 'default')")
    if args.timing_repeats < 1:
        p.error("--timing-repeats must be >= 1")
    if args.cpu is not None and (not hasattr(os, "sched_getaffinity") or args.cpu not in os.sched_getaffinity(0)):
        p.error(f"--cpu {args.cpu} is not one of this process's cores")
    return args


def main(argv=None) -> dict:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parse_args(argv)
    if args.timing_worker:  # the child of the timing part: one gain set, JSON on stdout
        print(json.dumps(timing(args.gains[0], args.timing_repeats, args.robot)), flush=True)
        return {}
    from wbc_jax.core import provenance

    out = pathlib.Path(args.out)
    command = "python benchmarks/wbc_peer.py " + " ".join(shlex.quote(a) for a in argv)
    result = json.loads(out.read_text()) if out.exists() else {}
    result.update(
        {
            "peer": "wbc_jax: the momentum-based whole-body controller (JAX, compiled by XLA) on C MuJoCo",
            "command": command,
            "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
            "cpu": provenance.device_label(),
            "cpu_count": os.cpu_count(),
            "provenance": provenance.record(
                {f"gains {gain_label(g)}": g for g in args.gains if g != "default"}, argv=[__file__, *argv]
            ),
            "threads": {"OMP_NUM_THREADS": "1 (timing)", "XLA_FLAGS": os.environ.get("XLA_FLAGS", "")},
            "versions": _versions(),
            "code": _code(),
            "definitions": {
                "magnitudes_n": list(MAGNITUDES),
                "directions": DIRECTIONS,
                "push_onset_s": PUSH_ONSET,
                "push_duration_s": PUSH_DURATION,
                "horizon_s": HORIZON,
                "robot": args.robot,
                "body": "trunk",
                "resolution_ns": RESOLUTION,
                "survival": "strict (constants.SURVIVAL_CRITERION)",
            },
        }
    )
    load_start = os.getloadavg()
    sets = result.setdefault("gain_sets", {})

    def save():
        from wbc_jax.core import io

        result["load_average"] = {
            "start": [round(x, 2) for x in load_start],
            "end": [round(x, 2) for x in os.getloadavg()],
        }
        io.atomic_write_json(out, result)

    for gains in args.gains:
        entry = sets.setdefault(gain_label(gains), {})
        entry["gains"] = None if gains == "default" else gains
        if "timing" in args.parts:
            cmd = [
                sys.executable,
                str(pathlib.Path(__file__).resolve()),
                "--timing-worker",
                "--robot",
                args.robot,
                "--gains",
                gains,
                "--timing-repeats",
                str(args.timing_repeats),
                *(["--cpu", str(args.cpu)] if args.cpu is not None else []),
            ]
            proc = subprocess.run(
                cmd, capture_output=True, text=True, cwd=ROOT, timeout=3600, env={**os.environ, "JAX_PLATFORMS": "cpu"}
            )
            if proc.returncode != 0:
                raise SystemExit(f"error: the timing of {gains} failed:\n{proc.stderr[-3000:]}")
            part = json.loads([line for line in proc.stdout.splitlines() if line.startswith("{")][-1])
            for key in ("timing", "sinusoid", "stand"):
                entry[key] = {"command": command, "code": result["code"], **part[key]}
            entry["timing"]["affinity"] = part["affinity"]
            save()
            print(json.dumps({gain_label(gains): entry["timing"]}), flush=True)
        if "envelope" in args.parts:
            entry["envelope"] = {"command": command, "code": result["code"], **envelope_part(gains, args.robot)}
            save()
            e = entry["envelope"]
            print(
                json.dumps(
                    {gain_label(gains): {k: e[k] for k in ("fraction_of_bound_median", "fraction_of_bound_min")}}
                ),
                flush=True,
            )
        if "grid" in args.parts:
            entry["grid"] = {
                "command": command,
                **grid_part(gains, pathlib.Path(args.work) / gain_label(gains) / "grid", args.robot),
            }
            save()
            print(json.dumps({gain_label(gains): {"survival_rate": entry["grid"]["survival_rate"]}}), flush=True)
    save()
    return result


if __name__ == "__main__":
    main()
