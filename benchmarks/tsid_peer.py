"""[TSID peer] One-core measurement of the TSID balancing controller (``benchmarks/tsid_baseline/``).

In one run, on one core (BLAS/OpenMP threads set to 1 before numpy loads; TSID, Pinocchio and C
MuJoCo step one robot in one thread; ``--cpu`` also pins the process to one core):

1. the control tick's time: the state map, TSID (problem data + eiquadprog solve + torques), and
   the physics (``mj_step1`` + ``mj_step2`` + 9 ``mj_step``) separately, over the 20 s sinusoid;
2. the 20 s sinusoid's CoM tracking (``com_rmse_m`` and the other ``constants.METRIC_NAMES``) and
   the 10 s stand task's;
3. the strict recovery envelope over the chest-push grid of ``wbc_jax/jobs/envelope.py``
   (``DEFAULT_MAGNITUDES``: 64 forces of 10-400 N for 0.1 s from 0.5 s, 32 azimuths, 3 s horizon):
   per direction the largest impulse that survives the strict criterion, by the two-phase bisection
   of ``wbc_jax.jobs.envelope.bisect`` (6 rounds over the 64 grid impulses, then 2 inside the bracketing
   step, to 0.25 N s: 8 rollouts per direction instead of 64); as a fraction of the feet-in-place LIP
   bound m omega d of ``wbc_jax.jobs.sweep_table.lip_bound``. ``--full-grid`` also runs all 64 x 32 pushes
   (survival rate and the grid's monotone envelope, as ``wbc_jax.jobs.sweep_table.envelope_of``);
4. ``--sensitivity``: the sinusoid and the envelope again with each setting that has no WBC
   counterpart changed, one at a time (``SENSITIVITY``);
5. ``--wbc-timing``: in the same run, right after TSID's timing, wbc_jax's controller on the same
   robot and task (``benchmarks/wbc_peer.py``'s timing part, a child process pinned alike: the
   compiled loop's CPU time per tick less C MuJoCo's), so that both per-tick times share a load.

``--robot`` picks the robot (``wbc_jax.robot.robots``: the iCub by default, or Talos from
example-robot-data's URDF); its MJCF, joints, feet, CoP rectangle and default gains come from its
description, the push body ``--body`` may be a role (``trunk``: the iCub's chest, Talos's torso_2_link).

The pushes (3, 4) are ``benchmarks/tsid_baseline/push_envelope.py``.

Writes a JSON file (default ``results/peers/tsid.json``): every figure with the command that produced
it, the CPU, the date, the load average, the package versions and the controller's settings.
JAX-free, as the baseline.

    python benchmarks/tsid_peer.py --cpu 1 --full-grid --sensitivity --out results/peers/tsid.json
    python benchmarks/tsid_peer.py --robot talos --cpu 1 --magnitudes 10 700 70 --directions 8 \\
        --horizon 2.5 --resolution 1 --wbc-timing --out results/talos/tsid_peer.json
"""

from __future__ import annotations

import os

for _name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_name] = "1"  # before numpy's BLAS starts its threads

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import datetime  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import pathlib  # noqa: E402
import platform  # noqa: E402
import shlex  # noqa: E402
import sys  # noqa: E402

import numpy as np  # noqa: E402

HERE = pathlib.Path(__file__).resolve().parent
# tsid_baseline is imported from this script's folder: Python puts it first on sys.path when the
# script runs (python benchmarks/tsid_peer.py).
import tsid_baseline as tb  # noqa: E402
from tsid_baseline.push_envelope import envelope, full_grid, sensitivity  # noqa: E402

from wbc_jax.robot.robots import DEFAULT_ROBOT, ROBOT_NAMES, describe  # noqa: E402

