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

from wbc_jax.commands import registry
from wbc_jax.core import processes
from wbc_jax.core.options import field_type, flag_name, is_nested
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
        if is_nested(field):  # a shared group of flags: its fields are this command's flags
            add_config_arguments(parser, getattr(config, field.name), skip)
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
        if is_nested(field):
            changes[field.name] = config_from_args(args, getattr(config, field.name))
            continue
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
    """Each command's (default config, help) by name (:func:`wbc_jax.commands.registry`)."""
    return {name: (command.default_config(), command.help) for name, command in registry().items()}


def _one_thread_pool() -> None:
    """One robot: XLA's CPU thread pool of one thread (``PJRT_NPROC``, read when JAX starts its
    CPU client; left alone if set, or if JAX has started already, e.g. ``main`` called from a
    notebook). The tick's kernels are small: spread over two cores the 20 s sinusoid's loop took
    0.84 s against 0.76 s on one thread (BENCHMARKS.md)."""
    from jax._src import xla_bridge

    if not xla_bridge.backends_are_initialized():
        os.environ.setdefault("PJRT_NPROC", "1")


def push_sweep_config(flags: list[str]):
    """The checked config that ``wbc-jax push-sweep FLAGS`` would run: for the scripts of
    experiments/ that take the job's flags after ``--``."""
    from wbc_jax.commands import push_sweep

    command = push_sweep.COMMAND
    cfg = config_from_args(build_parser().parse_args([command.name, *flags]), command.default_config())
    cfg.check()
    return cfg


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="wbc-jax", description=__doc__)
    dist = parser.add_argument_group(
        "several processes (jax.distributed; one process per host or per GPU, the same command in each)"
    )
    add_config_arguments(dist, DistributedConfig())
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    for name, command in registry().items():
        job = sub.add_parser(name, help=command.help)
        add_config_arguments(job, command.default_config())
        for shared, skip in command.shared:
            add_config_arguments(job, shared(), skip=skip)
        if command.compiles:
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
    command = registry()[args.command]
    if command.one_robot and not args.distributed:
        _one_thread_pool()  # before JAX starts (the checks below list its devices)
    try:
        dist = config_from_args(args, DistributedConfig())
        dist.check()
        if dist.distributed:  # before JAX starts (the checks below list its devices)
            processes.initialize(dist, f"wbc-jax {args.command}")
        # Every job checks its config (the declared ranges and the job's own checks) once, where it
        # starts, before anything loads a program or writes a file.
        configs = [config_from_args(args, command.default_config())]
        configs += [config_from_args(args, shared()) for shared, _ in command.shared]
        cfg = configs[0] if command.combine is None else command.combine(*configs)
        if command.compiles:
            from wbc_jax.sim import runner

            runner.enable_compilation_cache()
        line = command.run(cfg, not getattr(args, "quiet", False))
    except (
        ValueError,
        FileNotFoundError,
        NotADirectoryError,
        IsADirectoryError,
        PermissionError,
        ImportError,
        MemoryError,
    ) as err:
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
        again = "resume with the same command" if command.resumable else "run the same command again"
        print(f"wbc-jax {args.command}: interrupted; {again}", file=sys.stderr)
        if argv is None:  # the command line: leave now (every result file is written atomically)
            _leave(130)
        return 130
    print(json.dumps(line, indent=command.indent) if command.indent else json.dumps(line, separators=(",", ":")))
    return 0


if __name__ == "__main__":
    sys.exit(main())
