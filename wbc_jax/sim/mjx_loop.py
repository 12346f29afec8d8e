"""The closed loop over a horizon on an MJX engine (``jax``, ``warp``): one ``lax.scan`` of ticks.

Functions of a :class:`wbc_jax.sim.loop.ClosedLoop` first (MJX style, ``f(loop, ...)``): jit
them, vmap them over scenarios, differentiate them (``jax``). :func:`rollout_queue` instead runs
several scenarios per batch slot: a fallen or diverged robot is retired and its slot starts the
next scenario.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp

from wbc_jax.control.gains import Gains
from wbc_jax.core.mjx import mjx
from wbc_jax.core.types import Array
from wbc_jax.robot import dynamics
from wbc_jax.sim import metrics as metrics_lib
from wbc_jax.sim import physics, warp_split
from wbc_jax.sim.state import Feedforward, Push, Scenario, traced_at_matmul_precision


@jax.custom_jvp
def _dependency(seed):
    """0 that depends on ``seed`` (batched with it, carrying a tangent), whose derivative is a constant
    zero: in reverse mode no cotangent flows back through it, so a non-finite cotangent of a quantity
    that does not truly depend on the parameters (the initial state) cannot reach the gradient as
    NaN x 0."""
    return seed * 0


@_dependency.defjvp
def _dependency_jvp(primals, tangents):
    zero = primals[0] * 0
    return zero, jnp.zeros_like(zero)


def touch(tree, seed):
    """Every leaf of ``tree`` made to depend on the scalar ``seed`` (adding :func:`_dependency`).

    Give it a carry and a seed that varies along the vmapped batch and depends on the
    differentiated parameters: the batching (vmap) and linearisation (grad) rules of ``lax.scan``
    then find which carry entries are batched / have tangents in one pass over the body instead
    of several, and the nested scans (ticks, physics steps, solver iterations, line search) no
    longer multiply those passes: the values are the same, the trace is shorter."""
    zero = _dependency(seed)

    def one(x):
        x = jnp.asarray(x)
        if jnp.issubdtype(x.dtype, jnp.inexact) or jnp.issubdtype(x.dtype, jnp.integer):
            return x + zero.astype(x.dtype)
        if x.dtype == jnp.bool_:
            return x | (zero > 1)
        return x

    return jax.tree_util.tree_map(one, tree)


STEP_STATE = (
    "time", "qpos", "qvel", "act", "history", "qacc_warmstart", "plugin_state",
    "ctrl", "qfrc_applied", "xfrc_applied", "eq_active", "mocap_pos", "mocap_quat", "userdata",
)  # fmt: skip
"""The fields of ``mjx.Data`` that a physics step reads from the step before it: MuJoCo's integration state
(``mjSTATE_INTEGRATION``: time, physics state, warm start, controls and applied forces, mocap, user data). A step
computes the other fields anew, but for :data:`STALE_ROWS` (tests/test_keep_sound.py checks both on each engine)."""

STALE_ROWS = ("efc__J", "efc__D")
"""MuJoCo Warp's constraint rows (``Data._impl``) that a step reads beyond the rows it writes (its padded products
weigh them by zero): zero in a fresh ``mjx.Data``, they must not hold a diverged step's NaN."""


def keep_sound(new: mjx.Data, sound: Array, old: mjx.Data, whole: bool) -> mjx.Data:
    """``new`` where ``sound`` (() bool, an environment's under vmap), else ``old``'s :data:`STEP_STATE` and zero
    :data:`STALE_ROWS`: a diverged environment steps on from its last sound state. ``whole``: every field of ``old``
    taken instead, the derived ones too (kinematics, contacts), for a caller that reads them before the next step
    (records, contact observation); otherwise the other derived fields stay ``new``'s, which spares the batch a pass
    over the whole of both."""
    if whole:
        return new.where(~sound, old)
    names = {f.name for f in dataclasses.fields(new)}
    kept = {f: jnp.where(sound, getattr(new, f), getattr(old, f)) for f in STEP_STATE if f in names}
    impl = new._impl
    impl_names = {f.name for f in dataclasses.fields(impl)}
    stale = {f: jnp.where(sound, getattr(impl, f), 0) for f in STALE_ROWS if f in impl_names}
    return new.replace(**kept, _impl=impl.replace(**stale)) if stale else new.replace(**kept)


