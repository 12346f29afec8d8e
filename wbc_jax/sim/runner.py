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

from wbc_jax.sim import host_loop, mjx_loop, physics
from wbc_jax.sim import loop as loop_lib
from wbc_jax.sim import metrics as metrics_lib
from wbc_jax.sim.scenario import Setup
from wbc_jax.sim.state import Scenario

# A queued run (scenarios per batch slot) checks which robots are decided every this many ticks
# at most (the largest divisor of the horizon's ticks up to it): 0.25 s at 100 Hz.
QUEUE_CHECK_TICKS = 25


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
    """A queue length (scenarios per batch slot, :meth:`wbc_jax.sim.rollout.ClosedLoop.rollout_queue`)
    that can run on ``backend``; a clear error otherwise."""
    if isinstance(queue, bool) or not isinstance(queue, int) or queue < 1:
        raise ValueError(f"queue must be a whole number >= 1 (scenarios per batch slot), got {queue!r}")
    if queue > 1 and backend == "mujoco":
        raise ValueError("a queue of scenarios per batch slot (queue > 1) needs an MJX backend: --backend jax or warp")
    if queue > 1 and record:
        raise ValueError("a queue of scenarios per batch slot (queue > 1) cannot record trajectories")


def run(setup_: Setup, scen: Scenario, *, batch_size: int | None = None,
        on_tick: Callable[[int], None] | None = None, queue: int = 1) -> Run:  # fmt: skip
    """Run the closed loop over a Scenario batch (leading axis B) on the setup's backend.

    ``batch_size``: the compiled batch shape (B is padded up to it; None: B). ``on_tick``: called
    with the ticks done (C MuJoCo and chunked MJX runs), for progress bars. ``queue``: scenarios
    per batch slot (MJX backends): the batch runs ceil(size / queue) slots, each retiring fallen
    or diverged robots and starting its next scenario (:meth:`ClosedLoop.rollout_queue`); the
    outcomes equal those of the plain run, and a retired environment's metrics stop at its
    retirement (``ticks``)."""
    loop = setup_.loop
    check_queue(queue, loop.backend, loop.cfg.record)
    called = time.time()
    B = int(np.asarray(scen.friction).shape[0])
    size = B if batch_size is None else max(batch_size, B)
    padded = pad_batch(jax.tree_util.tree_map(np.asarray, scen), size)
    if queue > 1:
        out = _run_mjx_queue(setup_, padded, queue)
    elif loop.backend == "mujoco":
        if jax.process_count() > 1:
            raise ValueError(
                "a run over several processes (jax.distributed) needs an MJX backend: --backend jax or warp"
            )
        t0 = time.perf_counter()
        metrics, records, compile_s = host_loop.run_host(loop, padded, setup_.qpos0, setup_.dtype, on_tick=on_tick)
        out = Run(metrics, records, compile_s, time.perf_counter() - t0 - compile_s)
    else:
        out = _run_mjx(setup_, padded, size, on_tick)
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


def per_device(fn, mesh: Mesh, in_specs, out_specs):
    """``jit(shard_map(fn))``: each device runs ``fn`` on its own shard of the batch axis, with no
    communication between devices. MJX-Warp's step is a foreign call with no partitioning rule:
    under plain ``jit`` with sharded inputs XLA ran it over the whole batch on every device (its
    contact buffer sized for one device's share), which made two GPUs slower than one and changed
    outcomes; here each device sees exactly its share."""
    return jax.jit(jax.shard_map(fn, mesh=mesh, in_specs=in_specs, out_specs=out_specs, check_vma=False))


