"""A bound on each device's share of a chunk, and a timeline of where a chunk's time went.

    watch = Watchdog(chunk=3, bound_s=stall_bound(None, finished_run_s))
    results = run_watched([(label, work), ...], watch, "run")   # DeviceStalled past the bound

Each device's work runs in a daemon thread of its own (an XLA:GPU program with while loops runs its
loop control on the thread that launched it, :class:`wbc_jax.sim.runner.PerDevice`); the caller
waits at most the bound for all of them. A device that does not finish in time raises
:class:`DeviceStalled`, one line naming the chunk and the device, instead of a run that hangs (4
GPUs of MJX-Warp sat at 2-9 % busy for minutes, issue 45). The stuck thread cannot be stopped;
being a daemon it does not keep the process alive, and the CLI leaves without the interpreter's
shutdown (``wbc_jax/cli.py``). Each thread's waits (its start, the dispatch, the device's run, the
transfer to the host) go into ``Watchdog.rows``: the sweep writes them to ``timeline.json``.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import jax

# Default bound of a chunk's run: this many times the slowest chunk finished so far in the process,
# at least MIN_STALL_S; a run's first chunk (nothing finished yet) FIRST_CHUNK_STALL_S.
STALL_FACTOR = 10.0
MIN_STALL_S = 60.0
FIRST_CHUNK_STALL_S = 1800.0
# XLA's compile of a chunk's program (and C MuJoCo's first chunk, which compiles inside its run) is
# given at least this long: a cold Warp compile on a GPU takes minutes.
COMPILE_STALL_S = 1800.0
MAX_STALL_S = 86_400.0  # a bound of more than a day is a typo
PHASES = ("compile", "run")


class DeviceStalled(TimeoutError):
    """A device's share of a chunk did not finish within the watchdog's bound."""


def stall_bound(timeout_s: float | None, finished_run_s: Sequence[float]) -> float:
    """Seconds a chunk's run may take on a device: ``timeout_s`` if given (``--stall-timeout-s``),
    else max(MIN_STALL_S, STALL_FACTOR x the slowest finished chunk), FIRST_CHUNK_STALL_S before
    any chunk finished."""
    if timeout_s is not None:
        return float(timeout_s)
    if not finished_run_s:
        return FIRST_CHUNK_STALL_S
    return max(MIN_STALL_S, STALL_FACTOR * max(finished_run_s))


def device_label(device) -> str:
    """A device as the error and the timeline name it: ``gpu:2``, ``cpu:0``."""
    return f"{device.platform}:{device.id}"


@dataclasses.dataclass
class Watchdog:
    """The bound and the timeline of one chunk's work on its devices.

    chunk: the chunk's index (named by the error). bound_s: seconds its run may take
    (:func:`stall_bound`). warm: a chunk of this run finished in this process (the programs are
    compiled: C MuJoCo's run then gets ``bound_s`` alone). simulate_stall: the test hook (chunk,
    device index): that device's share of that chunk's run blocks until the watchdog gives up
    (``--simulate-stall``). rows: one dict per device and phase, seconds from the phase's start."""

    chunk: int
    bound_s: float
    warm: bool = False
    simulate_stall: tuple[int, int] | None = None
    rows: list = dataclasses.field(default_factory=list)

    def bound(self, phase: str, compiles: bool = False) -> float:
        """Seconds ``phase`` may take; ``compiles``: the run compiles its program too."""
        return max(self.bound_s, COMPILE_STALL_S) if phase == "compile" or compiles else self.bound_s

    def blocks(self, index: int, phase: str) -> bool:
        return phase == "run" and self.simulate_stall == (self.chunk, index)


