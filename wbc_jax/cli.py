"""``wbc-jax`` command line: one subcommand per job; each job's flags and defaults are generated
from its ``default_config()`` (a frozen dataclass whose fields carry their help and valid values,
:mod:`wbc_jax.core.options`), and every job checks its config (``check()``: the declared ranges
first) before it loads a program or writes a file."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys

from wbc_jax.core import processes
from wbc_jax.core.options import field_type, flag_name
from wbc_jax.core.processes import DistributedConfig


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
            if not math.isfinite(value) or value != int(value):
                raise argparse.ArgumentTypeError(f"{flag} expects a whole number, got {text!r}")
            return int(value)
        return value

    return convert


def add_config_arguments(parser: argparse.ArgumentParser, config, skip=()) -> None:
    """One flag (or positional argument) per field of the dataclass ``config`` (its values are the
    defaults; :func:`wbc_jax.core.options.option` declares them)."""
    for field in dataclasses.fields(config):
        if field.name in skip:
            continue
        meta = field.metadata
        flag = flag_name(field)
        default = getattr(config, field.name)
        kind, _, _ = field_type(type(config), field)
        kwargs = {"help": meta.get("help", "")}
        if kind is bool:
            parser.add_argument(flag, action=argparse.BooleanOptionalAction, default=default, dest=field.name, **kwargs)
            continue
        if "choices" in meta:
            kwargs["choices"] = list(meta["choices"])
        if "metavar" in meta:
            kwargs["metavar"] = meta["metavar"]
        if "nargs" in meta:
            kwargs["nargs"] = meta["nargs"]
        # Values given to a parse hook are read as numbers (its own checks name the problem).
        kwargs["type"] = _number(float if "parse" in meta else kind, flag) if kind in (int, float) else kind
        if meta.get("positional"):
            parser.add_argument(field.name, **kwargs)
            continue
        shown = meta["show"](default) if "show" in meta and default is not None else default
        kwargs["help"] += f" (default: {_show(shown)})"
        parser.add_argument(flag, dest=field.name, default=argparse.SUPPRESS, **kwargs)


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


def job_configs() -> dict:
    """Each job's (default config, help) by command name."""
    from wbc_jax.jobs import balance, envelope, info, limit, sweep_config, view
    from wbc_jax.tuning import config as tune_config

    return {
        "info": (info.default_config(), "print the robot model summary as JSON"),
        "balance": (balance.default_config(), "closed-loop balancing run: metrics, trajectory, plots"),
        "push-sweep": (sweep_config.default_config(), "batched push-recovery sweep (the main job)"),
        "envelope": (envelope.default_config(), "recovery envelope by batched bisection over the sweep's magnitudes"),
        "limit": (
            limit.default_config(),
            "the physical limit of push recovery: trajectory optimisation through MJX, "
            "bisection over the impulse, every limit replayed in C MuJoCo",
        ),
        "view": (view.default_config(), "log a run (or one env of a push sweep) to rerun: .rrd or viewer"),
        "tune": (
            tune_config.default_config(),
            "gain tuning in phases: gradient, CMA-ES, random search, held-out evaluation, the race's report",
        ),
        "heldout": (
            tune_config.heldout_default_config(),
            "gain files on the held-out grid, variations, one-foot task and sinusoid",
        ),
    }


def _one_thread_pool() -> None:
    """One robot: XLA's CPU thread pool of one thread (``PJRT_NPROC``, read when JAX starts its
    CPU client; left alone if set, or if JAX has started already, e.g. ``main`` called from a
    notebook). The tick's kernels are small: spread over two cores they cost about 40 % more CPU
    time (BENCHMARKS.md)."""
    from jax._src import xla_bridge

    if not xla_bridge.backends_are_initialized():
        os.environ.setdefault("PJRT_NPROC", "1")


# Commands that also take another config's flags: command -> (config, fields left to the job's own).
# ``tune`` holds out its gain sets with the held-out flags; its tasks and soft-QP weight are the run's.
SHARED_CONFIGS = {"tune": ("heldout", ("out", "tasks", "angular_weight_soft"))}


# Jobs that keep what they finished and go on from it with the same command (the others start over).
RESUMABLE = ("push-sweep", "limit", "tune", "heldout")


