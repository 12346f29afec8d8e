"""``wbc-jax`` command line: one subcommand per job; each job's flags and defaults are generated
from its ``default_config()`` (a frozen dataclass whose fields carry their help)."""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import types
import typing


def _field_type(owner: type, field: dataclasses.Field) -> type:
    """The scalar type of a config field (``float | None`` -> float, ``tuple[float, ...]`` -> float)."""
    hint = typing.get_type_hints(owner)[field.name]
    args = [a for a in typing.get_args(hint) if a is not type(None)]
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        hint = args[0]
    if typing.get_origin(hint) is tuple:
        inner = [a for a in typing.get_args(hint) if a is not Ellipsis]
        return inner[0] if inner else float
    return hint


class _Parser(argparse.ArgumentParser):
    """argparse with a one-line error (the problem and where help is) instead of the usage block."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _show(value) -> str:
    if isinstance(value, (tuple, list)):
        return " ".join(_show(v) for v in value)
    return f"{value:g}" if isinstance(value, float) else str(value)


def _number(kind: type, flag: str):
    def convert(text: str):
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{flag} expects a number, got {text!r}") from None
        if kind is int:
            if value != int(value):
                raise argparse.ArgumentTypeError(f"{flag} expects a whole number, got {text!r}")
            return int(value)
        return value

    return convert


def add_config_arguments(parser: argparse.ArgumentParser, config, skip=()) -> None:
    """One flag per field of the dataclass ``config`` (its values are the defaults)."""
    for field in dataclasses.fields(config):
        if field.name in skip:
            continue
        meta = field.metadata
        flag = meta.get("flag", "--" + field.name.replace("_", "-"))
        default = getattr(config, field.name)
        kind = _field_type(type(config), field)
        kwargs = {"dest": field.name, "help": meta.get("help", "")}
        if kind is bool:
            parser.add_argument(flag, action=argparse.BooleanOptionalAction, default=default, **kwargs)
            continue
        if "choices" in meta:
            kwargs["choices"] = list(meta["choices"])
        if "metavar" in meta:
            kwargs["metavar"] = meta["metavar"]
        if "nargs" in meta:
            kwargs["nargs"] = meta["nargs"]
        # Values given to a parse hook are read as numbers (its own checks name the problem).
        kwargs["type"] = _number(float if "parse" in meta else kind, flag) if kind in (int, float) else kind
        shown = meta["show"](default) if "show" in meta and default is not None else default
        kwargs["help"] += f" (default: {_show(shown)})"
        parser.add_argument(flag, default=argparse.SUPPRESS, **kwargs)


def config_from_args(args: argparse.Namespace, config):
    """The config with the flags given on the command line (``parse`` hooks applied)."""
    changes = {}
    for field in dataclasses.fields(config):
        if field.name not in vars(args):
            continue
        value = getattr(args, field.name)
        parse = field.metadata.get("parse")
        if parse is not None and value is not None:
            value = parse(value)
        elif isinstance(value, list):
            value = tuple(value)
        changes[field.name] = value
    return dataclasses.replace(config, **changes)


def push_sweep_config(flags: list[str]):
    """The checked config that ``wbc-jax push-sweep FLAGS`` would run: for the scripts of
    experiments/ that take the job's flags after ``--``."""
    from wbc_jax.jobs import sweep_config

    cfg = config_from_args(build_parser().parse_args(["push-sweep", *flags]), sweep_config.default_config())
    cfg.check()
    return cfg


def _info(args: argparse.Namespace) -> int:
    from wbc_jax.robot import model

    print(json.dumps(model.summary(model.load_robot(args.robot)), indent=2))
    return 0


def _balance(args: argparse.Namespace) -> int:
    from wbc_jax.jobs import balance
    from wbc_jax.sim import runner

    cfg = config_from_args(args, balance.default_config())
    cfg.check()
    runner.enable_compilation_cache()
    print(balance.main_json_line(balance.run(cfg, progress=not args.quiet)))
    return 0


def _push_sweep(args: argparse.Namespace) -> int:
    from wbc_jax.jobs import sweep, sweep_config
    from wbc_jax.sim import runner

    cfg = config_from_args(args, sweep_config.default_config())
    cfg.check()
    runner.enable_compilation_cache()
    summary = sweep.run_sweep(cfg, progress=not args.quiet)
    keys = ("n_envs", "survival_rate", "upright_rate", "nan_envs", "qp_infeasible_envs", "backend",
            "physics_steps_per_s", "compile_s", "run_s", "n_devices")  # fmt: skip
    print(json.dumps({k: summary[k] for k in keys}, separators=(",", ":")))
    return 0


