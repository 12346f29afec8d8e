"""A worker process of :func:`baseline_cpu.workers.run_parallel`, executed by ``runpy.run_path`` in a
``spawn`` child (never imported): it puts benchmarks/ on the path, so that ``baseline_cpu`` imports
whether or not the parent loaded it from its file, and runs the job it was given. The child imports
only numpy, mujoco, quadprog and ``wbc_jax/core/constants.py`` (by file path), never JAX."""

import pathlib
import sys

BENCHMARKS = str(pathlib.Path(__file__).resolve().parent.parent)
if BENCHMARKS not in sys.path:
    sys.path.insert(0, BENCHMARKS)

from baseline_cpu.workers import WORKER_RUN_NAME, worker_main  # noqa: E402

if __name__ == WORKER_RUN_NAME:
    worker_main(_WORKER_JOB, _WORKER_CONN, _WORKER_START)  # noqa: F821  (runpy's init_globals)