# The grid of wbc_jax/jobs/envelope.py (DEFAULT_MAGNITUDES) and of the documented 64 x 32 sweeps.
MAGNITUDES = (10.0, 400.0, 64)  # N: LO, HI, count (np.linspace)
DIRECTIONS = 32  # azimuths k 360 / N deg from 0 (forward; 90 = left)
PUSH_ONSET, PUSH_DURATION, HORIZON = 0.5, 0.1, 3.0  # s
RESOLUTION = 0.25  # N s: wbc_jax.jobs.envelope.search's default
CODE = ("benchmarks", "assets", "wbc_jax/core/constants.py")  # what the measurement runs (code_version)
PACKAGES = (
    "tsid",
    "libtsid",
    "pin",
    "libpinocchio",
    "eiquadprog",
    "mujoco",
    "numpy",
    "icub-models",
    "example-robot-data",
)


def versions() -> dict:
    """Versions of the packages of the measurement (None: not installed)."""
    from importlib import metadata

    out = {"python": platform.python_version()}
    for name in PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = None
    return out


def code_version() -> dict:
    """The repository's commit and whether the measurement's code (benchmarks/, assets/,
    wbc_jax/core/constants.py) differs from it in the working tree (None outside git)."""
    import subprocess

    def git(*cmd):
        return subprocess.run(["git", *cmd], cwd=HERE.parent, capture_output=True, text=True, check=True).stdout.strip()

    try:
        return {"commit": git("rev-parse", "HEAD"), "dirty": bool(git("status", "--porcelain", "--", *CODE))}
    except (OSError, subprocess.CalledProcessError):
        return {"commit": None, "dirty": None}


def _rounded(summary: dict) -> dict:
    return {k: (round(v, 9) if isinstance(v, float) else v) for k, v in summary.items()}


