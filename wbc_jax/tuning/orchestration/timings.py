"""``timings.json`` of a tune run: the wall seconds of each phase, kept across re-runs of the folder.

A phase's time is that of the work that made its result: measured by the invocation that finished it,
plus the time of earlier invocations stopped inside it (an error, Ctrl-C; kept under ``interrupted_s``
until the phase finishes, an invocation killed outright leaves none). A re-run of a finished phase
measures nothing new and its time stays as it was: a phase with a result file takes its result from
that file when the file is still the run's own (its sha256 in the run's manifest), else computes it
again and records that computation's time; a phase without one (train, the searches, the hybrid)
resumes from its checkpoints with nothing left to do."""

from __future__ import annotations

import json
import pathlib
import time
from collections.abc import Callable

from wbc_jax.core import io, loader
from wbc_jax.jobs import runs

INTERRUPTED = "interrupted_s"  # {phase: seconds} of invocations stopped inside a phase not yet finished


class PhaseTimings:
    """Runs the phases of one tune invocation and keeps ``out/timings.json`` (module docstring)."""

    def __init__(self, out: pathlib.Path, *, progress: bool = True):
        self.path = pathlib.Path(out) / "timings.json"
        self.progress = progress
        self.timings: dict = loader.read_json(self.path, "tune timings") if self.path.exists() else {}
        if not isinstance(self.timings, dict):
            raise ValueError(f"{self.path} is not a JSON object of phase timings; remove it or use another --out")

    def run(self, name: str, fn: Callable[[], object], result_file: pathlib.Path | None = None):
        """``fn()``, the phase ``name``, timed; ``result_file``: the JSON file ``fn`` writes its result
        to, read back instead of calling ``fn`` when the phase finished earlier and the file is its own."""
        if name in self.timings:
            if result_file is None:
                result = fn()  # resumes with nothing left to do: its time stays the finishing run's
                self._say(name, earlier=True)
                return result
            if runs.output_changed(result_file) is None:
                self._say(name, earlier=True)
                return loader.read_json(result_file, f"the {name} phase's result")
            del self.timings[name]  # its file was changed or removed: computed again, and timed again
        interrupted = self.timings.setdefault(INTERRUPTED, {})
        t0 = time.perf_counter()
        try:
            result = fn()
        except BaseException:
            interrupted[name] = round(interrupted.get(name, 0.0) + time.perf_counter() - t0, 1)
            io.atomic_write_json(self.path, self.timings)
            raise
        self.timings[name] = round(interrupted.pop(name, 0.0) + time.perf_counter() - t0, 1)
        if not interrupted:
            del self.timings[INTERRUPTED]
        if result_file is not None:
            runs.record_output(result_file)
        io.atomic_write_json(self.path, self.timings)
        self._say(name, earlier=False)
        return result

    def _say(self, name: str, *, earlier: bool) -> None:
        if self.progress:
            line = {"phase": name, "s": self.timings[name], **({"finished_earlier": True} if earlier else {})}
            print(json.dumps(line), flush=True)
