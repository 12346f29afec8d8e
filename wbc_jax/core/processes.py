"""Several processes joined by ``jax.distributed``: the flags, their checks and a bounded wait.

    cfg = DistributedConfig(distributed=True, coordinator="host0:4321", num_processes=2, process_id=1)
    cfg.check()                      # one line naming the flag, before JAX starts
    initialize(cfg, "wbc-jax push-sweep")

JAX's own wait for the coordinator ends (after ``initialization_timeout``, 300 s by default) by
aborting the process with a C++ stack trace. :func:`initialize` waits at most
``--initialization-timeout`` instead and then exits with one line that names the coordinator: a
watchdog thread runs while JAX waits (JAX releases the interpreter lock there), and JAX's own
limit is set past it so that the watchdog always speaks first.
"""

from __future__ import annotations

import dataclasses
import math
import os
import sys
import threading

from wbc_jax.core.options import check_options, option

# JAX's own limit is this much past ours: its abort must never come first.
_JAX_TIMEOUT_MARGIN_S = 30
# The exit status of a wait that timed out (as the command line's other errors).
TIMEOUT_EXIT_CODE = 2


@dataclasses.dataclass(frozen=True)
class DistributedConfig:
    """The command line's flags of several processes (before the job's name)."""

    distributed: bool = option(
        False,
        "join the processes with jax.distributed.initialize() before the job (under "
        "SLURM or Open MPI the addresses and ranks are read from the environment)",
    )
    coordinator: str | None = option(None, "process 0's address (with --distributed)", metavar="HOST:PORT")
    num_processes: int | None = option(None, "processes in all (with --distributed)", ge=1)
    process_id: int | None = option(None, "this process's rank, 0..N-1 (with --distributed)", ge=0)
    initialization_timeout: float = option(
        120.0,
        "seconds each process waits for all of them to join the coordinator before it exits with one "
        "line naming it (with --distributed)",
        gt=0,
        le=3600,
        unit="s",
    )

    def check(self) -> None:
        """Raise ValueError (one line naming the flag) for flags that cannot join processes."""
        check_options(self)
        given = {
            "--coordinator": self.coordinator,
            "--num-processes": self.num_processes,
            "--process-id": self.process_id,
        }
        named = [flag for flag, value in given.items() if value is not None]
        if named and not self.distributed:
            verb = "needs" if len(named) == 1 else "need"
            raise ValueError(
                f"{' '.join(named)} {verb} --distributed (they say how processes join; without it the "
                "job runs in this process alone)"
            )
        if named and len(named) < len(given):
            raise ValueError(
                "--coordinator, --num-processes and --process-id go together (or none: from SLURM/MPI); "
                f"got only {' '.join(named)}"
            )
        if self.num_processes is not None and self.process_id >= self.num_processes:
            raise ValueError(f"--process-id must be in 0..{self.num_processes - 1}, got {self.process_id}")
        if self.coordinator is not None:
            host, _, port = self.coordinator.rpartition(":")
            if not host or not port.isdigit() or not 1 <= int(port) <= 65535:
                raise ValueError(f"--coordinator must be HOST:PORT with a port in 1..65535, got {self.coordinator!r}")

    def where(self) -> str:
        """The coordinator, in words."""
        return self.coordinator or "the address SLURM/Open MPI gives"


def initialize(cfg: DistributedConfig, prog: str) -> None:
    """``jax.distributed.initialize`` from a checked config: after it every process sees the global
    device list. If the processes have not all joined within ``cfg.initialization_timeout``, print
    one line (``{prog}: error: ...``, naming the coordinator) and exit with
    :data:`TIMEOUT_EXIT_CODE`."""
    import jax

    if os.environ.get("JAX_PLATFORMS", "").startswith("cpu"):
        # CPU devices of several processes talk through Gloo (no NCCL there).
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
    joined = threading.Event()
    rank = "" if cfg.process_id is None else f"process {cfg.process_id} of {cfg.num_processes}: "

    def give_up() -> None:
        if joined.wait(cfg.initialization_timeout):
            return
        print(
            f"{prog}: error: {rank}the processes did not all join the coordinator at {cfg.where()} within "
            f"{cfg.initialization_timeout:g} s (--initialization-timeout); start process 0 and every other "
            "with the same --coordinator and --num-processes",
            file=sys.stderr,
            flush=True,
        )
        os._exit(TIMEOUT_EXIT_CODE)  # JAX's wait cannot be interrupted from Python

    threading.Thread(target=give_up, name="distributed-timeout", daemon=True).start()
    given = {"coordinator_address": cfg.coordinator, "num_processes": cfg.num_processes, "process_id": cfg.process_id}
    jax.distributed.initialize(
        **{k: v for k, v in given.items() if v is not None},
        initialization_timeout=math.ceil(cfg.initialization_timeout) + _JAX_TIMEOUT_MARGIN_S,
    )
    joined.set()
