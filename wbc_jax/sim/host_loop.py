"""The closed loop over a horizon on C MuJoCo (``mujoco``): ticks in a Python loop, or one program.

:func:`run_host` picks the driver (``SimConfig.host_loop``): the batch runs the whole horizon as
one compiled program (:mod:`wbc_jax.sim.host_scan`: C MuJoCo called from inside XLA, one
environment after another, the controller's dynamics terms from C MuJoCo); otherwise (no C++
compiler, or ``host_loop="python"``) the jitted, vmapped tick of a
:class:`wbc_jax.sim.loop.ClosedLoop` (its controller and metrics, the same code as on MJX)
alternates with C MuJoCo's ``mj_step`` in threads (:class:`wbc_jax.sim.physics.HostBatch`) in a
Python loop.
"""

from __future__ import annotations

import functools
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax.sim import executables, host_scan, native, physics
from wbc_jax.sim.loop import PROGRAMS
from wbc_jax.sim.state import Feedforward, Scenario


def host_models(loop, scen: Scenario) -> list:
    """The B C models of a batch: the nominal one with the solver settings, or each scenario's
    plant (friction, masses) when ``perturb_plant``."""
    base = physics.solver_mj_model(loop.robot.mj_model, loop.cfg.physics)
    if not loop.cfg.perturb_plant:
        return [base] * int(np.asarray(scen.friction).shape[0])
    return [
        physics.plant_mj_model(base, float(f), float(s)) for f, s in zip(scen.friction, scen.mass_scale, strict=True)
    ]


def driver(loop) -> str:
    """The driver of the loop's batches (any size, with feedforward torques or without): "compiled" (one
    program, :mod:`wbc_jax.sim.host_scan`) or "python" (a Python loop of ticks). ``SimConfig.host_loop``
    "auto" compiles where the native step builds (on the 2-core machine it compiles and runs faster
    than the Python loop, whose threads step a batch's physics on several cores: BENCHMARKS.md,
    "C MuJoCo drivers"); "compiled" asked for where it cannot build is an error."""
    if loop.cfg.host_loop == "python":
        return "python"
    problem = native.available()
    if problem is None:
        return "compiled"
    if loop.cfg.host_loop == "compiled":
        raise ValueError(f"host_loop='compiled' cannot run here: {problem}; use host_loop='python'")
    return "python"


