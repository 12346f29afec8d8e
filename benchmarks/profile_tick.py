"""Where a control tick's time goes (issue: GPU throughput, "a cheaper controller tick").

    python benchmarks/profile_tick.py --batch 65536 --out runs/profile_tick [--trace DIR]

Times each stage of the controller tick on its own, jitted and vmapped over ``--batch`` states
near the standing posture, on this device: the dynamics terms (kinematics, its derivative, mass
matrix, bias), the contact terms and momentum task, the torque law, the force distribution (the
contact QPs; and its first QP alone, without the soft fallback that vmap runs for every
environment), and the whole tick; then one MJX physics step of the same batch for scale. Each
figure is the fastest of --repeats runs after a warm-up, in microseconds per environment.
``--trace DIR`` also writes a JAX profiler (Perfetto) trace of the whole tick, whose stages carry
``jax.named_scope`` names.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax.control import constraints, forces, torques
from wbc_jax.core import io, provenance
from wbc_jax.robot import contacts
from wbc_jax.sim import physics, runner, scenario
from wbc_jax.sim.state import SimConfig


def timed(fn, *args, repeats: int) -> float:
    jax.block_until_ready(fn(*args))
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        best = min(best, time.perf_counter() - t0)
    return best


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batch", type=int, default=1024)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--backend", default="jax", help="physics backend of the scale step")
    p.add_argument("--out", default="runs/profile_tick")
    p.add_argument("--trace", default=None)
    args = p.parse_args(argv)
    runner.enable_compilation_cache()
    st = scenario.setup("stand", duration=1.0, sim=SimConfig(physics=physics.PhysicsConfig(backend=args.backend)))
    loop, ctrl, dtype, B = st.loop, st.loop.controller, st.dtype, args.batch
    rng = np.random.default_rng(0)
    qpos = np.repeat(st.qpos0[None], B, 0)
    qpos[:, st.robot.index.qpos_joints] += rng.normal(scale=0.02, size=(B, st.robot.index.n))
    qvel = rng.normal(scale=0.05, size=(B, st.robot.index.nv))
    qpos, qvel = jnp.asarray(qpos, dtype), jnp.asarray(qvel, dtype)
    gains = st.gains
    state0 = jax.jit(loop.init)(qpos[0])
    cset, settings = ctrl.contact_set, ctrl.config.force_settings

    def ref_at(t):
        return loop.schedule.at(jnp.asarray(t, dtype), dtype)

    def stage_terms(q, v):
        return loop.terms(q, v)

    def stage_torques(t):
        ref = ref_at(0.5)
        ct = contacts.contact_terms(cset, t, 0.5, ref.activation)
        rows = contacts.row_activation(cset, ct.activation)
        return torques.torque_terms(
            t,
            ct.J * rows[:, None],
            ct.Jdot_nu * rows,
            postural="stable",
            kp_postural=gains.kp_postural,
            kd_postural=gains.kd_postural,
            s_des=ref.s_des,
        )

    def stage_forces(t, tt):
        ref = ref_at(0.5)
        ct = contacts.contact_terms(cset, t, 0.5, ref.activation)
        A = constraints.wrench_map(cset, ct.W_p, t.W_p_CoM)
        w = jnp.asarray([5.0, -3.0, 9.81 * st.robot.index.mass, 0.5, -1.0, 0.2], dtype)
        return forces.distribute(cset, ct.activation, A, w, tt, ct.W_R, settings)[:2]

    def stage_equality_qp(t, tt):  # the distribution's first QP alone, without its soft fallback
        ref = ref_at(0.5)
        ct = contacts.contact_terms(cset, t, 0.5, ref.activation)
        A = constraints.wrench_map(cset, ct.W_p, t.W_p_CoM)
        w = jnp.asarray([5.0, -3.0, 9.81 * st.robot.index.mass, 0.5, -1.0, 0.2], dtype)
        return forces.momentum_equality_qp(cset, jnp.ones_like(ct.activation), A, w, tt, ct.W_R, settings)[0]

    def whole_tick(q, v):
        return ctrl.step(gains, state0.controller, loop.terms(q, v), ref_at(0.5), jnp.asarray(0.5, dtype))[0].tau

    vt = jax.jit(jax.vmap(stage_terms))
    t_batch = vt(qpos, qvel)
    vtt = jax.jit(jax.vmap(stage_torques))
    tt_batch = vtt(t_batch)
    result = {"batch": B, "device": provenance.device_label(), "dtype": str(dtype), "us_per_env": {}}
    us = lambda s: round(1e6 * s / B, 3)  # noqa: E731
    result["us_per_env"]["dynamics_terms"] = us(timed(vt, qpos, qvel, repeats=args.repeats))
    result["us_per_env"]["torque_law"] = us(timed(vtt, t_batch, repeats=args.repeats))
    result["us_per_env"]["force_distribution"] = us(
        timed(jax.jit(jax.vmap(stage_forces)), t_batch, tt_batch, repeats=args.repeats)
    )
    # Under vmap the soft QP (the fallback when the first is infeasible) runs for every
    # environment: the lax.cond on a batched predicate becomes a select. The difference between
    # these two figures is what that costs.
    result["us_per_env"]["force_distribution_first_qp_only"] = us(
        timed(jax.jit(jax.vmap(stage_equality_qp)), t_batch, tt_batch, repeats=args.repeats)
    )
    vw = jax.jit(jax.vmap(whole_tick))
    result["us_per_env"]["whole_tick"] = us(timed(vw, qpos, qvel, repeats=args.repeats))
    # One physics step of the same batch, for scale (a tick holds 10).
    m = physics.device_model(st.robot.mj_model, loop.backend, loop.cfg.physics)
    tau = jnp.zeros(st.robot.mj_model.nu, dtype)
    xfrc = jnp.zeros((st.robot.mj_model.nbody, 6), dtype)

    def ten_steps(q):
        d = physics.device_data(st.robot.mj_model, loop.backend, loop.cfg.physics, q, dtype, batch=B)
        return jax.lax.scan(lambda dd, _: (physics.step(m, dd, tau, xfrc), None), d, None, length=10)[0].qpos

    result["us_per_env"][f"physics_10_steps_{loop.backend}"] = us(
        timed(jax.jit(jax.vmap(ten_steps)), qpos, repeats=args.repeats)
    )
    if args.trace:
        with jax.profiler.trace(args.trace):
            jax.block_until_ready(vw(qpos, qvel))
    result["provenance"] = provenance.record(argv=provenance.script_argv(__file__, argv))
    io.atomic_write_json(pathlib.Path(args.out) / "profile_tick.json", result)
    print(json.dumps(result), flush=True)
    return result


if __name__ == "__main__":
    main()
