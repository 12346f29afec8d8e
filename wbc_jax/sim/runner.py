"""Batched runs of a set-up on any physics engine, sharded over a device mesh along the batch axis.

    run(setup, scenarios) -> Run          metrics (and records) of a Scenario batch

:func:`run` dispatches on the physics backend (:mod:`wbc_jax.sim.physics`): MJX backends run the
closed loop in XLA (jit + vmap, sharded over a device mesh along the batch axis,
:mod:`wbc_jax.sim.mjx_loop`), C MuJoCo runs the jitted controller and the threaded C physics tick
by tick (:mod:`wbc_jax.sim.host_loop`). Compiled programs are cached per loop structure and batch
shape; the last, smaller chunk of a batch is padded to the same shape.
"""

from __future__ import annotations

import dataclasses
import math
import os
import pathlib
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from wbc_jax.sim import host_loop, mjx_loop, physics, warp_graphs
from wbc_jax.sim import loop as loop_lib
from wbc_jax.sim import metrics as metrics_lib
from wbc_jax.sim.per_device import PerDevice
from wbc_jax.sim.scenario import Setup
from wbc_jax.sim.scenario import single as single_scenario
from wbc_jax.sim.state import Feedforward, Scenario
from wbc_jax.sim.watchdog import Watchdog, device_label, run_watched

# A queued run (scenarios per batch slot) checks which robots are decided every this many ticks
# at most (the largest divisor of the horizon's ticks up to it): 0.25 s at 100 Hz.
QUEUE_CHECK_TICKS = 25
# Memory of one environment of a batch, as a multiple of its MJX Data (the physics state): 4x
# covers what was measured (BENCHMARKS.md, the default robot's 31.6 kB Data in float32: 30-36 kB per env
# on an H100 with MJX-JAX, 117 kB on an H200 with Warp; experiments/checks/memory_estimate.py on the CPU).
MJX_ENV_FACTOR = 4
# C MuJoCo: one MjData per environment, resident after stepping (0.56 MB for the default robot,
# experiments/checks/memory_estimate.py), doubled for contact-rich states.
HOST_ENV_BYTES = 1_200_000


def enable_compilation_cache(path: str | os.PathLike | None = None) -> pathlib.Path:
    """Turn on JAX's persistent compilation cache (``$WBC_JAX_CACHE`` or the user's cache
    directory), so a second run of a job reuses the compiled programs of the first."""
    if path is None:
        path = (
            os.environ.get("WBC_JAX_CACHE")
            or pathlib.Path(os.environ.get("XDG_CACHE_HOME", pathlib.Path.home() / ".cache")) / "wbc_jax" / "xla"
        )
    path = pathlib.Path(path)
    path.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path


def lower_fresh(fn, *args):
    """``fn.lower(*args)`` (``fn`` a jitted function) with JAX's tracing caches cleared first.

    The persistent cache is keyed by the lowered program's text, and that text depends on what was
    traced before in the process: inner jitted functions cached by an earlier trace change how the
    program's private functions are shared and numbered (measured: the tuning gradient program traced
    second in a process differs from the same program traced first, so a carried cache missed it and a
    200 s compile ran again). Cleared, the text and the key depend on the program alone. Executables
    compiled ahead of time are kept; jitted functions re-trace on their next call."""
    jax.clear_caches()
    return fn.lower(*args)


def compile_ahead(fn, *args):
    """``fn`` compiled ahead of time for ``args``, keyed in the persistent cache by the program alone
    (:func:`lower_fresh`)."""
    return lower_fresh(fn, *args).compile()


def batch_devices() -> list:
    """The devices a batch is sharded over: every GPU (local, or global after jax.distributed); on
    the CPU, one device per process."""
    devices = jax.devices()
    if devices[0].platform != "cpu":
        return list(devices)
    # Host CPU devices of one process (XLA_FLAGS=--xla_force_host_platform_device_count) share that
    # machine's cores, so sharding over them gains nothing; and XLA:CPU deadlocks in the sharded
    # closed loop once a device holds several environments (jax 0.9.2: every thread idle, the
    # caller waiting forever; tests/test_sweep.py runs that configuration under a timeout).
    first: dict = {}
    for d in devices:
        first.setdefault(d.process_index, d)
    return list(first.values())


