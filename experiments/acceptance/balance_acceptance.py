"""Measured acceptance of the balancing controller (issue: the controller of the seed paper).

    python experiments/acceptance/balance_acceptance.py [--robot NAME] [--only NAME ...] [--out runs/acceptance]
        [--summary FILE] [--qp-warm-start] [--qp-engine ENGINE]

Runs each scenario with ``wbc_jax.jobs.balance.run`` and merges the metrics into
``results/balance_acceptance.json`` (the default robot's; another robot's into
``results/<robot>/balance_acceptance.json``; one key per scenario, NAME-mjx on ``--backend jax``;
re-running one scenario updates it).
Scenarios: stand (10 s), sinusoid (20 s, 2 cm at 0.2 Hz), one-foot (16 s), push-qp /
push-analytic (same lateral push, both force distributions), sinusoid-60-stable /
sinusoid-60-seed (postural variants over 60 s) and the joint-error figure of the last two.
"""

from __future__ import annotations

import argparse
import json
import pathlib

import numpy as np

from wbc_jax.control.qp import QP_ENGINES
from wbc_jax.core import io, provenance
from wbc_jax.jobs import balance
from wbc_jax.robot.robots import DEFAULT_ROBOT, ROBOT_NAMES
from wbc_jax.sim import runner

ROOT = pathlib.Path(__file__).resolve().parents[2]

# 4 N s lateral: inside the measured survival envelope at 90 deg (~6 N s, results/sweep_h100).
PUSH = {"push_force": (0.0, 40.0, 0.0), "push_onset": 1.0, "push_duration": 0.1}  # trunk, world +y (left)

SCENARIOS = {
    "stand": dict(task="stand", duration=10.0),
    "sinusoid": dict(task="sinusoid", duration=20.0),
    "one-foot": dict(task="one-foot", duration=16.0),
    "push-qp": dict(task="stand", duration=4.0, forces="qp", **PUSH),
    "push-analytic": dict(task="stand", duration=4.0, forces="analytic", **PUSH),
    "sinusoid-60-stable": dict(task="sinusoid", duration=60.0, postural="stable"),
    "sinusoid-60-seed": dict(task="sinusoid", duration=60.0, postural="seed"),
}


def joint_error_figure(out: pathlib.Path, dest: pathlib.Path) -> dict:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4))
    summary = {}
    for variant in ("stable", "seed"):
        path = out / f"sinusoid-60-{variant}" / "trajectory.npz"
        if not path.exists():
            continue
        z = np.load(path)
        err = np.linalg.norm(z["s"] - z["s_des"], axis=1)
        ax.plot(z["t"], np.rad2deg(err), label=f"postural = {variant}")
        last = z["t"] >= z["t"][-1] - 10.0
        first = (z["t"] >= 5.0) & (z["t"] < 15.0)
        summary[variant] = {
            "joint_err_deg_5_15s": float(np.rad2deg(err[first]).mean()),
            "joint_err_deg_last_10s": float(np.rad2deg(err[last]).mean()),
            "joint_err_deg_max": float(np.rad2deg(err).max()),
        }
    ax.set_xlabel("time [s]")
    ax.set_ylabel("|s - s_d| [deg]")
    ax.set_title("CoM sinusoid 2 cm / 0.2 Hz: joint-space error, postural task variants")
    ax.legend()
    fig.tight_layout()
    fig.savefig(dest, dpi=110)
    plt.close(fig)
    return summary


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--only", nargs="*", default=list(SCENARIOS), choices=list(SCENARIOS))
    parser.add_argument("--robot", default=DEFAULT_ROBOT, choices=list(ROBOT_NAMES))
    parser.add_argument("--out", default=str(ROOT / "runs" / "acceptance"))
    parser.add_argument(
        "--summary",
        default=None,
        help="default: results/balance_acceptance.json, another robot's results/<robot>/balance_acceptance.json",
    )
    parser.add_argument("--backend", default="auto", help="physics backend (wbc_jax.sim.physics.BACKENDS)")
    parser.add_argument(
        "--solver-iterations",
        type=int,
        default=None,
        help="MJX Newton iterations (default: the model's 4); results keyed NAME-itN",
    )
    parser.add_argument(
        "--qp-warm-start",
        action="store_true",
        help="the force QP warm-started (ControllerConfig.qp_warm_start); compare with cpu_loop.py's acceptance part",
    )
    parser.add_argument(
        "--qp-engine",
        default="jax",
        choices=list(QP_ENGINES),
        help="the force QP's solver (ControllerConfig.qp_engine; the Warp engines need warp-lang)",
    )
    args = parser.parse_args(argv)
    record = provenance.record(argv=provenance.script_argv(__file__, argv))
    runner.enable_compilation_cache()  # scenarios of the same shape compile once, as in the CLI
    results = ROOT / "results" if args.robot == DEFAULT_ROBOT else ROOT / "results" / args.robot
    out = pathlib.Path(args.out) if args.robot == DEFAULT_ROBOT else pathlib.Path(args.out) / args.robot
    summary_path = pathlib.Path(args.summary) if args.summary else results / "balance_acceptance.json"
    summary_path.parent.mkdir(parents=True, exist_ok=True)
    it = args.solver_iterations
    for name in args.only:
        key = name if it is None else f"{name}-it{it}"
        key += "-mjx" if args.robot != DEFAULT_ROBOT and args.backend == "jax" else ""
        result = balance.run(
            out=str(out / key),
            progress=False,
            solver_iterations=it,
            backend=args.backend,
            robot=args.robot,
            qp_warm_start=args.qp_warm_start,
            qp_engine=args.qp_engine,
            **SCENARIOS[name],
        )
        print(key, json.dumps(result), flush=True)
        # Merge (re-read: other processes may have written other scenarios meanwhile).
        current = json.loads(summary_path.read_text()) if summary_path.exists() else {}
        current[key] = {**result, "provenance": record}
        io.atomic_write_json(summary_path, current)
    if (out / "sinusoid-60-stable").exists() or (out / "sinusoid-60-seed").exists():
        figure = (
            summary_path.parent / "postural_joint_error.png"
        )  # beside its summary (--summary elsewhere: not results/)
        current = json.loads(summary_path.read_text()) if summary_path.exists() else {}
        current["postural_comparison"] = {**joint_error_figure(out, figure), "provenance": record}
        io.atomic_write_json(summary_path, current)


if __name__ == "__main__":
    main()
