"""The one chunk runner of batched jobs (the push sweep, the held-out evaluation of gain tuning).

A batch of scenarios runs in chunks of one compiled shape; each chunk's table (``env``, the
caller's columns, the metrics of :func:`wbc_jax.sim.metrics.summarize`, ``ticks_simulated``) is
written atomically to a Parquet part whose sha256 goes into its run's manifest
(:func:`wbc_jax.jobs.runs.record_output`). A part that is the run's own and holds exactly its
chunk's envs is read back instead of run again (a resumed run); any other (changed, copied in,
unreadable, of another range) is recomputed and named once on stderr.
"""

from __future__ import annotations

import dataclasses
import pathlib
import sys
import time
from collections.abc import Callable

import jax
import numpy as np

from wbc_jax.core import io
from wbc_jax.jobs import runs
from wbc_jax.sim import metrics as metrics_lib
from wbc_jax.sim import runner, scenario, watchdog
from wbc_jax.sim.state import Scenario


def part_name(c: int, tag: str = "") -> str:
    """The file of chunk ``c``; ``tag`` (a hash of what the parts depend on) in the name keeps parts
    of other settings apart in one folder."""
    return f"part-{c:05d}{f'-{tag}' if tag else ''}.parquet"


def read_part(path: pathlib.Path, lo: int, hi: int):
    """A part file if it is the run's own (its sha256 the one the manifest recorded when the run
    wrote it) and holds exactly envs lo..hi-1, else None (missing, changed, copied in, unreadable
    or wrong: recomputed)."""
    import pandas as pd

    if not path.exists() or runs.output_changed(path) is not None:
        return None
    try:
        table = pd.read_parquet(path)
    except Exception:
        return None
    if "env" not in table or not np.array_equal(table["env"].to_numpy(), np.arange(lo, hi)):
        return None
    return table


def agreed(flags: list[bool]) -> list[bool]:
    """Process 0's list of flags on every process (the list as is in a one-process run)."""
    if jax.process_count() == 1:
        return list(flags)
    from jax.experimental import multihost_utils

    return [bool(f) for f in multihost_utils.broadcast_one_to_all(np.asarray(flags, bool))]


@dataclasses.dataclass
class Chunks:
    """What :func:`run_chunks` did.

    Attributes:
      tables: each chunk's table in order (a chunk only process 0 can read is left out).
      compile_s, run_s: seconds of this process's simulation (0 when every part was on disk).
      done_envs: envs simulated now (the others were read back).
      started: when the first chunk started simulating (``time.perf_counter``; None: none did).
      replaced: the part files found that were not the run's own (recomputed).
      todo: per chunk, whether it was run (False: read back).
    """

    tables: list
    compile_s: float
    run_s: float
    done_envs: int
    started: float | None
    replaced: list[str]
    todo: list[bool]


def run_chunks(
    st: scenario.Setup,
    scen: Scenario,
    columns: dict,
    parts: pathlib.Path,
    *,
    batch: int,
    push_end: float,
    tag: str = "",
    queue: int = 1,
    watch: Callable[[int, list], watchdog.Watchdog] | None = None,
    timeline: Callable[[watchdog.Watchdog | None, float, float, list], None] | None = None,
    writer: bool = True,
    progress: bool = True,
    label: str = "run",
) -> Chunks:
    """Run the scenarios ``scen`` (B,) in chunks of ``batch`` into Parquet parts in ``parts``.

    Args:
      columns: {name: (B,)} written beside the metrics of each env.
      push_end: the end of the push (s), for the metrics' recovery.
      tag: in each part's name (:func:`part_name`).
      queue: :func:`wbc_jax.sim.runner.run`'s queue.
      watch: (chunk, the run seconds of the chunks finished) -> the chunk's watchdog (None: none).
      timeline: (watchdog, host seconds, wall seconds, todo) -> None: called by the writer after each
        chunk run and at a stall (then the stall is raised).
      writer: this process writes the parts (process 0 of a multi-process run).
      label: the job, in the progress bar and the stderr line on recomputed parts (with the folder
        above ``parts``, the job's ``--out``).
    """
    import pandas as pd
    from tqdm.auto import tqdm

    size = int(np.asarray(scen.friction).shape[0])
    bounds = [(lo, min(lo + batch, size)) for lo in range(0, size, batch)]
    stored = [read_part(parts / part_name(c, tag), lo, hi) for c, (lo, hi) in enumerate(bounds)]
    replaced = [part_name(c, tag) for c, t in enumerate(stored) if t is None and (parts / part_name(c, tag)).exists()]
    if replaced and writer:
        print(
            f"{label} --out {parts.parent}: {len(replaced)} part file(s) not the run's own (changed or copied in), "
            f"recomputed: "
            f"{replaced[:3]}",
            file=sys.stderr,
        )
    # Every process must run the same chunks (each run is a collective): process 0's parts decide.
    todo = agreed([t is None for t in stored])
    done = Chunks([], 0.0, 0.0, 0, None, replaced, todo)
    finished_run_s: list[float] = []  # each chunk's run, for the watchdog's default bound
    with tqdm(total=size, unit="env", disable=not progress, desc=f"{label} ({st.backend})") as bar:
        for c, (lo, hi) in enumerate(bounds):
            table = stored[c]
            if todo[c]:
                chunk_start = time.perf_counter()
                chunk = jax.tree_util.tree_map(lambda x, lo=lo, hi=hi: np.asarray(x)[lo:hi], scen)
                chunk_watch = None if watch is None else watch(c, finished_run_s)
                run_start = time.perf_counter()
                try:
                    result = runner.run(st, chunk, batch_size=batch, queue=queue, watch=chunk_watch)
                except watchdog.DeviceStalled:
                    if writer and timeline is not None:  # where the time went up to the stall
                        now = time.perf_counter()
                        timeline(chunk_watch, run_start - chunk_start, now - chunk_start, todo)
                    raise
                run_end = time.perf_counter()
                finished_run_s.append(result.run_s)
                done.compile_s += result.compile_s
                done.started = done.started or result.started
                done.run_s += result.run_s
                done.done_envs += hi - lo
                metrics = metrics_lib.summarize(result.metrics, push_end)
                table = pd.DataFrame(
                    {
                        "env": np.arange(lo, hi),
                        **{k: np.asarray(v)[lo:hi] for k, v in columns.items()},
                        **metrics,
                        "ticks_simulated": np.asarray(result.metrics.ticks),
                    }
                )
                if writer:
                    part = parts / part_name(c, tag)
                    io.atomic_write_parquet(part, table)
                    runs.record_output(part)
                    if timeline is not None:
                        now = time.perf_counter()
                        timeline(chunk_watch, (run_start - chunk_start) + (now - run_end), now - chunk_start, todo)
            if table is not None:  # None: a part only process 0 can read (no shared file system)
                done.tables.append(table)
            bar.update(hi - lo)
    return done