def device_mesh() -> Mesh:
    """1-D mesh over :func:`batch_devices`, axis 'batch'."""
    return Mesh(np.asarray(batch_devices()), ("batch",))


def pad_batch(tree, size: int):
    """Pad a batch (leading axis) to ``size`` with copies of its last entry."""
    n = int(jax.tree_util.tree_leaves(tree)[0].shape[0])
    if n == size:
        return tree
    return jax.tree_util.tree_map(
        lambda x: np.concatenate([np.asarray(x), np.repeat(np.asarray(x)[-1:], size - n, 0)]), tree
    )


def memory_estimate(setup_: Setup, batch: int, envs: int | None = None, queue: int = 1) -> dict:
    """Bytes a run of ``batch`` environments at once holds (``envs`` scenarios in all, default
    ``batch``; ``queue`` scenarios per batch slot), before it is allocated: {"bytes", "per_env",
    "scenario_bytes"}. Records (balance, view: one environment) are not counted."""
    envs = batch if envs is None else envs
    robot_mj = setup_.robot.mj_model
    data = jax.eval_shape(lambda: physics.device_data(robot_mj, "jax", setup_.loop.cfg.physics, setup_.qpos0))
    per_env = MJX_ENV_FACTOR * sum(x.size * x.dtype.itemsize for x in jax.tree_util.tree_leaves(data))
    if setup_.backend == "mujoco":
        per_env += HOST_ENV_BYTES
    one = jax.tree_util.tree_map(lambda x: np.asarray(x)[:1], single_scenario(setup_))
    scenario_bytes = sum(np.asarray(x).nbytes for x in jax.tree_util.tree_leaves(one)) + 64  # + the table's columns
    slots = math.ceil(batch / queue)
    return {"bytes": slots * per_env + envs * scenario_bytes, "per_env": per_env, "scenario_bytes": scenario_bytes}


def available_memory() -> tuple[int, str]:
    """(bytes free, where) on the batch's first device: GPU memory, or the host's available memory."""
    device = batch_devices()[0]
    stats = device.memory_stats() if device.platform != "cpu" else None
    if stats and "bytes_limit" in stats:
        return int(stats["bytes_limit"] - stats.get("bytes_in_use", 0)) * len(batch_devices()), str(device.platform)
    try:
        for line in pathlib.Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024, "host"
    except OSError:
        pass
    return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"), "host"


