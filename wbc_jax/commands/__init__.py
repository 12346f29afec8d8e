"""The ``wbc-jax`` commands: one module per command, named after it, each with one shape (a
:class:`Command`: its config, whose fields are the command's flags, and ``run(cfg, progress) ->
the one JSON line's dict``), registered once in :func:`registry`; :mod:`wbc_jax.cli` loops over it."""

from __future__ import annotations

import dataclasses
import functools
import importlib
from collections.abc import Callable
from typing import Any

# The command modules, in the order of ``wbc-jax --help``.
MODULES = ("info", "balance", "push_sweep", "envelope", "limit", "view", "tune", "heldout")


@dataclasses.dataclass(frozen=True)
class Command:
    """One command of the command line.

    Attributes:
      name: the command (``push-sweep``; its module is ``push_sweep``).
      help: one line for ``wbc-jax --help``.
      default_config: () -> the frozen dataclass whose fields are the command's flags
        (:mod:`wbc_jax.core.options`); its ``check()`` names a bad flag in one line.
      run: (cfg, progress: bool) -> dict: runs a config (built by ``combine``) and returns the dict of
        the one JSON line the command prints. The job checks its config where it starts, once,
        before it loads a program or writes a file.
      resumable: the job keeps what it finished and goes on from it with the same command.
      compiles: the job compiles programs: the persistent compilation cache is on, and ``--quiet``
        hides its progress bar.
      one_robot: the job simulates one robot: XLA's CPU thread pool of one thread (``cli``).
      indent: the JSON line's indent (None: one line).
      shared: other configs whose flags the command also takes: (() -> config, fields left to the
        command's own config).
      combine: (config, *shared configs) -> the config ``run`` takes (default: the config alone).
    """

    name: str
    help: str
    default_config: Callable[[], Any]
    run: Callable[[Any, bool], dict]
    resumable: bool = False
    compiles: bool = True
    one_robot: bool = False
    indent: int | None = None
    shared: tuple[tuple[Callable[[], Any], tuple[str, ...]], ...] = ()
    combine: Callable[..., Any] | None = None


@functools.cache
def registry() -> dict[str, Command]:
    """Every command by name (each module's ``COMMAND``), in the order of :data:`MODULES`."""
    commands = {}
    for module in MODULES:
        command = importlib.import_module(f"{__name__}.{module}").COMMAND
        commands[command.name] = command
    return commands
