"""The closed loop over a horizon on C MuJoCo as one compiled program (``mujoco`` backend).

The whole horizon is one XLA program: a ``lax.scan`` of the ticks of a
:class:`wbc_jax.sim.loop.ClosedLoop` (controller, metrics, records: the code every driver runs)
whose physics is C MuJoCo's ``mj_step``, called from inside the program through XLA's FFI
(:mod:`wbc_jax.sim.native`), so no Python runs between ticks. The environments' C models and data
stay in this process (:class:`wbc_jax.sim.physics.HostBatch` builds them); the program takes their
addresses as an argument, so one compiled program serves every run of its shape. Where the plant
is the controller's own model (:func:`engine_terms`), the controller takes its dynamics terms from
C MuJoCo, as TSID takes them from Pinocchio: each tick's ``mj_step`` is split at ``mj_step1``
(kinematics, mass matrix, collisions, bias and passive forces at the new state), whose results the
physics call returns (:func:`wbc_jax.sim.native.step_terms`), and the next tick starts with
``mj_step2``, so nothing is computed twice. The physics
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

from wbc_jax.robot import dynamics
from wbc_jax.sim import executables, native, physics
from wbc_jax.sim import metrics as metrics_lib
from wbc_jax.sim.loop import PROGRAMS
from wbc_jax.sim.state import Scenario, traced_at_matmul_precision


@traced_at_matmul_precision
def horizon(loop, gains, push, qpos, handles, feedforward=None):
    """Every tick of B environments on C MuJoCo, traced as one program.

    One environment (B = 1) is traced without ``vmap``: under ``vmap`` a branch on a batched
    predicate runs both sides (the soft momentum QP behind the first one), without it only the
    side taken.

    Args:
      gains, push: the scenarios' Gains and Push with a leading batch axis B.
      qpos: (B, nq) initial positions (zero velocity), in the controller's dtype; the C data of
        ``handles`` hold the same state.
      handles: (B, 4) uint32 (:func:`wbc_jax.sim.native.handles`).
      feedforward: :class:`wbc_jax.sim.state.Feedforward` torques with a leading batch axis B, or None.

    Returns:
      (Metrics with a batch axis, records with axes (B, T, ...) or None).
    """
    idx, B = loop.idx, qpos.shape[0]
    n_con = physics.max_contacts(loop.robot.mj_model)
    if B == 1:  # the batch axis only at the physics calls
        unbatched = lambda tree: jax.tree_util.tree_map(lambda x: x[0], tree)  # noqa: E731
        gains, push, qpos, feedforward = (unbatched(x) for x in (gains, push, qpos, feedforward))
        batched = lambda fn, in_axes=0: fn  # noqa: E731
        to_physics = lambda x: x[None]  # noqa: E731
        from_physics = lambda x: x[0]  # noqa: E731
    else:
        batched = jax.vmap
        to_physics = from_physics = lambda x: x
    control = batched(
        lambda g, s, q, v, k, ok, p, f, t: loop.control(g, s, q, v, k, ok, p, feedforward=f, terms=t),
        in_axes=(0, 0, 0, 0, None, 0, 0, 0, 0),
    )
    slots_read = loop.cfg.record or loop.observes_contacts
    if engine_terms(loop):
        physics_step = _SplitStep(loop, handles, B, n_con if slots_read else 0, qpos.dtype)
    else:
        physics_step = functools.partial(_plain_step, loop, handles, n_con if slots_read else 0)
    from_engine = batched(lambda q, v, e: dynamics.terms_from_engine(idx, q, v, e, loop.controller.frames))

    def tick(carry, k):
        state, q, v, ok, engine = carry
        terms = None if engine is None else from_engine(q, v, jax.tree_util.tree_map(from_physics, engine[1]))
        state, ctrl, record = control(gains, state, q, v, k, ok, push, feedforward, terms)
        xfrc = batched(loop.xfrc, in_axes=(0, None))(push, k)
        q, v, ok, slots, engine = physics_step(to_physics(ctrl), to_physics(xfrc), to_physics(ok), engine)
        q, v, ok = from_physics(q), from_physics(v), from_physics(ok)
        slots = tuple(from_physics(x) for x in slots)
        if loop.cfg.record:
            record = batched(loop.measure)(record, *slots)
        if loop.observes_contacts:
            state = batched(loop.observe)(state, *slots)
        return (state, q, v, ok, engine), record

    engine = physics_step.start() if isinstance(physics_step, _SplitStep) else None
    terms0 = None
    if engine is not None:  # the initial terms (zero velocity) from C MuJoCo too
        zero_v = jnp.zeros(qpos.shape[:-1] + (idx.nv,), qpos.dtype)
        terms0 = from_engine(qpos, zero_v, jax.tree_util.tree_map(from_physics, engine[1]))
    start = batched(lambda q, t: loop.init(q, terms=t))(qpos, terms0)
    carry = (start, qpos, jnp.zeros(qpos.shape[:-1] + (idx.nv,), qpos.dtype), jnp.ones(qpos.shape[:-1], bool), engine)
    (state, _, _, ok, _), records = jax.lax.scan(tick, carry, jnp.arange(loop.n_ticks, dtype=jnp.int32))
    metrics = metrics_lib.final(state.metrics, ok)
    if B == 1:
        metrics = jax.tree_util.tree_map(lambda x: x[None], metrics)
        return metrics, jax.tree_util.tree_map(lambda x: x[None], records)
    return metrics, jax.tree_util.tree_map(lambda x: jnp.swapaxes(x, 0, 1), records)


def engine_terms(loop) -> bool:
    """Whether the controller takes its dynamics terms from C MuJoCo (:func:`native.step_terms`)
    rather than computing them in XLA: where every plant is the controller's own model. A
    perturbed plant (its masses scaled) is not, and the controller must not see its dynamics."""
    return not loop.cfg.perturb_plant


def _plain_step(loop, handles, n_con: int, ctrl, xfrc, ok, engine):
    """The tick's physics by ``mj_step`` (:func:`native.step`), then the contact slots."""
    idx = loop.idx
    q, v, ok = native.step(handles, ctrl, xfrc, ok, idx.nq, idx.nv)
    slots = native.contacts(handles, q, n_con, q.dtype) if n_con else ()
    return q, v, ok, slots, engine