def check_memory(
    setup_: Setup, batch: int, *, envs: int | None = None, queue: int = 1, flag: str = "--chunk-size"
) -> dict:
    """Refuse a batch whose estimated memory (:func:`memory_estimate`) exceeds what is free, in
    one line naming ``flag``, the estimate and the largest batch that fits. Returns the estimate."""
    est = memory_estimate(setup_, batch, envs, queue)
    free, where = available_memory()
    if est["bytes"] > free:
        fixed = (envs or batch) * est["scenario_bytes"]
        fits = max(0, int((free - fixed) // est["per_env"]) * queue)
        hint = f"use {flag} {fits:,} or less" if fits >= 1 else "use a smaller grid"
        raise ValueError(
            f"{flag} {batch:,}: a batch of {batch:,} environments needs about "
            f"{est['bytes'] / 1e9:,.1f} GB ({est['per_env'] / 1e3:,.0f} kB each and {fixed / 1e9:,.2f} GB "
            f"of scenarios, estimated) and the {where} has {free / 1e9:,.1f} GB free; {hint}"
        )
    return est


@dataclasses.dataclass
class Run:
    """Result of :func:`run`: metrics (batch axis), records (B, T, ...) or None, seconds spent
    compiling (or loading) and running, and when the simulation started (``time.time()``: the
    call plus its compile time)."""

    metrics: metrics_lib.Metrics
    records: object
    compile_s: float
    run_s: float
    started: float = 0.0


def check_queue(queue, backend: str, record: bool = False) -> None:
    """A queue length (scenarios per batch slot, :func:`wbc_jax.sim.mjx_loop.rollout_queue`)
    that can run on ``backend``; a clear error otherwise."""
    if isinstance(queue, bool) or not isinstance(queue, int) or queue < 1:
        raise ValueError(f"queue must be a whole number >= 1 (scenarios per batch slot), got {queue!r}")
    if queue > 1 and backend == "mujoco":
        raise ValueError("a queue of scenarios per batch slot (queue > 1) needs an MJX backend: --backend jax or warp")
    if queue > 1 and record:
        raise ValueError("a queue of scenarios per batch slot (queue > 1) cannot record trajectories")


def run(
    setup_: Setup,
    scen: Scenario,
    *,
    batch_size: int | None = None,
    on_tick: Callable[[int], None] | None = None,
    queue: int = 1,
    feedforward: Feedforward | None = None,
    watch: Watchdog | None = None,
) -> Run:
    """Run the closed loop over a Scenario batch (leading axis B) on the setup's backend.

    ``batch_size``: the compiled batch shape (B is padded up to it; None: B). ``on_tick``: called
    with the ticks done (C MuJoCo and chunked MJX runs), for progress bars. ``queue``: scenarios
    per batch slot (MJX backends): the batch runs ceil(size / queue) slots, each retiring fallen
    or diverged robots and starting its next scenario (:func:`wbc_jax.sim.mjx_loop.rollout_queue`); the
    outcomes equal those of the plain run, and a retired environment's metrics stop at its
    retirement (``ticks``). ``feedforward``: torques added to the controller's in a window of
    ticks, with the batch axis B (:class:`wbc_jax.sim.state.Feedforward`; None: none). ``watch``: the
    chunk's bound per device and its timeline (:mod:`wbc_jax.sim.watchdog`; None: unbounded)."""
    loop = setup_.loop
    check_queue(queue, loop.backend, loop.cfg.record)
    if queue > 1 and feedforward is not None:
        raise ValueError("a queue of scenarios per batch slot (queue > 1) takes no feedforward torques")
    called = time.time()
    B = int(np.asarray(scen.friction).shape[0])
    size = B if batch_size is None else max(batch_size, B)
    padded = pad_batch(jax.tree_util.tree_map(np.asarray, scen), size)
    ff = None if feedforward is None else pad_batch(jax.tree_util.tree_map(np.asarray, feedforward), size)
    if queue > 1:
        out = _run_mjx_queue(setup_, padded, queue, watch=watch)
    elif loop.backend == "mujoco":
        if jax.process_count() > 1:
            raise ValueError(
                "a run over several processes (jax.distributed) needs an MJX backend: --backend jax or warp"
            )
        t0 = time.perf_counter()

        def host(times: dict):  # C MuJoCo's threads, driven from one host thread (compiling on a first call)
            start = time.perf_counter()  # not t0: the thread's own start is thread_start_s
            out = host_loop.run_host(loop, padded, setup_.qpos0, setup_.dtype, on_tick=on_tick, feedforward=ff)
            times.update(compile_s=out[2], wait_s=time.perf_counter() - start - out[2])
            return out

        label = f"{device_label(jax.devices('cpu')[0])} (C MuJoCo)"
        compiles = watch is not None and not watch.warm
        [(metrics, records, compile_s)] = run_watched([(label, host)], watch, "run", compiles=compiles)
        out = Run(metrics, records, compile_s, time.perf_counter() - t0 - compile_s)
    else:
        out = _run_mjx(setup_, padded, size, on_tick, ff, watch)
    out.started = called + out.compile_s
    out.metrics = jax.tree_util.tree_map(lambda x: np.asarray(x)[:B], out.metrics)
    if out.records is not None:
        out.records = jax.tree_util.tree_map(lambda x: np.asarray(x)[:B], out.records)
    return out


def _global_batch(tree, sharding: NamedSharding, dtype):
    """Global arrays (floats in ``dtype``) from the full batch every process holds: one process, or
    several after jax.distributed.initialize(), each filling the shards of its own devices."""
    floats = lambda x: np.asarray(x, dtype) if np.asarray(x).dtype.kind == "f" else np.asarray(x)  # noqa: E731
    return jax.tree_util.tree_map(
        lambda x: jax.make_array_from_callback(x.shape, sharding, lambda i, x=x: x[i]),
        jax.tree_util.tree_map(floats, tree),
    )


def _run_mjx(
    setup_: Setup, scen: Scenario, size: int, on_tick, ff: Feedforward | None = None, watch: Watchdog | None = None
) -> Run:
    """MJX backends: vmap(closed loop) per device (:class:`PerDevice`) over the batch, sharded
    along it over the device mesh. A run without records is one program (Warp's data never leaves
    it: its contact buffer is shared by a device's environments); a recorded run (``jax`` only)
    goes in chunks of ticks, for progress. Every array the programs close over lives on this
    process's own device (:mod:`wbc_jax.core.mjx`), so the same code runs in several processes. ``ff``:
    feedforward torques with the batch axis (None: none)."""
    loop, dtype = setup_.loop, setup_.dtype
    mesh = device_mesh()
    n_dev = mesh.devices.size
    padded = pad_batch(scen, size + (-size) % n_dev)
    batch = int(padded.friction.shape[0])
    local = batch // n_dev  # environments per device
    batched = PartitionSpec("batch")
    scen_dev = _global_batch(padded, NamedSharding(mesh, batched), dtype)
    qpos0 = np.asarray(setup_.qpos0, dtype)
    ff_dev = None if ff is None else _global_batch(pad_batch(ff, batch), NamedSharding(mesh, batched), dtype)
    nominal = physics.device_model(setup_.robot.mj_model, loop.backend, loop.cfg.physics)
    perturb = loop.cfg.perturb_plant

    def plant(s):
        return physics.plant_model(nominal, s.friction, s.mass_scale) if perturb else nominal

    cache = loop_lib.PROGRAMS  # compiled once per loop structure and batch shape
    ff_shape = None if ff is None else ff.torque.shape
    key = ("mjx", loop.structure_key, batch, str(dtype), n_dev, loop.cfg.record, ff_shape)
    compile_s = 0.0
    t0 = time.perf_counter()
    # Warp's data may not cross a vmap boundary (its contact buffer is shared by the batch): one
    # program for the whole horizon, recorded or not.
    if not loop.cfg.record or loop.backend == "warp":
        if key not in cache:

            def one(s, f):
                return mjx_loop.rollout(
                    loop,
                    plant(s),
                    loop.initial_qpos(jnp.asarray(qpos0), s.joint_offset),
                    s.gains,
                    s.push,
                    batch=local,
                    feedforward=f,
                )

            cache[key] = PerDevice(jax.vmap(one), mesh, (True, True))
            compile_s = cache[key].compile(scen_dev, ff_dev, watch=watch)
        _bound_warp_graphs(loop, len(cache[key].devices))
        t0 = time.perf_counter()
        one_process = jax.process_count() == 1  # each device's share copied to the host in its own thread
        outs = cache[key](scen_dev, ff_dev, watch=watch, to_host=one_process)
        metrics, records = jax.tree_util.tree_map(_to_host, outs)
        if on_tick is not None:
            on_tick(loop.n_ticks)
        return Run(metrics, records, compile_s, time.perf_counter() - t0)

    chunk = _tick_chunk(loop.n_ticks)

    def start(s):
        return jax.vmap(lambda x: mjx_loop.start(loop, loop.initial_qpos(jnp.asarray(qpos0), x.joint_offset)))(s)

    def advance(s, carry, k0, f):
        step = lambda x, c, u: mjx_loop.chunk(loop, plant(x), x.gains, x.push, c, k0, chunk, u)  # noqa: E731
        return jax.vmap(step)(s, carry, f)

    if key not in cache:
        start_fn = PerDevice(start, mesh, (True,))
        compile_s = start_fn.compile(scen_dev, watch=watch)
        advance_fn = PerDevice(advance, mesh, (True, True, False, True))
        compile_s += advance_fn.compile(scen_dev, start_fn(scen_dev), np.int32(0), ff_dev, watch=watch)
        cache[key] = (start_fn, advance_fn)
    start_fn, advance_fn = cache[key]
    t0 = time.perf_counter()
    carry = start_fn(scen_dev, watch=watch)
    pieces = []
    for k0 in range(0, loop.n_ticks, chunk):
        carry, records = advance_fn(scen_dev, carry, np.int32(k0), ff_dev, watch=watch)
        pieces.append(jax.tree_util.tree_map(_to_host, records))
        if on_tick is not None:
            on_tick(min(k0 + chunk, loop.n_ticks))
    metrics = jax.tree_util.tree_map(_to_host, metrics_lib.final(carry[1].metrics, carry[2]))
    records = jax.tree_util.tree_map(lambda *xs: np.concatenate(xs, axis=1), *pieces)
    return Run(metrics, records, compile_s, time.perf_counter() - t0)


def _run_mjx_queue(
    setup_: Setup, scen: Scenario, queue: int, check_ticks: int = QUEUE_CHECK_TICKS, watch: Watchdog | None = None
) -> Run:
    """MJX backends, a queue of scenarios per batch slot: each device takes its share of the
    batch's scenarios and works through them in order with ceil(share / queue) slots
    (:func:`wbc_jax.sim.mjx_loop.rollout_queue`, vmap over its slots; :class:`PerDevice`). A
    scenario's outcome does not depend on the slot that runs it, so the results equal the plain
    run's on any number of devices. ``check_ticks``: the most ticks between hand-ins
    (``benchmarks/queue_overhead.py`` varies it)."""
    loop, dtype = setup_.loop, setup_.dtype
    mesh = device_mesh()
    n_dev = mesh.devices.size
    size = int(scen.friction.shape[0])
    padded = pad_batch(scen, size + (-size) % n_dev)
    share = int(padded.friction.shape[0]) // n_dev  # scenarios per device
    slots = min(math.ceil(share / queue), share)  # slots per device
    batched = PartitionSpec("batch")
    scen_dev = _global_batch(padded, NamedSharding(mesh, batched), dtype)
    qpos0 = np.asarray(setup_.qpos0, dtype)
    nominal = physics.device_model(setup_.robot.mj_model, loop.backend, loop.cfg.physics)
    perturb = loop.cfg.perturb_plant
    segment = _tick_chunk(loop.n_ticks, target=check_ticks)
    key = ("mjx-queue", loop.structure_key, int(padded.friction.shape[0]), slots, segment, str(dtype), n_dev)
    cache = loop_lib.PROGRAMS
    compile_s = 0.0
    t0 = time.perf_counter()
    if key not in cache:

        def plant_of(x):
            return physics.plant_model(nominal, x.friction, x.mass_scale) if perturb else nominal

        def on_device(s):
            def slot(i):
                return mjx_loop.rollout_queue(loop, plant_of, jnp.asarray(qpos0), s, i, segment, "slots", batch=slots)

            return jax.vmap(slot, out_axes=None, axis_name="slots")(jnp.arange(slots, dtype=jnp.int32))

        cache[key] = PerDevice(on_device, mesh, (True,))
        compile_s = cache[key].compile(scen_dev, watch=watch)
    _bound_warp_graphs(loop, len(cache[key].devices))
    t0 = time.perf_counter()
    outs = cache[key](scen_dev, watch=watch, to_host=jax.process_count() == 1)
    metrics = jax.tree_util.tree_map(lambda x: _to_host(x)[:size], outs)
    return Run(metrics, None, compile_s, time.perf_counter() - t0)


def _bound_warp_graphs(loop, devices: int) -> None:
    """MJX-Warp's graph cache bound (``PhysicsConfig.warp_graph_cache``; None: 32 graphs per device of
    the run), set after the programs are traced (tracing may set Warp's own again) and before they run
    (:mod:`wbc_jax.sim.warp_graphs`)."""
    if loop.backend == "warp":
        warp_graphs.bound(loop.cfg.physics.warp_graph_cache, devices)


def _to_host(x) -> np.ndarray:
    """A (possibly multi-process) global array as one numpy array on every process."""
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        return np.asarray(multihost_utils.process_allgather(x, tiled=True))
    return np.asarray(x)


def _tick_chunk(n_ticks: int, target: int = 100) -> int:
    """The largest divisor of n_ticks up to ``target`` (whole horizon if that is tiny): chunks of
    one shape, compiled once."""
    best = max(d for d in range(1, min(target, n_ticks) + 1) if n_ticks % d == 0)
    return best if best >= 10 else n_ticks