def run_watched(
    tasks: Sequence[tuple[str, Callable[[dict], Any]]], watch: Watchdog | None, phase: str, *, compiles: bool = False
) -> list:
    """Run each ``(device label, work)`` in a daemon thread of its own and return the results in
    order. ``work(times)`` may record its own seconds in ``times`` (``dispatch_s``, ``wait_s``,
    ``transfer_s``, ``compile_s``). With a ``watch``, a device not done within its bound raises
    :class:`DeviceStalled` naming the chunk and the device(s); every thread's times are appended to
    ``watch.rows``. Without one (and one task) the work runs in the caller's thread. JAX's
    thread-local settings (x64, the default device) are the caller's in every thread."""
    if watch is None and len(tasks) == 1:
        return [tasks[0][1]({})]
    if phase not in PHASES:
        raise ValueError(f"phase must be one of {list(PHASES)}, got {phase!r}")
    started = time.perf_counter()
    x64, default_device = jax.config.jax_enable_x64, jax.config.jax_default_device
    results: list = [None] * len(tasks)
    errors: list = [None] * len(tasks)
    times: list = [{} for _ in tasks]
    done = [threading.Event() for _ in tasks]
    gave_up = threading.Event()

    def body(index: int, work: Callable[[dict], Any]) -> None:
        own = times[index]
        own["thread_start_s"] = time.perf_counter() - started  # the Python thread's wait to start
        try:
            if watch is not None and watch.blocks(index, phase):
                gave_up.wait()  # the simulated stall: released (doing nothing) once the watchdog gave up
                return
            with jax.enable_x64(x64), jax.default_device(default_device):
                results[index] = work(own)
        except BaseException as err:  # handed to the caller
            errors[index] = err
        finally:
            own["end_s"] = time.perf_counter() - started
            done[index].set()

    for index, (label, work) in enumerate(tasks):
        threading.Thread(target=body, args=(index, work), name=f"wbc-{phase}-{label}", daemon=True).start()
    bound = None if watch is None else watch.bound(phase, compiles)
    deadline = None if bound is None else started + bound
    for event in done:
        event.wait(None if deadline is None else max(0.0, deadline - time.perf_counter()))
    stalled = [label for (label, _), event in zip(tasks, done, strict=True) if not event.is_set()]
    if watch is not None:
        for (label, _), own in zip(tasks, times, strict=True):
            watch.rows.append(
                {"chunk": watch.chunk, "phase": phase, "device": label, **dict(own), "finished": "end_s" in own}
            )
    if stalled:
        gave_up.set()
        finished = len(tasks) - len(stalled)
        raise DeviceStalled(
            f"chunk {watch.chunk}: device {', '.join(stalled)} did not finish its {phase} within {bound:g} s "
            f"({finished} of {len(tasks)} device(s) did; bound: --stall-timeout-s); the chunks finished before are "
            f"kept: rerun the same command to resume"
        )
    for err in errors:
        if err is not None:
            raise err
    return results


TIMED = ("compile_s", "thread_start_s", "dispatch_s", "wait_s", "transfer_s")


def timeline_rows(watch: Watchdog, host_s: float, wall_s: float) -> list[dict]:
    """One row per device of the chunk: its seconds compiling, waiting for its thread to start,
    dispatching, waiting for its run and copying to the host (summed over the chunk's phases and
    calls), the chunk's host work outside the devices' threads (``host_s``: building the chunk's
    scenarios, its table, its part file) and its wall time. A device's row sums to at most
    ``wall_s`` (the phases run one after the other; the devices side by side)."""
    rows: dict = {}
    for r in watch.rows:
        row = rows.setdefault(
            r["device"], {"chunk": watch.chunk, "device": r["device"], **dict.fromkeys(TIMED, 0.0), "finished": True}
        )
        for key in TIMED:
            row[key] += float(r.get(key, 0.0))
        row["finished"] = row["finished"] and r["finished"]
    return [
        {
            **{k: round(v, 4) if isinstance(v, float) else v for k, v in row.items()},
            "host_s": round(host_s, 4),
            "wall_s": round(wall_s, 4),
        }
        for row in rows.values()
    ]
