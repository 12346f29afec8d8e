"""What the controller's dynamics terms cost, part by part, on one core (issue 46, dyn46).

    taskset -c 1 python benchmarks/dynamics_terms_parts.py --out runs/dynamics_terms_parts.json

On the 20 s sinusoid's own states (``controller_stages.sinusoid_states``), in the loop's dtype,
one thread of XLA's CPU pool: cumulative ``lax.scan`` programs of :func:`wbc_jax.robot.dynamics.terms`'s
pieces, each part's cost its program's time less the previous one's (as ``controller_stages.py``):

1. MJX's kinematics and CoM (``mjx.kinematics``, ``mjx.com_pos``);
2. + the frame Jacobians and the centroidal momentum matrix (``dynamics._kinematics``);
3. + their derivative along the motion (the ``jvp``: Jdot nu);
4. + the mass matrix (``mjx.crb``, ``mjx.full_m``);
5. + ``mjx.com_vel``, ``mjx.passive``, ``mjx.rne`` and the rest of ``terms`` (the whole of it).

And C MuJoCo on the same states, for comparison: ``mj_step1`` (the position and velocity stages,
which compute M, the bias and the passive forces) and ``mj_fullM``, ``mj_jac`` + ``mj_jacDot`` at the
soles (at the body origins), the same per body (the centroidal momentum matrix), each called from
Python (its call overhead, about a microsecond a call, is not subtracted).
"""

from __future__ import annotations

import os

os.environ.setdefault("PJRT_NPROC", "1")

import json
import pathlib
import statistics
import sys
import time

PARTS = (
    "kinematics + com_pos",
    "Jacobians + A_G",
    "jvp (Jdot nu)",
    "crb + full_m (M)",
    "com_vel, passive, rne (h) and the rest",
)


def programs(st):
    """The cumulative part programs (module docstring), each ``(qpos (T, nq), qvel (T, nv)) -> ()``."""
    import jax
    import jax.numpy as jnp

    from wbc_jax.core.mjx import mjx
    from wbc_jax.robot import dynamics

    loop, idx, dtype = st.loop, st.robot.index, st.dtype
    m, d0, frames = loop.mx, loop._d_template, loop.controller.frames

    def part(depth: int, q, v):
        d = d0.replace(qpos=q, qvel=v)
        if depth == 1:
            d = mjx.com_pos(m, mjx.kinematics(m, d))
            return d.xpos, d.xmat, d.subtree_com, d.cdof
        if depth == 2:
            return dynamics._kinematics(m, d, idx, q, frames)[0]
        if depth == 3:
            nu = dynamics.mixed_velocity(idx, q, v)
            kin = lambda x: dynamics._kinematics(m, d, idx, x, frames)[0]  # noqa: E731
            return jax.jvp(kin, (q,), (dynamics.qpos_rate(idx, q, nu),))
        if depth == 4:
            nu = dynamics.mixed_velocity(idx, q, v)
            kin = lambda x: dynamics._kinematics(m, d, idx, x, frames)  # noqa: E731
            (k, dk), (dkin, _) = jax.jvp(kin, (q,), (dynamics.qpos_rate(idx, q, nu),))
            return k, dkin, mjx.full_m(m, mjx.crb(m, dk))
        return loop.terms(q, v)

    def scanned(depth: int):
        def run(qs, vs):
            def tick(acc, x):
                out = part(depth, *x)
                return acc + sum(jnp.sum(jnp.asarray(leaf, dtype)) for leaf in jax.tree_util.tree_leaves(out)), None

            return jax.lax.scan(tick, jnp.zeros((), dtype), (qs, vs))[0]

        return run

    return [scanned(depth) for depth in range(1, len(PARTS) + 1)]


def c_mujoco_us(st, qpos, qvel, repeats: int) -> dict:
    """CPU µs per state of C MuJoCo's pieces, called from Python (median of ``repeats``)."""
    import mujoco
    import numpy as np

    m, idx = st.robot.mj_model, st.robot.index
    d = mujoco.MjData(m)
    M = np.zeros((m.nv, m.nv))
    jp, jr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
    soles = [int(b) for b in idx.foot_bodies]

    def step1():
        mujoco.mj_step1(m, d)

    def full_m():
        mujoco.mj_fullM(m, d, M)

    def soles_jac():
        for b in soles:
            mujoco.mj_jac(m, d, jp, jr, d.xpos[b], b)
            mujoco.mj_jacDot(m, d, jp, jr, d.xpos[b], b)

    def bodies_jac():
        for b in range(1, m.nbody):
            mujoco.mj_jac(m, d, jp, jr, d.xipos[b], b)
            mujoco.mj_jacDot(m, d, jp, jr, d.xipos[b], b)

    out = {}
    names = ("mj_step1", "mj_fullM", "soles: mj_jac + mj_jacDot", "bodies: mj_jac + mj_jacDot (A_G)")
    pieces = dict(zip(names, (step1, full_m, soles_jac, bodies_jac), strict=True))
    out = {name: [] for name in names}
    for _ in range(repeats):
        for name, fn in pieces.items():
            spent = 0.0
            for q, v in zip(qpos, qvel, strict=True):
                d.qpos[:], d.qvel[:] = q, v
                if name != "mj_step1":
                    mujoco.mj_step1(m, d)
                t0 = time.process_time()
                fn()
                spent += time.process_time() - t0
            out[name].append(1e6 * spent / len(qpos))
    return {name: {"median": statistics.median(x), "min": min(x), "max": max(x)} for name, x in out.items()}


def split(cpu_us: list[list[float]]) -> dict:
    """Per part: the median and range over the repeats of its program's time less the previous one's."""
    out = {}
    for i, name in enumerate(PARTS):
        diffs = [c - (cpu_us[i - 1][r] if i else 0.0) for r, c in enumerate(cpu_us[i])]
        out[name] = {
            "median_us": round(statistics.median(diffs), 1),
            "range_us": [round(min(diffs), 1), round(max(diffs), 1)],
        }
    out["all the terms"] = {"median_us": round(statistics.median(cpu_us[-1]), 1)}
    return out


def main(argv=None):
    from controller_stages import parse_timing_args, result_header, timing_parser

    argv = list(sys.argv[1:] if argv is None else argv)
    p = timing_parser("dynamics_terms_parts", __doc__, ticks=300, repeats=5, out_required=True)
    args = parse_timing_args(p, argv)
    import jax
    import jax.numpy as jnp
    from controller_stages import sinusoid_states

    from wbc_jax.core import io
    from wbc_jax.sim import runner

    runner.enable_compilation_cache()
    qpos, qvel, st = sinusoid_states(args.ticks)
    qs, vs = jnp.asarray(qpos, st.dtype), jnp.asarray(qvel, st.dtype)
    with jax.default_matmul_precision(st.loop.cfg.matmul_precision):
        compiled = [jax.jit(fn).lower(qs, vs).compile() for fn in programs(st)]
    cpu_us = [[] for _ in PARTS]
    for _ in range(args.repeats):
        for i, fn in enumerate(compiled):
            t0 = time.process_time()
            jax.block_until_ready(fn(qs, vs))
            cpu_us[i].append(1e6 * (time.process_time() - t0) / args.ticks)
    result = {
        **result_header("dynamics_terms_parts", argv, args, st.dtype),
        "xla_parts_cpu_us_per_tick": split(cpu_us),
        "c_mujoco_cpu_us_per_state": c_mujoco_us(st, qpos, qvel, args.repeats),
    }
    io.atomic_write_json(pathlib.Path(args.out), result)
    print(json.dumps(result, indent=1), flush=True)
    return result


if __name__ == "__main__":
    main()
