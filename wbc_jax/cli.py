"""``wbc-jax`` command line: one subcommand per job."""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np


def _info(args: argparse.Namespace) -> int:
    from wbc_jax import model

    print(json.dumps(model.summary(model.load_robot(args.robot)), indent=2))
    return 0


def _balance(args: argparse.Namespace) -> int:
    from wbc_jax import balance

    if args.duration is not None and not args.duration > 0:
        raise ValueError(f"--duration must be positive, got {args.duration}")
    push = None
    if args.push_force is not None:
        push = {"force": args.push_force, "onset": args.push_onset, "duration": args.push_duration}
    result = balance.run(
        args.task, duration=args.duration, forces=args.forces, postural=args.postural,
        out=args.out, gains_file=args.gains, push=push, progress=not args.quiet,
        solver_iterations=args.solver_iterations, tasks_file=args.tasks, control_dt=args.control_dt,
    )  # fmt: skip
    print(balance.main_json_line(result))
    return 0


def _push_sweep(args: argparse.Namespace) -> int:
    from wbc_jax import sweep

    def grid(lo_hi_n, name):
        lo, hi, n = lo_hi_n
        if int(n) < 1:
            raise ValueError(f"--{name} needs at least one point, got {int(n)}")
        return tuple(float(x) for x in np.linspace(lo, hi, int(n)))

    cfg = sweep.SweepConfig(
        magnitudes=grid(args.magnitudes, "magnitudes"),
        directions=tuple(float(x) for x in np.arange(int(args.directions)) * 360.0 / int(args.directions))
        if int(args.directions) >= 1 else (),
        gain_sets=args.gain_sets, horizon=args.horizon, task=args.task, forces=args.forces,
        postural=args.postural, seed=args.seed, chunk_size=args.chunk_size,
        push_duration=args.push_duration, push_onset=args.push_onset, body=args.body,
        joint_noise=args.joint_noise, friction=tuple(args.friction),
        mass_scale=tuple(args.mass_scale), solver_iterations=args.solver_iterations,
        tasks_file=args.tasks,
    )  # fmt: skip
    summary = sweep.run_sweep(cfg, args.out, gains_file=args.gains, progress=not args.quiet)
    keys = ("n_envs", "survival_rate", "nan_envs", "qp_infeasible_envs", "physics_steps_per_s",
            "compile_s", "run_s", "n_devices")  # fmt: skip
    print(json.dumps({k: summary[k] for k in keys}, separators=(",", ":")))
    return 0


def _view(args: argparse.Namespace) -> int:
    from wbc_jax import viz

    if args.spawn and args.out is not None:
        raise ValueError("--out and --spawn exclude each other: write a file or open a viewer")
    path = viz.view(args.run_dir, args.env, out=args.out, spawn=args.spawn)
    print(json.dumps({"rrd": None if path is None else str(path), "spawned": bool(args.spawn)}))
    return 0