class _SplitStep:
    """The tick's physics split at ``mj_step1`` with the dynamics terms from C MuJoCo
    (:func:`native.step_terms`): the engine carry is (the last contact slots, EngineTerms)."""

    def __init__(self, loop, handles, batch: int, n_con: int, dtype):
        m, idx = loop.robot.mj_model, loop.idx
        self.loop, self.handles, self.batch, self.dtype = loop, handles, batch, dtype
        self.sizes = dict(nq=idx.nq, nv=idx.nv, nbody=m.nbody, base_body=idx.base_body, frames=loop.controller.frames)
        self.slots0 = (
            jnp.zeros((batch, n_con, 3), dtype),
            jnp.zeros((batch, n_con, 3), dtype),
            jnp.zeros((batch, n_con, 2), jnp.int32),
        )
        self.n_con = n_con

    def start(self):
        """The loop's first call: mj_step1 at the initial states; (slots, EngineTerms) there."""
        m = self.loop.robot.mj_model
        ctrl = jnp.zeros((self.batch, m.nu), self.dtype)
        xfrc = jnp.zeros((self.batch, 0, m.nbody, 6), self.dtype)
        ok = jnp.ones(self.batch, bool)
        _, _, _, slots, e = native.step_terms(self.handles, ctrl, xfrc, ok, self.slots0, start=True, **self.sizes)
        return slots, e

    def __call__(self, ctrl, xfrc, ok, engine):
        q, v, ok, slots, e = native.step_terms(self.handles, ctrl, xfrc, ok, engine[0], **self.sizes)
        return q, v, ok, slots if self.n_con else (), (slots, e)


def program(loop, gains, push, qpos, handles, feedforward=None):
    """The compiled :func:`horizon` for these argument shapes (and feedforward window, or none): (program,
    seconds spent compiling or loading it now). Cached in this process (:data:`wbc_jax.sim.loop.PROGRAMS`) and
    on disk (:mod:`wbc_jax.sim.executables`)."""
    window = None if feedforward is None else feedforward.torque.shape
    key = ("host-scan", loop.structure_key, qpos.shape, str(qpos.dtype), window)
    if key in PROGRAMS:
        return PROGRAMS[key], 0.0
    t0 = time.perf_counter()
    args = (gains, push, qpos, handles, feedforward)
    PROGRAMS[key] = executables.compiled(
        "host_scan",
        (loop.structure_key, native.SOURCE.read_bytes()),
        args,
        lambda: jax.jit(functools.partial(horizon, loop)).lower(*args),
    )
    return PROGRAMS[key], time.perf_counter() - t0


def run_scan(loop, scen: Scenario, models: list, qpos: np.ndarray, dtype, *, on_tick=None, feedforward=None):
    """Every tick of a batch of B environments on C MuJoCo in one compiled program.

    Args:
      scen: Scenario with a leading batch axis B (numpy arrays).
      models: B C models (:func:`wbc_jax.sim.host_loop.host_models`).
      qpos: (B, nq) initial positions.
      dtype: the controller's float dtype.
      on_tick: called once with the number of ticks, when the program is done.
      feedforward: :class:`wbc_jax.sim.state.Feedforward` torques with a leading batch axis B, or None.

    Returns:
      (Metrics with a batch axis, records with axes (B, T, ...) or None, seconds compiling).
    """
    problem = native.available()
    if problem is not None:
        raise RuntimeError(f"the compiled C MuJoCo loop is not available here: {problem}")
    floats = lambda x: np.asarray(x, dtype) if np.asarray(x).dtype.kind == "f" else np.asarray(x)  # noqa: E731
    gains, push = (jax.tree_util.tree_map(floats, tree) for tree in (scen.gains, scen.push))
    ff = None if feedforward is None else jax.tree_util.tree_map(floats, feedforward)
    host = physics.HostBatch(models, qpos, threads=1)
    try:
        ids = native.handles(host.models, host.data)
        fn, compile_s = program(loop, gains, push, np.asarray(qpos, dtype), ids, ff)
        metrics, records = jax.block_until_ready(fn(gains, push, np.asarray(qpos, dtype), ids, ff))
    finally:
        host.close()
    if on_tick is not None:
        on_tick(loop.n_ticks)
    metrics = jax.tree_util.tree_map(np.asarray, metrics)
    records = None if records is None else jax.tree_util.tree_map(np.asarray, records)
    return metrics, records, compile_s