@traced_at_matmul_precision
def start(loop, qpos: Array, batch: int = 1):
    """Initial carry (physics data, loop state, physics_ok) of an MJX backend at ``qpos``;
    ``batch``: the number of environments run together (Warp's contact buffer)."""
    d = physics.device_data(loop.robot.mj_model, loop.backend, loop.cfg.physics, qpos, qpos.dtype, batch)
    return d, loop.init(qpos), jnp.ones((), bool)


@traced_at_matmul_precision
def chunk(
    loop, plant: mjx.Model, gains: Gains, push: Push, carry, k0, n_ticks: int, feedforward: Feedforward | None = None
):
    """Run ``n_ticks`` (static) ticks from tick ``k0`` (traced) on an MJX backend:
    (carry, records with a leading time axis or None). ``feedforward``: torques added to the
    controller's (:class:`wbc_jax.sim.state.Feedforward`; None: none)."""

    split = loop.warp_terms == "step1"  # the terms off the first step's first phase (warp_split)

    def tick(carry, k):
        d, state, ok = carry

        def steps(dd, ctrl, first: int):  # physics steps first..n_sub-1 of tick k, each step's wrenches built in it
            def one(dd, i):
                return physics.step(plant, dd, ctrl, loop.xfrc_at(push, k, i).astype(dd.qpos.dtype)), None

            return jax.lax.scan(one, dd, jnp.arange(first, loop.n_sub))[0]

        if split:
            step1, step2 = warp_split.phases()
            d = step1(plant, d)
            terms = dynamics.terms_from_split(loop.idx, loop.robot.mj_model, d, loop.controller.frames)
            state, ctrl, record = loop.control(gains, state, d.qpos, d.qvel, k, ok, push, feedforward, terms=terms)
            first = step2(plant, d.replace(ctrl=ctrl, xfrc_applied=loop.xfrc_at(push, k, 0).astype(d.qpos.dtype)))
            d_new = steps(first, ctrl, 1)
        else:
            state, ctrl, record = loop.control(gains, state, d.qpos, d.qvel, k, ok, push, feedforward)
            d_new = steps(d, ctrl, 0)
        finite = physics.state_ok(d_new.qpos, d_new.qvel)
        d_new = keep_sound(d_new, finite, d, whole=loop.cfg.record or loop.observes_contacts)
        if loop.cfg.record and loop.backend == "warp":  # no per-environment contact forces there
            nan = jnp.full_like(record.f_meas, jnp.nan)
            record = record.replace(f_meas=nan, Ldot_meas=jnp.full_like(record.Ldot_meas, jnp.nan))
        elif loop.cfg.record or loop.observes_contacts:
            slots = physics.contacts(plant, d_new)
            if loop.cfg.record:
                record = loop.measure(record, *slots)
            if loop.observes_contacts:
                state = loop.observe(state, *slots)
        return (d_new, state, finite), record

    if loop.remat:
        policy = loop.remat
        tick = jax.checkpoint(
            tick, policy=getattr(jax.checkpoint_policies, policy) if isinstance(policy, str) else None
        )
    return jax.lax.scan(tick, carry, k0 + jnp.arange(n_ticks))


def rollout(
    loop,
    plant: mjx.Model,
    qpos0: Array,
    gains: Gains,
    push: Push,
    controller_overrides=None,
    batch: int = 1,
    feedforward: Feedforward | None = None,
):
    """The whole horizon on an MJX backend: (Metrics, records or None). ``plant``: the MJX model
    simulated (:func:`wbc_jax.sim.physics.plant_model` of the nominal one for a perturbed plant).
    ``controller_overrides``: fields of the controller state to replace (regularisation as
    differentiable arrays, gain tuning's gradient check). ``feedforward``: torques added to the
    controller's (None: none)."""
    d, state, ok = start(loop, qpos0, batch)
    if controller_overrides:
        state = state.replace(controller=state.controller.replace(**controller_overrides))
    carry = (d, state, ok)
    (d, state, ok), records = chunk(loop, plant, gains, push, carry, 0, loop.n_ticks, feedforward)
    return metrics_lib.final(state.metrics, ok), records