def _run_mjx(setup_: Setup, scen: Scenario, size: int, on_tick) -> Run:
    """MJX backends: vmap(closed loop) per device (:func:`per_device`) over the batch, sharded
    along it over the device mesh. A run without records is one program (Warp's data never leaves
    it: its contact buffer is shared by a device's environments); a recorded run (``jax`` only)
    goes in chunks of ticks, for progress. Every array the programs close over lives on this
    process's own device (:mod:`wbc_jax.core.mjx`), so the same code runs in several processes."""
    loop, dtype = setup_.loop, setup_.dtype
    mesh = device_mesh()
    n_dev = mesh.devices.size
    padded = pad_batch(scen, size + (-size) % n_dev)
    batch = int(padded.friction.shape[0])
    local = batch // n_dev  # environments per device
    batched, same = PartitionSpec("batch"), PartitionSpec()
    scen_dev = _global_batch(padded, NamedSharding(mesh, batched), dtype)
    qpos0 = np.asarray(setup_.qpos0, dtype)
    nominal = physics.device_model(setup_.robot.mj_model, loop.backend, loop.cfg.physics)
    perturb = loop.cfg.perturb_plant

    def plant(s):
        return physics.plant_model(nominal, s.friction, s.mass_scale) if perturb else nominal

    cache = loop_lib.PROGRAMS  # compiled once per loop structure and batch shape
    key = ("mjx", loop.structure_key, batch, str(dtype), n_dev, loop.cfg.record)
    compile_s = 0.0
    t0 = time.perf_counter()
    # Warp's data may not cross a vmap boundary (its contact buffer is shared by the batch): one
    # program for the whole horizon, recorded or not.
    if not loop.cfg.record or loop.backend == "warp":
        if key not in cache:

            def one(s):
                return mjx_loop.rollout(loop, plant(s), loop.initial_qpos(jnp.asarray(qpos0), s.joint_offset),
                                        s.gains, s.push, batch=local)  # fmt: skip

            program = per_device(jax.vmap(one), mesh, in_specs=(batched,), out_specs=batched)
            cache[key] = program.lower(scen_dev).compile()
            compile_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        metrics, records = jax.tree_util.tree_map(_to_host, cache[key](scen_dev))
        if on_tick is not None:
            on_tick(loop.n_ticks)
        return Run(metrics, records, compile_s, time.perf_counter() - t0)

    chunk = _tick_chunk(loop.n_ticks)

    def start(s):
        return jax.vmap(lambda x: mjx_loop.start(loop, loop.initial_qpos(jnp.asarray(qpos0), x.joint_offset)))(s)

    def advance(s, carry, k0):
        step = lambda x, c: mjx_loop.chunk(loop, plant(x), x.gains, x.push, c, k0, chunk)  # noqa: E731
        return jax.vmap(step)(s, carry)

    if key not in cache:
        start_program = per_device(start, mesh, in_specs=(batched,), out_specs=batched)
        start_fn = start_program.lower(scen_dev).compile()
        carry_shape = jax.eval_shape(start_program, scen_dev)
        advance_fn = per_device(advance, mesh, in_specs=(batched, batched, same), out_specs=batched)
        cache[key] = (start_fn, advance_fn.lower(scen_dev, carry_shape, jnp.int32(0)).compile())
        compile_s = time.perf_counter() - t0
    start_fn, advance_fn = cache[key]
    t0 = time.perf_counter()
    carry = start_fn(scen_dev)
    pieces = []
    for k0 in range(0, loop.n_ticks, chunk):
        carry, records = advance_fn(scen_dev, carry, jnp.int32(k0))
        pieces.append(jax.tree_util.tree_map(_to_host, records))
        if on_tick is not None:
            on_tick(min(k0 + chunk, loop.n_ticks))
    metrics = jax.tree_util.tree_map(_to_host, metrics_lib.final(carry[1].metrics, carry[2]))
    records = jax.tree_util.tree_map(lambda *xs: np.concatenate(xs, axis=1), *pieces)
    return Run(metrics, records, compile_s, time.perf_counter() - t0)


def _run_mjx_queue(setup_: Setup, scen: Scenario, queue: int, check_ticks: int = QUEUE_CHECK_TICKS) -> Run:
    """MJX backends, a queue of scenarios per batch slot: each device takes its share of the
    batch's scenarios and works through them in order with ceil(share / queue) slots
    (:func:`wbc_jax.sim.mjx_loop.rollout_queue`, vmap over its slots; :func:`per_device`). A
    scenario's outcome does not depend on the slot that runs it, so the results equal the plain
    run's on any number of devices. ``check_ticks``: the most ticks between hand-ins
    (``experiments/queue_overhead.py`` varies it)."""
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

        program = per_device(on_device, mesh, in_specs=(batched,), out_specs=batched)
        cache[key] = program.lower(scen_dev).compile()
        compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    metrics = jax.tree_util.tree_map(lambda x: _to_host(x)[:size], cache[key](scen_dev))
    return Run(metrics, None, compile_s, time.perf_counter() - t0)


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