def _tune(args: argparse.Namespace) -> int:
    from wbc_jax import tune

    kw = dict(steps=args.steps, batch=args.batch, horizon=args.horizon, seed=args.seed, lr=args.lr)
    tc = tune.TuneConfig(**{k: v for k, v in kw.items() if v is not None})
    report = tune.run(tc, args.out, baseline=not args.no_baseline, progress=not args.quiet)
    held = report["held_out"]
    print(json.dumps({name: {k: r[k] for k in ("objective", "survival_rate", "com_rmse_m", "effort_rms_nm")}
                      for name, r in held.items()}, separators=(",", ":")))  # fmt: skip
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="wbc-jax", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    info = sub.add_parser("info", help="print the robot model summary as JSON")
    info.add_argument("--robot", default="icub")
    info.set_defaults(func=_info)

    bal = sub.add_parser("balance", help="closed-loop balancing run: metrics, trajectory, plots")
    bal.add_argument("--task", default="stand", choices=["stand", "sinusoid", "one-foot"])
    bal.add_argument("--duration", type=float, default=None, help="seconds (task default)")
    bal.add_argument("--forces", default="qp", choices=["qp", "analytic"])
    bal.add_argument("--postural", default="stable", choices=["stable", "seed"])
    bal.add_argument("--gains", default=None, help="gains JSON file (default: WBC iCubGazeboV2_5)")
    bal.add_argument("--out", default="runs/balance", help="output folder")
    bal.add_argument("--push-force", type=float, nargs=3, default=None, metavar=("FX", "FY", "FZ"),
                     help="push on the chest, world axes [N]")  # fmt: skip
    bal.add_argument("--push-onset", type=float, default=1.0)
    bal.add_argument("--push-duration", type=float, default=0.1)
    bal.add_argument("--solver-iterations", type=int, default=None,
                     help="MJX Newton iterations (default: the model's, 4)")
    bal.add_argument("--control-dt", type=float, default=None,
                     help="controller period in s, a multiple of the 1 ms physics step (default 0.01)")
    bal.add_argument("--tasks", default=None, metavar="FILE",
                     help="task/contact file (JSON/YAML): motion tasks, contacts, scene objects, initial posture; "
                          "e.g. experiments/tasks/reach_circle.yaml, experiments/tasks/hand_on_table.yaml")
    bal.add_argument("--quiet", action="store_true", help="no progress bar")
    bal.set_defaults(func=_balance)

    sw = sub.add_parser("push-sweep", help="batched push-recovery sweep (the main job)")
    sw.add_argument("--magnitudes", type=float, nargs=3, default=[20.0, 100.0, 3],
                    metavar=("LO", "HI", "N"), help="push force grid [N]")  # fmt: skip
    sw.add_argument("--directions", type=int, default=4, help="number of azimuths over 360 deg")
    sw.add_argument("--gain-sets", type=int, default=1)
    sw.add_argument("--gains", default=None, help="gains JSON file (the first gain set)")
    sw.add_argument("--horizon", type=float, default=1.5, help="seconds per rollout")
    sw.add_argument("--push-duration", type=float, default=0.1)
    sw.add_argument("--push-onset", type=float, default=0.5)
    sw.add_argument("--body", default="chest", help="pushed body")
    sw.add_argument("--joint-noise", type=float, default=0.0, help="initial joint noise std [rad]")
    sw.add_argument("--friction", type=float, nargs=2, default=[1.0, 1.0], metavar=("LO", "HI"))
    sw.add_argument("--mass-scale", type=float, nargs=2, default=[1.0, 1.0], metavar=("LO", "HI"))
    sw.add_argument("--task", default="stand", choices=["stand", "one-foot"],
                    help="two feet (stand) or pushed in the single-support phase of the one-foot "
                         "task (7-9 s: e.g. --push-onset 7.5 --horizon 9)")  # fmt: skip
    sw.add_argument("--forces", default="qp", choices=["qp", "analytic"])
    sw.add_argument("--postural", default="stable", choices=["stable", "seed"])
    sw.add_argument("--solver-iterations", type=int, default=None)
    sw.add_argument("--seed", type=int, default=0)
    sw.add_argument("--tasks", default=None, metavar="FILE",
                    help="task/contact file (JSON/YAML), as balance --tasks")
    sw.add_argument("--chunk-size", type=int, default=12, help="environments per compiled batch")
    sw.add_argument("--out", default="runs/push_sweep")
    sw.add_argument("--quiet", action="store_true")
    sw.set_defaults(func=_push_sweep)

    vw = sub.add_parser("view", help="log a run (or one env of a push sweep) to rerun: .rrd or viewer")
    vw.add_argument("run_dir", help="output folder of a balance run or a push sweep")
    vw.add_argument("--env", type=int, default=None, help="sweep env to re-simulate and show")
    vw.add_argument("--out", default=None, help=".rrd file (default RUN_DIR/rollout.rrd or env_I.rrd)")
    vw.add_argument("--spawn", action="store_true", help="open a rerun viewer instead of a file")
    vw.set_defaults(func=_view)
    tn = sub.add_parser("tune", help="gradient-based gain tuning + held-out comparison")
    tn.add_argument("--out", default="runs/tune", help="output folder (resumes a run there)")
    tn.add_argument("--steps", type=int, default=None, help="optimiser steps (default 12)")
    tn.add_argument("--batch", type=int, default=None, help="push scenarios per step (default 4)")
    tn.add_argument("--horizon", type=float, default=None, help="seconds per rollout (default 1.0)")
    tn.add_argument("--seed", type=int, default=None, help="training scenarios seed (default 0)")
    tn.add_argument("--lr", type=float, default=None, help="adam learning rate (default 0.1)")
    tn.add_argument("--no-baseline", action="store_true", help="skip the random-search baseline")
    tn.add_argument("--quiet", action="store_true")
    tn.set_defaults(func=_tune)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (ValueError, FileNotFoundError) as err:
        print(f"wbc-jax {args.command}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