@traced_at_matmul_precision
def rollout_queue(
    loop, plant_of: Callable, qpos0: Array, scens: Scenario, slot: Array, segment: int, axis_name: str, batch: int = 1
):
    """One of S batch slots (``jax.vmap`` over ``slot`` with ``axis_name``) working through a
    shared queue of N scenarios on an MJX backend; returns the N scenarios' Metrics.

    Slot s starts scenario s. Each scenario runs until it has fallen or diverged (its outcome
    is then decided: neither upright nor survived) or reaches the horizon; every ``segment``
    ticks (static, a divisor of the horizon's) the slots whose scenario is decided hand in its
    metrics and take the next pending scenarios in slot order, so the batch stops paying
    solver iterations for robots on the floor. The loop runs until the queue is empty, with
    one predicate for all slots (a per-slot predicate would make JAX merge the loop's carry
    leaf by leaf, which Warp's batch-shared contact buffer does not allow). Each slot keeps its
    own tick, so the tick is batched under vmap and a branch on the time runs both sides: the
    force distribution's contact-ramp branch (:func:`wbc_jax.control.forces.distribute`) stays a
    branch only because a contact that never ramps has a constant activation
    (:func:`wbc_jax.robot.contacts.activation_at`; BENCHMARKS.md).

    Args:
      plant_of: Scenario -> MJX model simulated (the nominal one, or perturbed).
      qpos0: (nq,) nominal initial posture.
      scens: the queue, Scenario with a leading axis N (the same for every slot).
      slot: () this slot's index s < N (the vmapped argument).
      segment: ticks between hand-ins.
      axis_name: the vmap axis of the slots.
      batch: environments run together (Warp's contact buffer).

    Returns:
      Metrics with a leading axis N, not mapped over the slots (``out_axes=None``). A retired
      environment's metrics cover its ticks up to the hand-in (``ticks``); the others equal
      :meth:`rollout`'s.
    """
    if loop.n_ticks % segment:
        raise ValueError(f"segment {segment} must divide the horizon's {loop.n_ticks} ticks")
    N = int(jax.tree_util.tree_leaves(scens)[0].shape[0])
    pick = lambda i: jax.tree_util.tree_map(lambda x: x[jnp.minimum(i, N - 1)], scens)  # noqa: E731

    def fresh(i):
        return start(loop, loop.initial_qpos(qpos0, pick(i).joint_offset), batch)

    def select(decided, new, old):
        d = old[0].where(decided, new[0])  # Data.where: Warp's batch-shared buffers stay whole
        rest = jax.tree_util.tree_map(lambda a, b: jnp.where(decided, a, b), new[1:], old[1:])
        return (d, *rest)

    carry = fresh(slot)
    outcome = metrics_lib.final(carry[1].metrics, carry[2])
    out = jax.tree_util.tree_map(lambda x: jnp.zeros((N, *x.shape), x.dtype), outcome)
    gather = lambda x: jax.lax.all_gather(x, axis_name)  # noqa: E731  (S, ...) the same in every slot

    def body(loop_state):
        idx, k, carry, out, next_free = loop_state
        s = pick(idx)
        carry, _ = chunk(loop, plant_of(s), s.gains, s.push, carry, k, segment)
        k = k + segment
        met = metrics_lib.final(carry[1].metrics, carry[2])
        decided = (met.fell | met.nan | (k >= loop.n_ticks)) & (idx < N)
        flags = gather(decided)
        rows = jnp.where(flags, gather(idx), N)  # N: out of bounds, dropped
        out = jax.tree_util.tree_map(lambda o, m: o.at[rows].set(m, mode="drop"), out, gather(met))
        counts = flags.astype(jnp.int32)
        rank = (jnp.cumsum(counts, dtype=jnp.int32) - counts)[jax.lax.axis_index(axis_name)]
        new_idx = jnp.where(decided, next_free + rank, idx)
        carry = select(decided & (new_idx < N), fresh(new_idx), carry)
        return new_idx, jnp.where(decided, 0, k), carry, out, next_free + jnp.sum(counts, dtype=jnp.int32)

    def pending(loop_state):
        return jnp.any(gather(loop_state[0]) < N)

    S = jax.lax.psum(1, axis_name)
    first = (jnp.asarray(slot, jnp.int32), jnp.zeros((), jnp.int32), carry, out, jnp.asarray(S, jnp.int32))
    return jax.lax.while_loop(pending, body, first)[3]
