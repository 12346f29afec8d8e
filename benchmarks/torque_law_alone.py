"""The torque law alone, on one core: ``torques.torque_terms`` with each postural variant on the
sinusoid's states, its inputs (dynamics and contact terms) computed beforehand (issue 46).

    taskset -c 1 python benchmarks/torque_law_alone.py --out runs/torque_law_alone.json [--before REF]

``benchmarks/controller_stages.py`` charges each stage with what XLA fuses across its seams; here
the law's own cost, without the dynamics terms: a ``lax.scan`` over the ticks of the law alone,
CPU microseconds per tick, median and range of ``--repeats`` runs, ``--before REF``'s law (that
commit's package, :func:`controller_stages.import_commit`) interleaved in the same process, and
XLA's op counts of each program. One thread of XLA's CPU pool (``PJRT_NPROC=1``).
"""

from __future__ import annotations

import os

os.environ.setdefault("PJRT_NPROC", "1")

import importlib
import json
import pathlib
import statistics
import sys
import time

import controller_stages  # this folder's (the script's own on sys.path): the states, a commit's package

ROOT = pathlib.Path(__file__).resolve().parent.parent
POSTURAL = ("seed", "stable")


def law_inputs(st, qs, vs):
    """Per tick (stacked): the dynamics terms, J_c and Jdot_nu_c (rows scaled by the activations)
    and s_des, as the controller hands them to ``torque_terms``."""
    import jax
    import jax.numpy as jnp

    from wbc_jax.robot import contacts

    loop, dtype = st.loop, st.dtype
    cset = loop.controller.contact_set

    def one(q, v, k):
        time_now = k * loop.cfg.control_dt
        t = loop.terms(q, v)
        ref = loop.schedule.at(time_now, dtype)
        ct = contacts.contact_terms(cset, t, time_now, jnp.clip(ref.activation, 0.0, 1.0))
        rows = contacts.row_activation(cset, ct.activation)
        return t, ct.J * rows[:, None], ct.Jdot_nu * rows, ref.s_des

    step = jax.jit(one)
    ticks = [step(qs[k], vs[k], k) for k in range(qs.shape[0])]
    return jax.tree_util.tree_map(lambda *x: jnp.stack(x), *ticks)


def law_program(pkg: str, postural: str, st):
    """``inputs -> ()``: the scan of package ``pkg``'s torque law over the ticks."""
    import jax
    import jax.numpy as jnp

    torques = importlib.import_module(f"{pkg}.control.torques")
    cfg, gains, dtype = st.loop.controller.config, st.gains, st.dtype

    def run(inputs):
        def tick(acc, x):
            t, J_c, Jdot_nu_c, s_des = x
            tt = torques.torque_terms(
                t,
                J_c,
                Jdot_nu_c,
                postural=postural,
                kp_postural=gains.kp_postural,
                kd_postural=gains.kd_postural,
                s_des=s_des,
                pinv_damping=jnp.asarray(cfg.pinv_damping, dtype),
                pinv_tol=cfg.pinv_tol,
                kp_postural_reg=jnp.asarray(cfg.kp_postural_reg, dtype),
                compensate_passive=cfg.compensate_passive,
            )
            return acc + jnp.sum(tt.Sigma) + jnp.sum(tt.tau_model), None

        return jax.lax.scan(tick, jnp.zeros((), dtype), inputs)[0]

    return run


def main(argv=None) -> dict:
    argv = list(sys.argv[1:] if argv is None else argv)
    p = controller_stages.timing_parser("torque_law_alone", __doc__, ticks=300, repeats=11)
    p.add_argument("--before", default=None, metavar="REF", help="also git commit REF's torque law, interleaved")
    args = controller_stages.parse_timing_args(p, argv)
    import jax
    import jax.numpy as jnp

    from wbc_jax.core import io
    from wbc_jax.sim import runner

    packages = {"now": "wbc_jax"}
    if args.before:
        packages[f"before ({args.before})"] = controller_stages.import_commit(args.before)
    runner.enable_compilation_cache()
    qpos, qvel, st = controller_stages.sinusoid_states(args.ticks)
    with jax.default_matmul_precision(st.loop.cfg.matmul_precision):  # as the loop's programs
        inputs = law_inputs(st, jnp.asarray(qpos, st.dtype), jnp.asarray(qvel, st.dtype))
        compiled = {
            (name, postural): jax.jit(law_program(pkg, postural, st)).lower(inputs).compile()
            for name, pkg in packages.items()
            for postural in POSTURAL
        }
    cpu_us = {key: [] for key in compiled}
    for _ in range(args.repeats):  # interleaved: the machine's load reaches every program alike
        for key, program in compiled.items():
            t0 = time.process_time()
            jax.block_until_ready(program(inputs))
            cpu_us[key].append(1e6 * (time.process_time() - t0) / args.ticks)
    result = {
        **controller_stages.result_header("torque_law_alone", argv, args, st.dtype),
        "torque_law_cpu_us_per_tick": {
            f"{name}, {postural}": {
                "median_us": round(statistics.median(times), 1),
                "range_us": [round(min(times), 1), round(max(times), 1)],
                **controller_stages.op_counts(compiled[(name, postural)]),
            }
            for (name, postural), times in cpu_us.items()
        },
    }
    io.atomic_write_json(pathlib.Path(args.out), result)
    print(json.dumps(result), flush=True)
    return result


if __name__ == "__main__":
    main()
