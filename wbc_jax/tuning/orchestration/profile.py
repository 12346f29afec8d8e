"""Where a gradient step's time goes (phase ``profile`` of ``wbc-jax tune``, profile.json).

One control tick of the training closed loop at the training batch B (standing robots with the
training's joint noise, the training's solver settings), split into the parts of its forward and
backward passes, each compiled on its own and timed (median of repeats, blocking on the outputs):

* physics: the tick's n_sub MJX steps, with MJX's solver ``while_loop`` (what a forward run, and the
  implicit gradient's forward, does) and as the fixed-iteration scan of the unrolled gradient (every
  Newton and line-search iteration, also after convergence), and the reverse pass (VJP) of each solver
  gradient (``implicit``, ``unrolled``);
* controller: one control tick (dynamics terms, momentum task, the force QP with its implicit
  derivative, torques) and its VJP with respect to the gains and the state;
* a host round trip (a tiny program and the transfer of its result).

The summary estimates a training step from these per-tick parts (T ticks, each recomputed once in the
backward pass with ``--checkpoint tick``) and, when the training phase ran, sets it against the
measured step.
"""

from __future__ import annotations

import json
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax.core import io, provenance
from wbc_jax.sim import physics
from wbc_jax.tuning.algorithms import problem as tp

REPEATS = 5


def _time(fn, *args) -> tuple[float, float]:
    """(compile s, median run s) of a jitted fn."""
    t0 = time.perf_counter()
    compiled = jax.jit(fn).lower(*args).compile()
    compile_s = time.perf_counter() - t0
    jax.block_until_ready(compiled(*args))
    runs = []
    for _ in range(REPEATS):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        runs.append(time.perf_counter() - t0)
    return compile_s, float(np.median(runs))


def measure(problem: tp.Problem, out, *, mesh=None) -> dict:
    """The per-tick timings (module docstring) into ``out/profile.json``."""
    tc, loop, st = problem.tc, problem.loop, problem.setup
    B, dtype = tc.batch, st.dtype
    rng = np.random.default_rng(tc.seed)
    qpos0 = jnp.asarray(st.qpos0, dtype)
    offsets = jnp.asarray(rng.normal(scale=max(tc.joint_noise, 1e-3), size=(B, problem.robot.index.n)), dtype)
    qpos = jax.vmap(lambda o: loop.initial_qpos(qpos0, o))(offsets)
    nominal = physics.device_model(st.robot.mj_model, "jax", loop.cfg.physics)
    d0 = jax.vmap(lambda q: physics.device_data(st.robot.mj_model, "jax", loop.cfg.physics, q, dtype))(qpos)
    controls, reg = tp.controls_cast(problem, problem.init_params())
    state = jax.vmap(loop.init)(qpos)
    push = jax.tree_util.tree_map(
        lambda x: jnp.broadcast_to(x, (B, *jnp.shape(x))),
        tp.sample_pushes(tc, problem.robot, problem.table, tp.batch_rng(tc.seed, 0, 0), 1, dtype)[0].push,
    )
    push = jax.tree_util.tree_map(lambda x: x[:, 0], push)
    k = jnp.int32(0)
    nbody = st.robot.mj_model.nbody

    def phys(d, ctrl):
        xfrc = jnp.zeros((loop.n_sub, nbody, 6), dtype)
        d, _ = jax.lax.scan(lambda dd, x: (physics.step(nominal, dd, ctrl, x), None), d, xfrc)
        return d.qpos, d.qvel

    def control(g, s, q, v, p):
        return loop.control(g, s, q, v, k, jnp.ones((), bool), p)[1]

    ctrl = jax.vmap(control, in_axes=(None, 0, 0, 0, 0))(controls, state, qpos, d0.qvel, push)
    res: dict = {}

    def phys_sum(q, v, c):
        d = d0.replace(qpos=q, qvel=v)
        qq, vv = jax.vmap(phys)(d, c)
        return jnp.sum(qq) + jnp.sum(vv)

    res["physics_forward_while"] = _time(lambda q, v, c: phys_sum(q, v, c), qpos, d0.qvel, ctrl)
    with physics.fixed_iteration_solver(problem.iterations):
        res["physics_forward_fixed"] = _time(lambda q, v, c: phys_sum(q, v, c), qpos, d0.qvel, ctrl)
        res["physics_vjp_unrolled"] = _time(jax.grad(phys_sum, argnums=(0, 1, 2)), qpos, d0.qvel, ctrl)
    with physics.implicit_solver():
        res["physics_vjp_implicit"] = _time(jax.grad(phys_sum, argnums=(0, 1, 2)), qpos, d0.qvel, ctrl)

    def ctrl_sum(g, q, v):
        return jnp.sum(jax.vmap(control, in_axes=(None, 0, 0, 0, 0))(g, state, q, v, push))

    res["controller_forward"] = _time(ctrl_sum, controls, qpos, d0.qvel)
    res["controller_vjp"] = _time(jax.grad(ctrl_sum, argnums=(0, 1, 2)), controls, qpos, d0.qvel)
    tiny = jnp.ones(B, dtype)
    t0 = time.perf_counter()
    for _ in range(20):
        np.asarray(jax.jit(lambda x: x + 1)(tiny))
    host_ms = (time.perf_counter() - t0) / 20 * 1e3
    run = {name: v[1] for name, v in res.items()}
    implicit = tc.solver_gradient == "implicit"
    phys_fwd = run["physics_forward_while" if implicit else "physics_forward_fixed"]
    phys_vjp = run["physics_vjp_implicit" if implicit else "physics_vjp_unrolled"]
    fwd_tick = run["controller_forward"] + phys_fwd
    bwd_tick = run["controller_vjp"] + phys_vjp
    T = loop.n_ticks
    remat = fwd_tick if tc.checkpoint != "none" else 0.0
    estimate = T * (fwd_tick + remat + bwd_tick)
    summary = {
        "batch": B,
        "ticks": T,
        "n_sub": loop.n_sub,
        "solver_iterations": problem.iterations,
        "per_tick_ms": {name: round(v * 1e3, 3) for name, v in run.items()},
        "fixed_over_while_loop": run["physics_forward_fixed"] / run["physics_forward_while"],
        "unrolled_over_implicit_vjp": run["physics_vjp_unrolled"] / run["physics_vjp_implicit"],
        "solver_gradient": tc.solver_gradient,
        "share_of_estimated_step": {
            "controller_forward": T * run["controller_forward"] / estimate,
            "physics_forward": T * phys_fwd / estimate,
            "rematerialisation": T * remat / estimate,
            "controller_vjp": T * run["controller_vjp"] / estimate,
            "physics_vjp": T * phys_vjp / estimate,
        },
        "estimated_step_s": estimate,
        "host_round_trip_ms": round(host_ms, 3),
        "forward_physics_steps_per_s_while": B
        * loop.n_sub
        / (run["controller_forward"] + run["physics_forward_while"]),
    }
    info_path = pathlib.Path(out) / "gradient" / "train_info.json"
    if info_path.exists():
        info = json.loads(info_path.read_text())
        if info.get("step_s_median") and info.get("batch") == B:
            summary["measured_step_s"] = info["step_s_median"]
            summary["measured_over_estimated"] = info["step_s_median"] / estimate
    result = {
        "summary": summary,
        "compile_s": {name: round(v[0], 1) for name, v in res.items()},
        "device": provenance.device_label(),
        "provenance": provenance.record(tc.input_files),
    }
    io.atomic_write_json(pathlib.Path(out) / "profile.json", result)
    return result
