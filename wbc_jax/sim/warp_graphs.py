"""The CUDA graphs MJX-Warp's foreign calls keep: their bound, and how many are held (issue 45).

    warp_graphs.bound(0)       # after tracing, before the run: keep every graph captured
    warp_graphs.bound(None, 4) # the default on 4 GPUs: 32 graphs per GPU
    warp_graphs.held()         # {callable name: graphs held}, after the run

MJX-Warp's step enters XLA as a Warp ``jax_callable`` in graph mode WARP (mujoco-mjx 3.17.0,
``mujoco/mjx/warp/ffi.py:111``, ``_src/io.py:598-602``). Each time XLA reaches the call, Warp's
callback (Python, under the interpreter lock and Warp's process-wide ``_FFI_CALLBACK_LOCK``,
``warp/_src/jax/ffi.py:47,896``) replays the graph it captured for the same device, call site and
buffer addresses (``ffi.py:963-980``), or captures a new one: it wraps the step's 559 array
arguments as Warp arrays, runs the step's Python (every kernel launch) under capture and
instantiates the graph (``ffi.py:1065-1091``). The graphs of one callable sit in ONE
least-recently-used cache shared by all of the process's devices, 32 graphs by default
(``JAX_CALLABLE_DEFAULT_GRAPH_CACHE_MAX``, ``ffi.py:52,1755``), and each ``wp.jax_callable`` call
for it sets that bound again (``ffi.py:1878-1880``; mujoco-mjx makes that call when it first traces
a call structure, ``mujoco/mjx/warp/ffi.py:161-206``): which is why :func:`bound` is applied after
the programs are traced. mujoco-mjx passes no bound of its own, so this reaches Warp's registry
(``warp._src.jax.ffi._FFI_CALLABLE_REGISTRY``), read and set through ``FfiCallable.graph_cache_max``
/ ``graph_cache_size``; a Warp without them is refused in one line.
"""

from __future__ import annotations

import sys

# A bound on graphs per callable: 0 keeps every graph captured; more than this is a typo.
MAX_GRAPH_CACHE = 100_000
# Warp's own bound (JAX_CALLABLE_DEFAULT_GRAPH_CACHE_MAX), which it shares among all devices. One GPU's
# sweep holds 20 graphs; four held 50 unbounded, so under 32 every call missed and captured again under
# Warp's process-wide lock: 4 GPUs ran 6x slower than one (BENCHMARKS.md, "Why 4 GPUs of Warp were
# slower"). The default bound is this many per device of the run.
WARP_GRAPH_CACHE = 32
# Who captures the step's CUDA graphs (Warp's JaxCallableGraphMode): Warp, per device, call site and
# buffer addresses (MJX's default on a GPU); XLA, as part of its command buffers (the callback runs
# only while XLA captures); nobody (every call launches each kernel from Python). The staged modes
# keep one capture per call site, which the devices of a process share (PerDevice traces once):
# unsafe on several GPUs (google-deepmind/mujoco#3191), so not offered.
GRAPH_MODES = ("warp", "jax", "none")


def _callables() -> list:
    """Warp's registered ``jax_callable`` objects; [] when Warp was never imported (no MJX-Warp run)."""
    if "warp" not in sys.modules:
        return []
    from warp._src.jax import ffi  # only where Warp is already loaded

    registry = getattr(ffi, "_FFI_CALLABLE_REGISTRY", None)
    callables = list(registry.values()) if isinstance(registry, dict) else None
    if callables is None or not all(hasattr(c, "graph_cache_max") for c in callables):
        version = getattr(sys.modules["warp"], "__version__", "?")
        raise RuntimeError(
            f"warp-lang {version} keeps its jax_callable graphs elsewhere than warp-lang 1.18 "
            "(_FFI_CALLABLE_REGISTRY, graph_cache_max); --warp-graph-cache needs 1.18"
        )
    return callables


def check(limit: int | None, mode: str = "warp") -> None:
    """Refuse, in one line, a bound that is not None nor a whole number in [0, MAX_GRAPH_CACHE], or a
    graph mode not in :data:`GRAPH_MODES`."""
    if mode not in GRAPH_MODES:
        raise ValueError(f"--warp-graph-mode must be one of {list(GRAPH_MODES)}, got {mode!r}")
    if limit is not None and (
        isinstance(limit, bool) or not isinstance(limit, int) or not 0 <= limit <= MAX_GRAPH_CACHE
    ):
        raise ValueError(
            f"--warp-graph-cache must be a whole number in [0, {MAX_GRAPH_CACHE:,}] (0: no bound), got {limit!r}"
        )


def default_bound(devices: int) -> int | None:
    """The bound when none is asked for: Warp's own on one device (None: left alone), else
    :data:`WARP_GRAPH_CACHE` graphs per device, as if each device had Warp's cache to itself."""
    return None if devices <= 1 else WARP_GRAPH_CACHE * devices


def bound(limit: int | None, devices: int = 1) -> int:
    """Set the graph cache of every registered Warp callable: ``limit`` graphs, 0 for no bound,
    None for :func:`default_bound` of ``devices`` (the devices the run's programs run on). Returns
    the callables set."""
    check(limit)
    if limit is None:
        limit = default_bound(devices)
    if limit is None:
        return 0
    callables = _callables()
    for c in callables:
        c.graph_cache_max = None if limit == 0 else limit
    return len(callables)


def held() -> dict[str, dict]:
    """Per registered Warp callable: the graphs it holds and its bound (None: unbounded)."""
    return {c.name: {"graphs": int(c.graph_cache_size), "bound": c.graph_cache_max} for c in _callables()}