def _envelope(args: argparse.Namespace) -> int:
    from wbc_jax.jobs import envelope
    from wbc_jax.sim import runner

    cfg = config_from_args(args, envelope.default_config())
    cfg.check()
    runner.enable_compilation_cache()
    found = envelope.search(cfg, resolution=args.resolution, progress=not args.quiet)
    line = {"rollouts": found["rollouts"], "grid_rollouts": found["grid_rollouts"], "rounds": found["rounds"],
            "backend": found["backend"],
            "run_s": found["run_s"], "compile_s": found["compile_s"],
            "impulse_ns": {str(a): e["impulse_ns"] for a, e in found["envelope"][0].items()}}  # fmt: skip
    print(json.dumps(line, separators=(",", ":")))
    return 0


def _view(args: argparse.Namespace) -> int:
    from wbc_jax.jobs import view

    if args.spawn and args.out is not None:
        raise ValueError("--out and --spawn exclude each other: write a file or open a viewer")
    path = view.view(args.run_dir, args.env, out=args.out, spawn=args.spawn)
    print(json.dumps({"rrd": None if path is None else str(path), "spawned": bool(args.spawn)}))
    return 0


def _tune(args: argparse.Namespace) -> int:
    from wbc_jax.sim import runner
    from wbc_jax.tuning import campaign, config

    cfg = config_from_args(args, config.default_config())
    cfg.check()
    # The held-out fields shared with the tuning run (tasks, angular_weight_soft) are the run's.
    hc = config_from_args(args, config.heldout_default_config())
    runner.enable_compilation_cache()
    summary = campaign.run(cfg, hc, progress=not args.quiet)
    print(json.dumps(summary, separators=(",", ":"), default=str))
    return 0


def _heldout(args: argparse.Namespace) -> int:
    from wbc_jax.sim import runner
    from wbc_jax.tuning import config, heldout

    cfg = config_from_args(args, config.heldout_default_config())
    cfg.check()
    runner.enable_compilation_cache()
    print(json.dumps(heldout.run(cfg, progress=not args.quiet), separators=(",", ":")))
    return 0


def build_parser() -> argparse.ArgumentParser:
    from wbc_jax.jobs import balance, sweep_config
    from wbc_jax.jobs.envelope import default_config as envelope_default
    from wbc_jax.tuning import config as tune_config

    parser = _Parser(prog="wbc-jax", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    info = sub.add_parser("info", help="print the robot model summary as JSON")
    info.add_argument("--robot", default="icub")
    info.set_defaults(func=_info)

    bal = sub.add_parser("balance", help="closed-loop balancing run: metrics, trajectory, plots")
    add_config_arguments(bal, balance.default_config())
    bal.add_argument("--quiet", action="store_true", help="no progress bar")
    bal.set_defaults(func=_balance)

    sw = sub.add_parser("push-sweep", help="batched push-recovery sweep (the main job)")
    add_config_arguments(sw, sweep_config.default_config())
    sw.add_argument("--quiet", action="store_true", help="no progress bar")
    sw.set_defaults(func=_push_sweep)

    ev = sub.add_parser("envelope", help="recovery envelope by batched bisection over the sweep's magnitudes")
    add_config_arguments(ev, envelope_default())
    ev.add_argument("--resolution", type=float, default=0.25, help="bracket width to reach [N s] (default: 0.25)")
    ev.add_argument("--quiet", action="store_true", help="no progress bar")
    ev.set_defaults(func=_envelope)

    vw = sub.add_parser("view", help="log a run (or one env of a push sweep) to rerun: .rrd or viewer")
    vw.add_argument("run_dir", help="output folder of a balance run or a push sweep")
    vw.add_argument("--env", type=int, default=None, help="sweep env to re-simulate and show")
    vw.add_argument("--out", default=None, help=".rrd file (default RUN_DIR/rollout.rrd or env_I.rrd)")
    vw.add_argument("--spawn", action="store_true", help="open a rerun viewer instead of a file")
    vw.set_defaults(func=_view)

    tn = sub.add_parser("tune", help="gain tuning in phases: gradient, CMA-ES, random search, held-out evaluation")
    add_config_arguments(tn, tune_config.default_config())
    add_config_arguments(tn, tune_config.heldout_default_config(), skip=("out", "tasks", "angular_weight_soft"))
    tn.add_argument("--quiet", action="store_true", help="no progress bar")
    tn.set_defaults(func=_tune)

    ho = sub.add_parser("heldout", help="gain files on the held-out grid, variations, one-foot task and sinusoid")
    add_config_arguments(ho, tune_config.heldout_default_config())
    ho.add_argument("--quiet", action="store_true", help="no progress bar")
    ho.set_defaults(func=_heldout)
    return parser


def main(argv: list[str] | None = None) -> int:
    # Before JAX starts: XLA:CPU logs an error line for each program read back from the persistent
    # compilation cache (its tuning flags "prefer-no-gather/scatter" are not host CPU features), which
    # would bury the commands' output; the programs run correctly.
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (ValueError, FileNotFoundError, NotADirectoryError, IsADirectoryError, PermissionError) as err:
        print(f"wbc-jax {args.command}: error: {err}", file=sys.stderr)
        return 2
    except ImportError as err:
        print(f"wbc-jax {args.command}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