def measure(args, log=print) -> dict:
    """Everything of the module docstring, as a JSON-ready dict."""
    command = "python benchmarks/tsid_peer.py " + " ".join(shlex.quote(a) for a in args.argv)
    load_start = os.getloadavg()
    peer = tb.TsidPeer(robot=args.robot)
    config = tb.TsidConfig()
    log(f"sinusoid x {args.timing_repeats} (timing)")
    runs = [
        peer.simulate("sinusoid", duration=args.sinusoid_duration, timing=True, record=False, config=config)
        for _ in range(args.timing_repeats)
    ]
    sin = runs[0]
    if any(r["summary"] != sin["summary"] for r in runs[1:]):
        raise RuntimeError("the sinusoid's repeats differ: the closed loop is not deterministic")
    log("stand")
    stand = peer.simulate("stand", duration=args.stand_duration, record=True, config=config)
    drift = float(np.linalg.norm(stand["com"][-1] - stand["com_ref"][-1]))
    # The median repeat per quantity (a shared machine's other load only adds time), and each repeat's.
    per_tick = [k for k in sin["timing"] if k.endswith(("_per_tick", "_per_mj_step"))]
    timing = {k: round(float(np.median([r["timing"][k] for r in runs])), 3) for k in per_tick}
    timing["repeats"] = {k: [round(r["timing"][k], 3) for r in runs] for k in per_tick}
    timing["ticks"] = sin["n_ticks"]
    for kind in ("", "cpu_"):  # simulated seconds per second of the loop (controller + physics)
        loop_s = [sum(r["timing"][f"{part}_{kind}s"] for part in ("state_map", "tsid", "physics")) for r in runs]
        timing[f"real_time_factor{'_cpu' if kind else ''}"] = round(
            sin["n_ticks"] * peer.control_dt / float(np.median(loop_s)), 2
        )
    out = {
        "peer": "TSID (Pinocchio + eiquadprog) on C MuJoCo, benchmarks/tsid_baseline/",
        "robot": args.robot,
        "command": command,
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "cpu": tb.bc.cpu_name(),
        "cpu_count": os.cpu_count(),
        "affinity": sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "threads": {k: os.environ.get(k) for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")},
        "versions": versions(),
        "code": code_version(),
        "controller": {
            **{k: v for k, v in dataclasses.asdict(config).items() if not k.startswith(("kp_", "kd_"))},
            "gains": {k: v.tolist() for k, v in config.gains(peer.description).items()},
            "foot_size": config.sole_rectangle(peer.description),
            "mu": tb.floor_friction(peer.mj_model) if config.mu is None else config.mu,
            "solver": "tsid.SolverHQuadProgFast (eiquadprog), one solve per 10 ms tick",
        },
        "timing": {
            "command": command,
            "task": f"sinusoid, {args.sinusoid_duration} s, one robot, one thread, "
            f"median of {args.timing_repeats} runs (microseconds per 10 ms tick)",
            **timing,
        },
        "sinusoid": {"command": command, "duration_s": args.sinusoid_duration, **_rounded(sin["summary"])},
        "stand": {
            "command": command,
            "duration_s": args.stand_duration,
            "com_drift_m": drift,
            **_rounded(stand["summary"]),
        },
    }
    if args.wbc_timing:
        log("wbc_jax timing (benchmarks/wbc_peer.py, a child process)")
        out["wbc_jax"] = wbc_timing(args)
    if args.no_envelope:
        out["load_average"] = {
            "start": [round(x, 2) for x in load_start],
            "end": [round(x, 2) for x in os.getloadavg()],
        }
        return out
    log("envelope (bisection)")
    grid_def = {
        "magnitudes_n": list(args.magnitudes),
        "directions": args.directions,
        "push_onset_s": args.push_onset,
        "push_duration_s": args.push_duration,
        "horizon_s": args.horizon,
        "body": args.body,
        "survival": "strict (constants.SURVIVAL_CRITERION)",
    }
    out["envelope"] = {"command": command, **grid_def, **envelope(peer, config, args, log)}
    if args.full_grid:
        log("full grid")
        out["grid"] = {"command": command, **grid_def, **full_grid(peer, config, args, log)}
    if args.sensitivity:
        out["sensitivity"] = {
            "command": command,
            "what": "one setting changed from the defaults; the envelope by the same bisection and grid",
            **sensitivity(peer, args, log),
        }
    out["load_average"] = {"start": [round(x, 2) for x in load_start], "end": [round(x, 2) for x in os.getloadavg()]}
    return out


def wbc_timing(args) -> dict:
    """wbc_jax's controller on the same robot, task and core (``benchmarks/wbc_peer.py --timing-worker``:
    its default gains, the 20 s sinusoid, medians of ``--timing-repeats`` runs), as that script
    reports it: {timing, sinusoid, stand, command}."""
    import subprocess

    cmd = [
        sys.executable,
        str(HERE / "wbc_peer.py"),
        "--timing-worker",
        "--robot",
        args.robot,
        "--gains",
        "default",
        "--timing-repeats",
        str(args.timing_repeats),
        *(["--cpu", str(args.cpu)] if args.cpu is not None else []),
    ]
    env = {k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS")}  # the worker sets its own
    proc = subprocess.run(
        cmd, capture_output=True, text=True, cwd=HERE.parent, timeout=3600, env={**env, "JAX_PLATFORMS": "cpu"}
    )
    if proc.returncode != 0:
        raise SystemExit(f"error: wbc_jax's timing failed:\n{proc.stderr[-3000:]}")
    part = json.loads([line for line in proc.stdout.splitlines() if line.startswith("{")][-1])
    return {"command": " ".join(shlex.quote(c) for c in cmd[1:]), **part}


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--out", default=str(HERE.parent / "results" / "peers" / "tsid.json"), help="JSON file to write")
    p.add_argument("--cpu", type=int, default=None, help="pin the process to this core (default: no pinning)")
    p.add_argument(
        "--magnitudes", type=float, nargs=3, default=MAGNITUDES, metavar=("LO", "HI", "N"), help="push force grid [N]"
    )
    p.add_argument("--directions", type=int, default=DIRECTIONS, help="azimuths over 360 deg")
    p.add_argument("--push-onset", type=float, default=PUSH_ONSET)
    p.add_argument("--push-duration", type=float, default=PUSH_DURATION)
    p.add_argument("--horizon", type=float, default=HORIZON, help="seconds per push rollout")
    p.add_argument("--robot", default=DEFAULT_ROBOT, choices=ROBOT_NAMES, help="the robot (wbc_jax/robot/<name>.py)")
    p.add_argument(
        "--body", default="trunk", help="pushed body, or a role (trunk: the iCub's chest, Talos's torso_2_link)"
    )
    p.add_argument("--resolution", type=float, default=RESOLUTION, help="envelope bracket [N s]")
    p.add_argument("--sinusoid-duration", type=float, default=tb.TASK_DURATION["sinusoid"])
    p.add_argument("--stand-duration", type=float, default=tb.TASK_DURATION["stand"])
    p.add_argument("--timing-repeats", type=int, default=5, help="sinusoid runs for the tick timing (median)")
    p.add_argument(
        "--no-envelope",
        action="store_true",
        help="timing, sinusoid and stand only (no pushes): the tick beside benchmarks/cpu_loop.py's",
    )
    p.add_argument("--full-grid", action="store_true", help="also run every push of the grid")
    p.add_argument(
        "--wbc-timing", action="store_true", help="also time wbc_jax's controller on the same robot in this run"
    )
    p.add_argument("--sensitivity", action="store_true", help="also the envelope of each SENSITIVITY variant")
    p.add_argument(
        "--rollout-timeout",
        type=float,
        default=120.0,
        help="seconds one push rollout may take before the process ends with a traceback",
    )
    args = p.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    lo, hi, n = args.magnitudes
    if not (0 < lo < hi and n == int(n) and n >= 2):
        p.error(f"--magnitudes needs 0 < LO < HI and a whole N >= 2, got {args.magnitudes}")
    for name in ("directions", "timing_repeats"):
        if getattr(args, name) < 1:
            p.error(f"--{name.replace('_', '-')} must be >= 1")
    for name in (
        "push_onset",
        "push_duration",
        "horizon",
        "resolution",
        "sinusoid_duration",
        "stand_duration",
        "rollout_timeout",
    ):
        value = getattr(args, name)
        if not (math.isfinite(value) and value > 0):
            p.error(f"--{name.replace('_', '-')} must be a positive number, got {value}")
    if args.horizon <= args.push_onset + args.push_duration:
        p.error(f"--horizon {args.horizon} s must end after the push ({args.push_onset} + {args.push_duration} s)")
    return args


def main(argv=None) -> dict:
    args = parse_args(argv)
    problem = tb.tsid_problem()
    if problem is not None:
        raise SystemExit(f"error: {problem}")
    try:
        tb.body_id(tb.load_mj_model(robot=args.robot), describe(args.robot).body(args.body))
    except ValueError as err:
        raise SystemExit(f"error: --body: {err}") from None
    if args.cpu is not None:
        if not hasattr(os, "sched_setaffinity"):
            raise SystemExit("error: --cpu needs os.sched_setaffinity (Linux)")
        if args.cpu not in os.sched_getaffinity(0):
            raise SystemExit(
                f"error: --cpu {args.cpu} is not one of this process's cores {sorted(os.sched_getaffinity(0))}"
            )
        os.sched_setaffinity(0, {args.cpu})
    result = measure(args, log=lambda s: print(s, flush=True))
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(out.suffix + ".tmp")
    tmp.write_text(json.dumps(result, indent=1) + "\n")
    tmp.replace(out)
    t = result["timing"]
    print(
        f"wrote {out}: tick {t['controller_us_per_tick']:.0f} us controller + {t['physics_us_per_tick']:.0f} us "
        f"physics (CPU time {t['controller_cpu_us_per_tick']:.0f} + {t['physics_cpu_us_per_tick']:.0f}); "
        "sinusoid CoM RMSE "
        f"{result['sinusoid']['com_rmse_m'] * 1e3:.3f} mm"
    )
    if "envelope" in result:
        e = result["envelope"]
        print(f"envelope {e['fraction_of_bound_median']:.3f} ({e['fraction_of_bound_min']:.3f}) of the LIP bound")
    return result


if __name__ == "__main__":
    main()
