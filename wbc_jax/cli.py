"""``wbc-jax`` command line: one subcommand per job."""

from __future__ import annotations

import argparse
import json
import sys


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
    )  # fmt: skip
    print(balance.main_json_line(result))
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
    bal.add_argument("--quiet", action="store_true", help="no progress bar")
    bal.set_defaults(func=_balance)
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
