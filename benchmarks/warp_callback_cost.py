"""The host work of one MJX-Warp step's callback, without a GPU (issue 45, BENCHMARKS.md "Why 4 GPUs of Warp were
slower").

    python benchmarks/warp_callback_cost.py --out results/scaling/warp_callback_cost_cpu.json

Each time XLA reaches MJX-Warp's step, Warp's callback runs under its process-wide lock
(warp/_src/jax/ffi.py:896). Its two Python paths are timed here on this host, on warp-lang's own
structures, for the step's array arguments (counted from mujoco-mjx's ``_step_shim``):

* ``replay_key_s``: what every call pays before launching a cached graph: each buffer's address read
  through ctypes and the tuple hashed (ffi.py:963-967);
* ``wrap_buffers_s``: what a capture pays first: every buffer wrapped as a Warp array
  (``_build_arg_list``, ffi.py:857-873), before the step's launches under capture and the graph's
  instantiation, which need a GPU and are not timed.

Writes the seconds per call (median of ``--repeats``) with provenance to ``--out``.
"""

from __future__ import annotations

import argparse
import ctypes
import inspect
import pathlib
import statistics
import sys
import time

from wbc_jax.core import io, provenance


def step_array_arguments() -> int:
    """The plain array arguments of MJX-Warp's step callback (mujoco-mjx's ``_step_shim``, as Warp
    classifies them; its few variadic tuples of arrays, model-dependent, are left out: a lower bound)."""
    import warp as wp
    from mujoco.mjx.warp import forward
    from warp._src.types import matches_array_class

    params = inspect.signature(forward._step_shim).parameters.values()
    n = sum(matches_array_class(p.annotation, wp.array) for p in params)
    if n == 0:
        raise SystemExit("warp_callback_cost.py: error: found no array argument in mujoco-mjx's _step_shim")
    return n


def replay_key_seconds(n: int, repeats: int) -> float:
    """Median seconds to read ``n`` buffer addresses from an XLA call frame and hash them."""
    from warp._src.jax.xla_ffi import XLA_FFI_Buffer

    buffers = (XLA_FFI_Buffer * n)()
    pointers = (ctypes.POINTER(XLA_FFI_Buffer) * n)(*[ctypes.pointer(buffers[i]) for i in range(n)])
    inputs = ctypes.cast(pointers, ctypes.POINTER(ctypes.POINTER(XLA_FFI_Buffer)))
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        hash((0, 0, *[inputs[i].contents.data for i in range(n)]))
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def wrap_seconds(n: int, repeats: int) -> float:
    """Median seconds to wrap ``n`` host buffers as Warp arrays (on Warp's CPU device)."""
    import numpy as np
    import warp as wp

    host = np.zeros(1024, np.float32)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        [wp.array(ptr=host.ctypes.data, dtype=wp.float32, shape=(1024,), device="cpu") for _ in range(n)]
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", required=True, help="the result's JSON file")
    p.add_argument("--repeats", type=int, default=200, choices=range(10, 100_001), metavar="10..100000")
    args = p.parse_args(argv)
    try:
        import warp as wp
    except ImportError:
        raise SystemExit(
            "warp_callback_cost.py: error: needs warp-lang (pip install -e '.[cuda]', or the wheel's contents on "
            "PYTHONPATH)"
        ) from None
    wp.config.quiet = True
    wp.init()
    n = step_array_arguments()
    result = {
        "step_array_arguments": n,
        "replay_key_s": replay_key_seconds(n, args.repeats),
        "wrap_buffers_s": wrap_seconds(n, max(10, args.repeats // 10)),
        "warp": wp.__version__,
        "provenance": provenance.record(argv=["benchmarks/warp_callback_cost.py", *sys.argv[1:]]),
    }
    io.atomic_write_json(pathlib.Path(args.out), result)
    print(result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
