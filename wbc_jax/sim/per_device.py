"""One single-device program per device of the batch mesh, run side by side under a watchdog.

:class:`PerDevice` is how MJX chunks run on several devices (:mod:`wbc_jax.sim.runner`); each
device's compile and run go through :func:`wbc_jax.sim.watchdog.run_watched`, so a stalled device
is an error naming it and the chunk, and each device's waits are timed.
"""

from __future__ import annotations

import time

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from wbc_jax.sim.watchdog import Watchdog, device_label, run_watched


class PerDevice:
    """``fn`` compiled once for each of this process's devices of ``mesh``; a call runs each device's
    shard of the batch axis on that device (asynchronously, side by side) and returns global arrays
    sharded along the batch axis, as ``jit(shard_map(fn))`` would, with no communication between
    devices. Single-device programs, because (i) MJX-Warp's step is a foreign call with no
    partitioning rule: under ``jit`` with sharded inputs XLA ran it over the whole batch on every
    device (its contact buffer sized for one device's share), which made two GPUs slower than one
    and changed outcomes, and (ii) XLA (jax 0.11.2, CUDA) crashed compiling the closed loop as one
    two-GPU ``shard_map`` program.

    Args:
      fn: the per-device function of its arguments' local shards.
      mesh: the 1-D batch mesh (:func:`wbc_jax.sim.runner.device_mesh`).
      batched: per positional argument, True if it is sharded along the batch axis (a global
        array), False if every device takes it whole (a host value).
    """

    def __init__(self, fn, mesh: Mesh, batched: tuple[bool, ...]):
        self.fn, self.mesh, self.batched = fn, mesh, batched
        self.devices = [d for d in mesh.devices.flat if d.process_index == jax.process_index()]
        self.compiled: dict = {}

    def _local(self, args, device):
        """The arguments as ``device`` sees them: its shard of each batched global array."""

        def shard(x):
            return next(s.data for s in x.addressable_shards if s.device == device)

        return [jax.tree_util.tree_map(shard, a) if b else a for a, b in zip(args, self.batched, strict=True)]

    def compile(self, *args, watch: Watchdog | None = None) -> float:
        """Compile for every local device; returns the seconds spent. Tracing happens here, in the
        caller's thread (JAX's settings such as ``enable_x64`` are thread-local); only XLA's compile
        runs in a thread per device (bounded by ``watch``)."""
        t0 = time.perf_counter()
        lowered = []
        for device in self.devices:
            on = jax.sharding.SingleDeviceSharding(device)
            lowered.append(jax.jit(self.fn, in_shardings=on, out_shardings=on).lower(*self._local(args, device)))

        def compile_one(low):
            def work(times: dict):
                start = time.perf_counter()
                out = low.compile()
                times["compile_s"] = time.perf_counter() - start
                return out

            return work

        tasks = [(device_label(d), compile_one(low)) for d, low in zip(self.devices, lowered, strict=True)]
        self.compiled = dict(zip(self.devices, run_watched(tasks, watch, "compile"), strict=True))
        return time.perf_counter() - t0

    def __call__(self, *args, watch: Watchdog | None = None, to_host: bool = False):
        """Run every device's share (one host thread per device: an XLA:GPU program with while
        loops, the QP and the physics' solver, runs its loop control on the thread that launched
        it, so launching the devices one after the other from one thread ran them one after the
        other). ``to_host``: return numpy arrays (each device's share copied in its own thread;
        one process only) instead of global device arrays. ``watch``: the chunk's bound and
        timeline (each device's dispatch, wait for its run and transfer)."""
        if to_host and jax.process_count() > 1:
            raise ValueError("to_host gathers one process's devices; use global arrays across processes")

        def run_one(device):
            def work(times: dict):
                start = time.perf_counter()
                out = self.compiled[device](*self._local(args, device))
                dispatched = time.perf_counter()
                out = jax.block_until_ready(out)
                ran = time.perf_counter()
                if to_host:
                    out = jax.tree_util.tree_map(np.asarray, out)
                times.update(
                    dispatch_s=dispatched - start, wait_s=ran - dispatched, transfer_s=time.perf_counter() - ran
                )
                return out

            return work

        outs = run_watched([(device_label(d), run_one(d)) for d in self.devices], watch, "run")
        if to_host:  # the devices' shares in mesh order: the global batch
            return jax.tree_util.tree_map(lambda *leaves: np.concatenate(leaves, axis=0), *outs)
        sharding = NamedSharding(self.mesh, PartitionSpec("batch"))
        n_dev = self.mesh.devices.size

        def assemble(*leaves):
            shape = (leaves[0].shape[0] * n_dev, *leaves[0].shape[1:])
            return jax.make_array_from_single_device_arrays(shape, sharding, list(leaves))

        return jax.tree_util.tree_map(assemble, *outs)