def run_host(
    loop,
    scen: Scenario,
    qpos0: np.ndarray,
    dtype,
    *,
    on_tick=None,
    threads: int | None = None,
    feedforward: Feedforward | None = None,
):
    """Every tick of a batch of B environments on C MuJoCo (``mujoco`` backend).

    One robot runs as one compiled program (:func:`driver`, :mod:`wbc_jax.sim.host_scan`).
    In the Python loop, an even batch of 2 or more without records runs as two halves in a pipeline: while XLA
    computes one half's controller (one core), C MuJoCo steps the other half (the other
    cores), so the controller and the physics overlap; one XLA execution at a time.

    Args:
      scen: Scenario with a leading batch axis B (numpy or JAX arrays).
      qpos0: (nq,) nominal initial posture (each env adds its joint offset).
      dtype: the controller's float dtype.
      on_tick: called with the number of ticks done (progress bars).
      threads: C MuJoCo worker threads (None: all cores, one fewer when pipelined).
      feedforward: torques added to the controller's, with a leading batch axis B
        (:class:`wbc_jax.sim.state.Feedforward`; None: none).

    Returns:
      (Metrics with a batch axis, records with axes (B, T, ...) or None, seconds compiling).
    """
    scen = jax.tree_util.tree_map(np.asarray, scen)
    B = int(scen.friction.shape[0])
    models = host_models(loop, scen)
    qpos = np.asarray(qpos0, float)[None].repeat(B, 0)
    qpos[:, loop.idx.qpos_joints] += scen.joint_offset
    if driver(loop) == "compiled":
        return host_scan.run_scan(loop, scen, models, qpos, dtype, on_tick=on_tick, feedforward=feedforward)
    cast = lambda x: jnp.asarray(x, dtype if np.asarray(x).dtype.kind == "f" else None)  # noqa: E731
    pipelined = B >= 2 and B % 2 == 0 and not (loop.cfg.record or loop.observes_contacts)
    parts = [slice(0, B // 2), slice(B // 2, B)] if pipelined else [slice(0, B)]
    take = lambda tree, part: jax.tree_util.tree_map(lambda x: cast(np.asarray(x)[part]), tree)  # noqa: E731
    gains = [take(scen.gains, part) for part in parts]
    push = [take(scen.push, part) for part in parts]
    ff = [None if feedforward is None else take(feedforward, part) for part in parts]
    fns, compile_s = host_programs(loop, gains[0], cast(qpos[parts[0]]), push[0], ff[0])
    states = [fns["init"](cast(qpos[part])) for part in parts]
    cores = threads or os.cpu_count() or 1
    hosts = [physics.HostBatch(models[part], qpos[part], max(1, cores - 1) if pipelined else cores) for part in parts]
    records = []
    n_con = physics.max_contacts(loop.robot.mj_model)

    def control(h, k):  # dispatched: XLA computes while the caller goes on
        q, v = hosts[h].state()
        return fns["control"](gains[h], states[h], cast(q), cast(v), np.int32(k), ~hosts[h].diverged, push[h], ff[h])

    def physics_tick(h, out):
        states[h], ctrl, record, forces, bodies = out
        hosts[h].step(np.asarray(ctrl, float), host_xfrc(loop, forces, bodies))
        return record

    try:
        if pipelined:
            # C0(k+1) and C1(k) each run beside the other half's physics of tick k.
            out0 = jax.block_until_ready(control(0, 0))
            for k in range(loop.n_ticks):
                out1 = control(1, k)
                physics_tick(0, out0)
                jax.block_until_ready(out1)
                if k + 1 < loop.n_ticks:
                    out0 = control(0, k + 1)
                physics_tick(1, out1)
                if k + 1 < loop.n_ticks:
                    jax.block_until_ready(out0)
                if on_tick is not None:
                    on_tick(k + 1)
        else:
            for k in range(loop.n_ticks):
                record = physics_tick(0, control(0, k))
                if loop.cfg.record or loop.observes_contacts:
                    slots = hosts[0].contacts(n_con)
                    if loop.cfg.record:
                        records.append(fns["measure"](record, *slots))
                    if loop.observes_contacts:
                        states[0] = fns["observe"](states[0], *slots)
                if on_tick is not None:
                    on_tick(k + 1)
    finally:
        for host in hosts:
            host.close()
    diverged = np.concatenate([host.diverged for host in hosts])
    metrics = jax.tree_util.tree_map(
        lambda *xs: np.concatenate([np.asarray(x) for x in xs]), *[state.metrics for state in states]
    )
    metrics = metrics.replace(nan=metrics.nan | diverged)
    if not records:
        return metrics, None, compile_s
    stacked = jax.tree_util.tree_map(lambda *xs: np.stack([np.asarray(x) for x in xs], axis=1), *records)
    return metrics, stacked, compile_s


def host_xfrc(loop, force: np.ndarray, body: np.ndarray) -> np.ndarray:
    """(B, n_sub, nbody, 6) body wrenches from the pushes' forces (B, n_sub, P, 3) on bodies
    (B, P), as :meth:`step_push_forces` / :meth:`push_bodies` computed them in the control step."""
    force, body = np.asarray(force, float), np.asarray(body)
    B, S, P = force.shape[:3]
    out = np.zeros((B, S, loop.robot.mj_model.nbody, 6))
    b_idx = np.broadcast_to(np.arange(B)[:, None, None], (B, S, P))
    s_idx = np.broadcast_to(np.arange(S)[None, :, None], (B, S, P))
    np.add.at(out, (b_idx, s_idx, np.broadcast_to(body[:, None, :], (B, S, P)), slice(0, 3)), force)
    return out


def control_host(loop, gains, state, qpos, qvel, k, physics_ok, push, feedforward=None):
    """:meth:`control` plus the pushes' forces of the tick's physics steps (host loop)."""
    state, ctrl, record = loop.control(gains, state, qpos, qvel, k, physics_ok, push, feedforward)
    return state, ctrl, record, loop.step_push_forces(push, k).astype(ctrl.dtype), loop.push_bodies(push)


def host_programs(loop, gains, qpos, push, ff=None):
    """The compiled, vmapped init, control and measure of the host loop for this batch shape
    (compiled once per loop, shape and feedforward length, kept on disk by :mod:`wbc_jax.sim.executables`):
    (programs, seconds spent compiling or loading them now)."""
    cache = PROGRAMS
    key = ("host", loop.structure_key, qpos.shape, str(qpos.dtype), None if ff is None else ff.torque.shape)
    if key in cache:
        return cache[key], 0.0
    t0 = time.perf_counter()
    B = qpos.shape[0]
    init = jax.jit(jax.vmap(loop.init))
    control = jax.jit(jax.vmap(functools.partial(control_host, loop), in_axes=(0, 0, 0, 0, None, 0, 0, 0)))
    ok = np.ones(B, bool)
    n_con = physics.max_contacts(loop.robot.mj_model)
    slots = (np.zeros((B, n_con, 3)), np.zeros((B, n_con, 3)), np.zeros((B, n_con, 2), np.int64))

    def state():  # traces init: only when a program must be compiled
        return jax.eval_shape(init, qpos)

    def control_args():
        return gains, state(), qpos, qpos[:, : loop.idx.nv], np.int32(0), ok, push, ff

    def compiled(name, args, lower):
        return executables.compiled(f"host_{name}", loop.structure_key, args, lower)

    programs = {
        "init": compiled("init", qpos, lambda: init.lower(qpos)),
        "control": compiled("control", (gains, qpos, push, ff), lambda: control.lower(*control_args())),
    }
    if loop.cfg.record:
        measure = jax.jit(jax.vmap(loop.measure))
        programs["measure"] = compiled(
            "measure",
            (gains, qpos, push, ff, slots),
            lambda: measure.lower(jax.eval_shape(control, *control_args())[2], *slots),
        )
    if loop.observes_contacts:
        observe = jax.jit(jax.vmap(loop.observe))
        programs["observe"] = compiled("observe", (qpos, slots), lambda: observe.lower(state(), *slots))
    cache[key] = programs
    return programs, time.perf_counter() - t0
