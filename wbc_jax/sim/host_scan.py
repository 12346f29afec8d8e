"""The closed loop over a horizon on C MuJoCo as one compiled program (``mujoco`` backend).

The whole horizon is one XLA program: a ``lax.scan`` of the ticks of a
:class:`wbc_jax.sim.loop.ClosedLoop` (controller, metrics, records: the code every driver runs)
whose physics is C MuJoCo's ``mj_step``, called from inside the program through XLA's FFI
(:mod:`wbc_jax.sim.native`), so no Python runs between ticks. The environments' C models and data
stay in this process (:class:`wbc_jax.sim.physics.HostBatch` builds them); the program takes their
addresses as an argument, so one compiled program serves every run of its shape. The physics
equals :mod:`wbc_jax.sim.host_loop`'s step for step (``HostBatch.step``: a diverged environment is
restored to its last sound state and frozen); the environments of a batch step one after the
other on the program's thread.
"""

from __future__ import annotations

import functools
import time

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax.sim import executables, native, physics
from wbc_jax.sim import metrics as metrics_lib
from wbc_jax.sim.loop import PROGRAMS
from wbc_jax.sim.state import Scenario, traced_at_matmul_precision


@traced_at_matmul_precision
def horizon(loop, gains, push, qpos, handles):
    """Every tick of B environments on C MuJoCo, traced as one program.

    One environment (B = 1) is traced without ``vmap``: under ``vmap`` a branch on a batched
    predicate runs both sides (the soft momentum QP behind the first one), without it only the
    side taken.

    Args:
      gains, push: the scenarios' Gains and Push with a leading batch axis B.
      qpos: (B, nq) initial positions (zero velocity), in the controller's dtype; the C data of
        ``handles`` hold the same state.
      handles: (B, 4) uint32 (:func:`wbc_jax.sim.native.handles`).

    Returns:
      (Metrics with a batch axis, records with axes (B, T, ...) or None).
    """
    idx, B = loop.idx, qpos.shape[0]
    n_con = physics.max_contacts(loop.robot.mj_model)
    if B == 1:  # the batch axis only at the physics calls
        unbatched = lambda tree: jax.tree_util.tree_map(lambda x: x[0], tree)  # noqa: E731
        gains, push, qpos = unbatched(gains), unbatched(push), unbatched(qpos)
        batched = lambda fn, in_axes=0: fn  # noqa: E731
        to_physics = lambda x: x[None]  # noqa: E731
        from_physics = lambda x: x[0]  # noqa: E731
    else:
        batched = jax.vmap
        to_physics = from_physics = lambda x: x
    control = batched(loop.control, in_axes=(0, 0, 0, 0, None, 0, 0))

    def tick(carry, k):
        state, q, v, ok = carry
        state, ctrl, record = control(gains, state, q, v, k, ok, push)
        xfrc = batched(loop.xfrc, in_axes=(0, None))(push, k)
        q, v, ok = (
            from_physics(x)
            for x in native.step(handles, to_physics(ctrl), to_physics(xfrc), to_physics(ok), idx.nq, idx.nv)
        )
        if loop.cfg.record or loop.observes_contacts:
            slots = tuple(from_physics(x) for x in native.contacts(handles, to_physics(q), n_con, q.dtype))
            if loop.cfg.record:
                record = batched(loop.measure)(record, *slots)
            if loop.observes_contacts:
                state = batched(loop.observe)(state, *slots)
        return (state, q, v, ok), record

    start = batched(loop.init)(qpos)
    carry = (start, qpos, jnp.zeros(qpos.shape[:-1] + (idx.nv,), qpos.dtype), jnp.ones(qpos.shape[:-1], bool))
    (state, _, _, ok), records = jax.lax.scan(tick, carry, jnp.arange(loop.n_ticks, dtype=jnp.int32))
    metrics = metrics_lib.final(state.metrics, ok)
    if B == 1:
        metrics = jax.tree_util.tree_map(lambda x: x[None], metrics)
        return metrics, jax.tree_util.tree_map(lambda x: x[None], records)
    return metrics, jax.tree_util.tree_map(lambda x: jnp.swapaxes(x, 0, 1), records)


def program(loop, gains, push, qpos, handles):
    """The compiled :func:`horizon` for these argument shapes: (program, seconds spent compiling
    or loading it now). Cached in this process (:data:`wbc_jax.sim.loop.PROGRAMS`) and on disk
    (:mod:`wbc_jax.sim.executables`)."""
    key = ("host-scan", loop.structure_key, qpos.shape, str(qpos.dtype))
    if key in PROGRAMS:
        return PROGRAMS[key], 0.0
    t0 = time.perf_counter()
    args = (gains, push, qpos, handles)
    PROGRAMS[key] = executables.compiled(
        "host_scan",
        (loop.structure_key, native.SOURCE.read_bytes()),
        args,
        lambda: jax.jit(functools.partial(horizon, loop)).lower(*args),
    )
    return PROGRAMS[key], time.perf_counter() - t0


def run_scan(loop, scen: Scenario, models: list, qpos: np.ndarray, dtype, *, on_tick=None):
    """Every tick of a batch of B environments on C MuJoCo in one compiled program.

    Args:
      scen: Scenario with a leading batch axis B (numpy arrays).
      models: B C models (:func:`wbc_jax.sim.host_loop.host_models`).
      qpos: (B, nq) initial positions.
      dtype: the controller's float dtype.
      on_tick: called once with the number of ticks, when the program is done.

    Returns:
      (Metrics with a batch axis, records with axes (B, T, ...) or None, seconds compiling).
    """
    problem = native.available()
    if problem is not None:
        raise RuntimeError(f"the compiled C MuJoCo loop is not available here: {problem}")
    floats = lambda x: np.asarray(x, dtype) if np.asarray(x).dtype.kind == "f" else np.asarray(x)  # noqa: E731
    gains, push = (jax.tree_util.tree_map(floats, tree) for tree in (scen.gains, scen.push))
    host = physics.HostBatch(models, qpos, threads=1)
    try:
        ids = native.handles(host.models, host.data)
        fn, compile_s = program(loop, gains, push, np.asarray(qpos, dtype), ids)
        metrics, records = jax.block_until_ready(fn(gains, push, np.asarray(qpos, dtype), ids))
    finally:
        host.close()
    if on_tick is not None:
        on_tick(loop.n_ticks)
    metrics = jax.tree_util.tree_map(np.asarray, metrics)
    records = None if records is None else jax.tree_util.tree_map(np.asarray, records)
    return metrics, records, compile_s
