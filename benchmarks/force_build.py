"""The force distribution's pieces, each alone, on one core (issue 46): where the QP's build goes.

    taskset -c 0 python benchmarks/force_build.py --out runs/force_build.json [--ticks 1000] [--before REF]

The inputs are the 20 s sinusoid's own (those of the tick's force distribution,
:func:`controller_stages.stage_prefix`), computed once; then each piece runs alone in a
``lax.scan`` over them: the whole distribution (cold start), the engaged contacts' equality QP
with its violation checks, its build without the solve, the null space and its basis, the
constraint rows, a contact violation check and the solve alone on the built QPs. CPU microseconds
per tick (the median and range of ``--repeats``, programs interleaved) and XLA's op counts of
each program (fusions, dots, library calls, while loops). One thread of XLA's CPU pool.
``--before REF``: the same pieces of commit REF's package (those it has), interleaved with these.
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

ROOT = pathlib.Path(__file__).resolve().parent.parent


def distribute_inputs(ticks: int):
    """``(static, stacked, st)``: the force distribution's static arguments ``(cset, settings)``,
    its array arguments ``(activation, A, wrench, tt, W_R)`` stacked over the sinusoid's ticks."""
    import jax
    import jax.numpy as jnp
    from controller_stages import sinusoid_states, stage_prefix

    qpos, qvel, _ = sinusoid_states(ticks)
    prefix, st, _ = stage_prefix(ticks)
    cset, *_, settings = prefix(5, jnp.asarray(qpos[0], st.dtype), jnp.asarray(qvel[0], st.dtype), 0, True)

    def arrays(q, v, k):
        _, activation, A, wrench, tt, W_R, _ = prefix(5, q, v, k, True)
        return activation, A, wrench, tt, W_R

    ks = jnp.arange(ticks, dtype=jnp.int32)
    with jax.default_matmul_precision(st.loop.cfg.matmul_precision):
        stacked = jax.jit(jax.vmap(arrays))(jnp.asarray(qpos, st.dtype), jnp.asarray(qvel, st.dtype), ks)
    return (cset, settings), stacked, st


def pieces(cset, settings, pkg: str = "wbc_jax") -> dict:
    """name -> ``fn(activation, A, wrench, tt, W_R) -> pytree``: the pieces timed, of the package
    ``pkg`` (this checkout's or another commit's, :func:`controller_stages.import_commit`; a piece
    whose function the package lacks is left out)."""
    import jax.numpy as jnp

    constraints = importlib.import_module(f"{pkg}.control.constraints")
    forces = importlib.import_module(f"{pkg}.control.forces")

    def ones(A):
        return jnp.ones(len(cset.contacts), A.dtype)

    named = {
        "distribute (cold)": lambda a, A, w, tt, R: forces.distribute(cset, a, A, w, tt, R, settings)[:2],
        "wbc_qp (equality QP + checks)": lambda a, A, w, tt, R: forces.wbc_qp(cset, ones(A), A, w, tt, R, settings)[:2],
        "equality QP": lambda a, A, w, tt, R: forces.momentum_equality_qp(cset, ones(A), A, w, tt, R, settings)[0],
        "constraint rows": lambda a, A, w, tt, R: constraints.constraints(cset, R, ones(A)),
        # Its cost, not its value: the wrenches A' w.
        "contact violation": lambda a, A, w, tt, R: constraints.contact_violation(cset, A.T @ w, R, ones(A)),
    }
    if hasattr(forces, "equality_qp_data"):
        named["equality QP's build (no solve)"] = lambda a, A, w, tt, R: forces.equality_qp_data(
            cset, ones(A), A, w, tt, R, settings
        )
        named["null space and basis"] = lambda a, A, w, tt, R: forces.null_space(cset, A, ones(A), w)[:2]
    return named


def scanned(fn, dtype):
    """``fn`` over the stacked ticks in a ``lax.scan``; every output summed (so none is dropped)."""
    import jax
    import jax.numpy as jnp

    def run(stacked):
        def tick(acc, x):
            out = fn(*x)
            return acc + sum(jnp.sum(jnp.asarray(leaf, dtype)) for leaf in jax.tree_util.tree_leaves(out)), None

        return jax.lax.scan(tick, jnp.zeros((), dtype), stacked)[0]

    return run


def main(argv=None) -> dict:
    from controller_stages import parse_timing_args, result_header, timing_parser

    argv = list(sys.argv[1:] if argv is None else argv)
    p = timing_parser("force_build", __doc__, ticks=1000, repeats=9)
    p.add_argument(
        "--before",
        default=None,
        metavar="REF",
        help="also the pieces of git commit REF's force distribution, interleaved with this checkout's",
    )
    args = parse_timing_args(p, argv)
    import jax
    from controller_stages import import_commit, op_counts

    from wbc_jax.control import qp
    from wbc_jax.control.constraints import row_weights
    from wbc_jax.core import io
    from wbc_jax.sim import runner

    runner.enable_compilation_cache()
    (cset, settings), stacked, st = distribute_inputs(args.ticks)
    packages = {"now": "wbc_jax"}
    if args.before:
        packages[f"before ({args.before})"] = import_commit(args.before)
    named = {
        (variant, name): fn for variant, pkg in packages.items() for name, fn in pieces(cset, settings, pkg).items()
    }
    with jax.default_matmul_precision(st.loop.cfg.matmul_precision):
        built = jax.jit(jax.vmap(named[("now", "equality QP's build (no solve)")]))(*stacked)

        def solve_alone(H, g, C, b):
            return qp.solve_qp(H, g, C, b, iterations=settings.qp_iterations, row_weight=row_weights(cset))[0]

        qp_args = (built.H, built.g, built.C, built.b)
        compiled = {key: jax.jit(scanned(fn, st.dtype)).lower(stacked).compile() for key, fn in named.items()}
        solve_key = ("now", "solve_qp alone (on the built QPs)")
        compiled[solve_key] = jax.jit(scanned(solve_alone, st.dtype)).lower(qp_args).compile()
    data = {key: qp_args if key == solve_key else stacked for key in compiled}
    cpu_us = {name: [] for name in compiled}
    for _ in range(args.repeats):  # interleaved: the machine's load reaches every program alike
        for name, fn in compiled.items():
            t0 = time.process_time()
            jax.block_until_ready(fn(data[name]))
            cpu_us[name].append(1e6 * (time.process_time() - t0) / args.ticks)
    result = {
        **result_header("force_build", argv, args, st.dtype),
        "cpu_us_per_tick": {
            variant: {
                name: {"median": round(statistics.median(v), 1), "range": [round(min(v), 1), round(max(v), 1)]}
                for (var, name), v in cpu_us.items()
                if var == variant
            }
            for variant in packages
        },
        "ops": {
            variant: {name: op_counts(fn) for (var, name), fn in compiled.items() if var == variant}
            for variant in packages
        },
    }
    io.atomic_write_json(pathlib.Path(args.out), result)
    print(json.dumps({k: v for k, v in result.items() if k != "provenance"}, indent=1), flush=True)
    return result


if __name__ == "__main__":
    main()