def _run_job(command: str, cfg, quiet: bool, shared=None) -> dict:
    """Run a checked config (``shared``: the checked config of :data:`SHARED_CONFIGS`); returns the one
    JSON line's dict."""
    from wbc_jax.sim import runner

    if command == "info":
        from wbc_jax.jobs import info

        return info.run(cfg)
    if command == "view":
        from wbc_jax.jobs import view

        path = view.view(cfg.run_dir, cfg.env, out=cfg.out, spawn=cfg.spawn)
        return {"rrd": None if path is None else str(path), "spawned": bool(cfg.spawn)}
    runner.enable_compilation_cache()
    if command == "balance":
        from wbc_jax.jobs import balance

        return balance.run(cfg, progress=not quiet)
    if command == "push-sweep":
        from wbc_jax.jobs import sweep

        summary = sweep.run_sweep(cfg, progress=not quiet)
        keys = ("n_envs", "survival_rate", "upright_rate", "nan_envs", "qp_infeasible_envs", "backend",
                "physics_steps_per_s", "compile_s", "run_s", "started_s", "n_devices")  # fmt: skip
        return {k: summary[k] for k in keys}
    if command == "envelope":
        from wbc_jax.jobs import envelope

        found = envelope.search(cfg, progress=not quiet)
        return {"rollouts": found["rollouts"], "grid_rollouts": found["grid_rollouts"], "rounds": found["rounds"],
                "backend": found["backend"], "run_s": found["run_s"], "compile_s": found["compile_s"],
                "started_s": found["started_s"],
                "impulse_ns": {str(a): e["impulse_ns"] for a, e in found["envelope"][0].items()}}  # fmt: skip
    if command == "limit":
        from wbc_jax.jobs import limit_rounds

        summary = limit_rounds.run(cfg, progress=not quiet)
        return {"body": cfg.body, "median_fraction_of_lip": summary["median_fraction_of_lip"],
                "targets": summary["targets"], "wall_s": summary["wall_s"], "device": summary["device"],
                "limit_ns": {str(a): r["limit_ns"] for a, r in summary["directions"].items()}}  # fmt: skip
    if command == "heldout":
        from wbc_jax.tuning import heldout

        return heldout.run(cfg, progress=not quiet)
    from wbc_jax.tuning import campaign

    return json.loads(json.dumps(campaign.run(cfg, shared, progress=not quiet), default=str))


def push_sweep_config(flags: list[str]):
    """The checked config that ``wbc-jax push-sweep FLAGS`` would run: for the scripts of
    experiments/ that take the job's flags after ``--``."""
    from wbc_jax.jobs import sweep_config

    cfg = config_from_args(build_parser().parse_args(["push-sweep", *flags]), sweep_config.default_config())
    cfg.check()
    return cfg


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="wbc-jax", description=__doc__)
    dist = parser.add_argument_group(
        "several processes (jax.distributed; one process per host or per GPU, the same command in each)"
    )
    add_config_arguments(dist, DistributedConfig())
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    for command, (config, help_text) in job_configs().items():
        job = sub.add_parser(command, help=help_text)
        add_config_arguments(job, config)
        if command in SHARED_CONFIGS:
            other, skip = SHARED_CONFIGS[command]
            add_config_arguments(job, job_configs()[other][0], skip=skip)
        if command not in ("info", "view"):
            job.add_argument("--quiet", action="store_true", help="no progress bar")
    return parser


def _leave(status: int) -> None:
    """Exit without the interpreter's shutdown: interrupted mid-tick, the C physics' worker threads
    may still run, and finalising under them crashed the process (SIGSEGV in 1 of 4 interrupted sweeps here)."""
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(status)


def main(argv: list[str] | None = None) -> int:
    # Before JAX starts: XLA:CPU logs an error line for each program read back from the persistent
    # compilation cache (its tuning flags "prefer-no-gather/scatter" are not host CPU features), which
    # would bury the commands' output; the programs run correctly.
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")
    args = build_parser().parse_args(argv)
    if args.command == "balance" and not args.distributed:
        _one_thread_pool()  # before JAX starts (the checks below list its devices)
    try:
        dist = config_from_args(args, DistributedConfig())
        dist.check()
        if dist.distributed:  # before JAX starts (the checks below list its devices)
            processes.initialize(dist, f"wbc-jax {args.command}")
        # Every job: the declared ranges and the job's own checks (config.check) before anything
        # loads a program or writes a file.
        cfg = config_from_args(args, job_configs()[args.command][0])
        cfg.check()
        shared = None
        if args.command in SHARED_CONFIGS:
            shared = config_from_args(args, job_configs()[SHARED_CONFIGS[args.command][0]][0])
            shared = dataclasses.replace(shared, tasks=cfg.tasks, angular_weight_soft=cfg.angular_weight_soft)
            shared.check()
        line = _run_job(args.command, cfg, getattr(args, "quiet", False), shared)
    except (ValueError, FileNotFoundError, NotADirectoryError, IsADirectoryError, PermissionError,
            ImportError, MemoryError) as err:  # fmt: skip
        print(f"wbc-jax {args.command}: error: {err}", file=sys.stderr)
        return 2
    except TimeoutError as err:  # a device stalled (wbc_jax/sim/watchdog.py): its thread cannot be stopped
        print(f"wbc-jax {args.command}: error: {err}", file=sys.stderr)
        if argv is None:  # the command line: leave without waiting on the stuck thread at shutdown
            _leave(3)
        return 3
    except OSError as err:  # the file system refused a write (full disk, a name too long, ...)
        where = f" ({err.filename})" if err.filename else ""
        print(f"wbc-jax {args.command}: error: {err.strerror or err}{where}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        again = "resume with the same command" if args.command in RESUMABLE else "run the same command again"
        print(f"wbc-jax {args.command}: interrupted; {again}", file=sys.stderr)
        if argv is None:  # the command line: leave now (every result file is written atomically)
            _leave(130)
        return 130
    print(json.dumps(line, indent=2) if args.command == "info" else json.dumps(line, separators=(",", ":")))
    return 0


if __name__ == "__main__":
    sys.exit(main())
