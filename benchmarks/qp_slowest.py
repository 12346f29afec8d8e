"""The batch's slowest force QP on the benchmark loop's own states (issue 46, qpmax46).

    taskset -c 0 python benchmarks/qp_slowest.py --out results/cpu_targets/qpmax46 [--loop-envs 256]
        [--pairs default:cold 5e-7:warm ...] [--ticks 15 25 40] [--explain-tick 40] [--one-foot]

Under ``vmap`` the QP's ``lax.while_loop`` runs until the batch's last problem has converged, so a
batch pays its slowest QP. The QPs: benchmarks/benchmark.py's closed loop (profile_tick's
``loop_run_inputs``: the stand task, 0.5 s, ``--loop-envs`` pushes of 40 N at 0.2 s for 0.1 s,
azimuths over 360 deg, MJX-JAX) and every tick's first force QP (the engaged feet's equality QP,
profile_tick's ``first_qp_data``). Per ``--pairs`` entry ``TOL:START`` (TOL a number or ``default``,
:func:`wbc_jax.control.qp.default_tolerances`; START ``cold`` or ``warm``: each environment's QP from
its own last tick's solution, a chain over the ticks as ``ControllerConfig.qp_warm_start``): Newton
steps per tick, mean and max over the batch, at ``--ticks`` (default before, in and after the push)
and over the ticks after the push; the solutions' error against quadprog's (float64 on the same
float32 data), ``max|y - y*| / (1 + max|y*|)``.

Why the slowest need more steps (``explain``): for the cold start's slowest problems at
``--explain-tick``, the rows active at quadprog's solution (cone, torsion, unilateral, cop of a foot)
with their multipliers, the interior point's final slacks and multipliers on those rows (scaled), and
its dual, primal and complementarity residuals after each Newton step (``interior_point`` run for
1, 2, ... steps); the 16 slowest problems of that tick and their tick before, slowest_qps.npz
(tests/test_qp_slowest.py). ``--one-foot``: the one-foot acceptance scenario (C MuJoCo, 16 s) per pair, each
figure against results/balance_acceptance.json (where the loop amplifies the QP's solution error).
"""

from __future__ import annotations

import argparse
import json
import pathlib

ROOT = pathlib.Path(__file__).resolve().parent.parent
START_KINDS = ("cold", "warm")
ROW_KINDS = ("cone", "torsion", "unilateral", "cop")


def parse_pair(text: str) -> tuple[float | None, bool]:
    """``TOL:START`` -> (tol or None for the default, warm)."""
    tol, _, start = text.partition(":")
    if start not in START_KINDS:
        raise ValueError(f"--pairs entry {text!r}: START must be one of {START_KINDS} (TOL:START, e.g. 5e-7:warm)")
    if tol == "default":
        return None, start == "warm"
    try:
        value = float(tol)
    except ValueError:
        value = float("nan")
    if not 0 < value < 1:
        raise ValueError(f"--pairs entry {text!r}: TOL must be 'default' or a number in (0, 1)")
    return value, start == "warm"


def parse_args(argv=None) -> argparse.Namespace:
    from profile_tick import parse_args as profile_args

    from wbc_jax.core import constants

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="runs/qp_slowest")
    p.add_argument("--loop-envs", type=int, default=256, help="environments (pushes) of the recorded loop")
    p.add_argument("--ticks", type=int, nargs="+", default=None, help="ticks reported (default: before, in, after)")
    p.add_argument("--pairs", nargs="+", default=["default:cold", "default:warm", "5e-7:cold", "5e-7:warm"])
    p.add_argument("--explain-tick", type=int, default=None, help="default: the last of --ticks")
    p.add_argument("--explain-count", type=int, default=4, help="the slowest problems explained")
    p.add_argument("--one-foot", action="store_true", help="the one-foot acceptance scenario per pair")
    p.add_argument("--runs", default="runs/qp_slowest_one_foot", help="the one-foot runs' own outputs (trajectories)")
    args = p.parse_args(argv)
    try:
        args.pairs = [parse_pair(t) for t in args.pairs]
    except ValueError as err:
        p.error(str(err))
    if args.loop_envs < 1 or args.explain_count < 1:
        p.error("--loop-envs and --explain-count must be >= 1")
    # profile_tick's loop settings (the benchmark's push) and its check of --ticks against them.
    ticks = [] if args.ticks is None else ["--ticks", *map(str, args.ticks)]
    loop = profile_args(["--loop-envs", str(args.loop_envs), *ticks])
    args.ticks, args.horizon, args.push_onset, args.push_duration = (
        loop.ticks,
        loop.horizon,
        loop.push_onset,
        loop.push_duration,
    )
    args.explain_tick = args.ticks[-1] if args.explain_tick is None else args.explain_tick
    n_ticks = round(args.horizon / constants.CONTROL_DT)
    if not 0 <= args.explain_tick < n_ticks:
        p.error(f"--explain-tick must be a tick of the loop, 0..{n_ticks - 1}")
    return args


def loop_qps(st, args):
    """(H, g, C, b), each (E, T, ...): the first force QP of every tick of the recorded loop."""
    import jax
    import jax.numpy as jnp
    from profile_tick import loop_run_inputs, stage_functions

    fns = stage_functions(st)
    qpos, qvel, state = loop_run_inputs(st, args.loop_envs, args.push_onset, args.push_duration)

    def qp_of(q, v, s, k):
        t = st.loop.terms(q, v)
        Ldot_star = fns["tick"](q, v, s, k).Ldot_star
        tt = fns["torque_law"](t, s, k)
        return fns["first_qp_data"](tt, *fns["force_inputs"](t, k, Ldot_star))

    per_tick = jax.jit(jax.vmap(qp_of, in_axes=(0, 0, 0, None)))
    ticks = [
        per_tick(qpos[:, k], qvel[:, k], jax.tree_util.tree_map(lambda x, k=k: x[:, k], state), jnp.int32(k))
        for k in range(qpos.shape[1])
    ]
    return tuple(jnp.stack(parts, axis=1) for parts in zip(*ticks, strict=True))


def solve_chain(qps, weight, tol: float | None, warm: bool):
    """y (E, T, n) and Newton steps (E, T): solve_qp on every tick, vmapped over the environments;
    warm: each from the same environment's last tick's ``info.start``."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from wbc_jax.control import qp

    H, g, C, b = (jnp.swapaxes(a, 0, 1) for a in qps)  # ticks first, for the scan

    def tick(start, problem):
        def one(H, g, C, b, start):
            return qp.solve_qp(H, g, C, b, tol=tol, row_weight=weight, start=start if warm else None)

        y, info = jax.vmap(one)(*problem, start)
        return info.start, (y, info.iterations)

    start0 = jnp.full((H.shape[1], 2, C.shape[2]), jnp.nan, H.dtype)
    y, steps = jax.jit(lambda *a: jax.lax.scan(tick, start0, a)[1])(H, g, C, b)
    return np.swapaxes(np.asarray(y), 0, 1), np.swapaxes(np.asarray(steps), 0, 1)


def quadprog_solutions(qps):
    """quadprog's (float64) y* (E, T, n) and multipliers (E, T, m); NaN where it finds none."""
    import numpy as np
    import quadprog

    H, g, C, b = (np.asarray(a, np.float64) for a in qps)
    y, lam = np.full(g.shape, np.nan), np.full(b.shape, np.nan)
    for idx in np.ndindex(*g.shape[:2]):
        try:
            Hs = 0.5 * (H[idx] + H[idx].T)
            y[idx], _, _, _, lam[idx], _ = quadprog.solve_qp(Hs, -g[idx], -C[idx].T, -b[idx], 0)
        except ValueError:  # quadprog finds the problem infeasible
            continue
    return y, lam


def row_names(cset) -> list[str]:
    """Each constraint row's contact and kind, e.g. ``r_sole cop``."""
    from wbc_jax.control.constraints import constraint_rows

    names = []
    for c in cset.contacts:
        rows = constraint_rows(c.params, c.type)
        kind = ["cone"] * rows.count
        for name in ROW_KINDS[1:]:
            sl = getattr(rows, name)
            for i in range(rows.count)[sl] if isinstance(sl, slice) else [sl]:
                kind[i] = name
        names += [f"{c.name} {k}" for k in kind]
    return names


def explain(qps, weight, y_ref, lam_ref, steps, tick: int, count: int, names: list[str]) -> list[dict]:
    """The slowest cold problems of ``tick``: active rows, final slacks/multipliers, residuals by step."""
    import jax
    import numpy as np

    from wbc_jax.control.qp_ipm import interior_point

    H, g, C, b = (np.asarray(a[:, tick]) for a in qps)
    H = 0.5 * (H + np.swapaxes(H, 1, 2))
    slowest = np.argsort(-steps[:, tick], kind="stable")[:count]

    def run(k: int):  # k Newton steps whatever the residual (tol 0), every problem of the tick
        def one(*problem):
            res = interior_point(*problem, k, 0.0, weight)
            return res.residual_parts, res.lam, res.s

        return tuple(np.asarray(a) for a in jax.jit(jax.vmap(one))(H, g, C, b))

    most = int(steps[:, tick].max())
    by_step = [run(k)[0][slowest] for k in range(1, most + 1)]
    _, lam, s = run(int(most))
    out = []
    for j, e in enumerate(slowest.tolist()):
        scale = np.max(np.abs(lam_ref[e, tick])) if np.isfinite(lam_ref[e, tick]).all() else np.nan
        active = np.nonzero(lam_ref[e, tick] > 1e-6 * max(scale, 1e-12))[0]
        near = np.argsort(s[e] / np.maximum(np.abs(b[e]), 1.0))[:3]
        out.append(
            {
                "env": e,
                "newton_steps": int(steps[e, tick]),
                "active_rows": [
                    {"row": int(i), "kind": names[i], "multiplier": float(lam_ref[e, tick, i])} for i in active
                ],
                "smallest_slack_rows": [
                    {"row": int(i), "kind": names[i], "slack": float(s[e, i]), "multiplier": float(lam[e, i])}
                    for i in near
                ],
                "residuals_by_step": {
                    part: [float(f"{r[j, p]:.3g}") for r in by_step]
                    for p, part in enumerate(("dual", "primal", "complementarity"))
                },
            }
        )
    return out


def save_slowest(qps, steps, tick: int, path: pathlib.Path, count: int = 16) -> None:
    """The ``count`` slowest cold problems of ``tick`` and the same environments' problems of the
    tick before (the warm start's source), ``H (count, 2, n, n)``, ... (tests/test_qp_slowest.py)."""
    import numpy as np

    slowest = np.argsort(-steps[:, tick], kind="stable")[:count]
    arrays = {k: np.asarray(a)[slowest][:, tick - 1 : tick + 1] for k, a in zip("HgCb", qps, strict=True)}
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, env=slowest, tick=tick, cold_newton_steps=steps[slowest, tick], **arrays)


def one_foot(tol: float | None, warm: bool, runs: pathlib.Path) -> dict:
    """The one-foot acceptance scenario with this pair: figures and their relative change against
    results/balance_acceptance.json."""
    from wbc_jax.control.controller import ControllerConfig
    from wbc_jax.jobs import balance

    key = f"{tol or 'default'}_{'warm' if warm else 'cold'}"
    r = balance.run(
        out=str(runs / key),
        progress=False,
        controller=ControllerConfig(qp_tol=tol),
        qp_warm_start=warm,
        task="one-foot",
        duration=16.0,
    )
    committed = json.loads((ROOT / "results" / "balance_acceptance.json").read_text())["one-foot"]
    figures = [k for k, v in committed.items() if isinstance(v, float) and not k.endswith("_s") and k in r]
    figures = [k for k in figures if k != "real_time_factor"]
    return {
        "figures": {k: r[k] for k in figures},
        "relative_to_committed": {k: float(f"{abs(r[k] - committed[k]) / abs(committed[k]):.3g}") for k in figures},
    }


def main(argv=None) -> dict:
    args = parse_args(argv)  # bad flags refused before anything compiles
    import jax
    from loop_timing import make_setup

    from wbc_jax.sim import runner

    runner.enable_compilation_cache()
    st = make_setup("jax", args.horizon, None)  # the recorded loop cold, as benchmark.py's default
    # The loop's matmul precision, as its own programs are traced (profile_tick.staged: a GPU's default is TF32).
    with jax.default_matmul_precision(st.loop.cfg.matmul_precision):
        result = measure(st, args, argv)
    print(json.dumps({k: v for k, v in result.items() if k != "provenance"}), flush=True)
    return result


def measure(st, args, argv) -> dict:
    """qp_slowest.json's figures (module docstring) on ``st``'s recorded loop; writes it and slowest_qps.npz."""
    import numpy as np

    from wbc_jax.control.constraints import row_weights
    from wbc_jax.core import constants, io, provenance

    cset = st.loop.controller.contact_set
    qps = loop_qps(st, args)
    weight = row_weights(cset)
    y_ref, lam_ref = quadprog_solutions(qps)
    after = slice(round((args.push_onset + args.push_duration) / constants.CONTROL_DT) + 1, qps[1].shape[1])
    pairs, steps_cold = {}, None
    for tol, warm in args.pairs:
        y, steps = solve_chain(qps, weight, tol, warm)
        err = np.max(np.abs(y - y_ref), axis=-1) / (1.0 + np.max(np.abs(y_ref), axis=-1))
        key = f"{tol or 'default'}:{'warm' if warm else 'cold'}"
        if tol is None and not warm:
            steps_cold = steps
        pairs[key] = {
            "newton_steps": {
                **{
                    f"tick_{k}": {"mean": round(float(steps[:, k].mean()), 2), "max": int(steps[:, k].max())}
                    for k in args.ticks
                },
                "after_push": {
                    "ticks": [after.start, after.stop - 1],
                    "batch_max_mean_over_ticks": round(float(steps[:, after].max(axis=0).mean()), 2),
                    "max": int(steps[:, after].max()),
                    "mean": round(float(steps[:, after].mean()), 2),
                },
            },
            "error_vs_quadprog": {
                q: float(f"{np.nanpercentile(err, p):.3g}") for q, p in (("median", 50), ("p99", 99), ("max", 100))
            },
        }
        if args.one_foot:
            pairs[key]["one_foot"] = one_foot(tol, warm, pathlib.Path(args.runs))
        print(key, json.dumps(pairs[key]), flush=True)
    if steps_cold is None:
        steps_cold = solve_chain(qps, weight, None, False)[1]
    result = {
        "loop": {
            "envs": args.loop_envs,
            "horizon_s": args.horizon,
            "push_onset_s": args.push_onset,
            "push_duration_s": args.push_duration,
        },
        "dtype": str(st.dtype),
        "matmul_precision": st.loop.cfg.matmul_precision,
        "qp_size": {"n": int(qps[1].shape[-1]), "m": int(qps[3].shape[-1])},
        "active_rows_at_quadprog_solution": {
            f"tick_{k}": np.bincount(
                np.sum(lam_ref[:, k] > 1e-6 * np.nanmax(lam_ref[:, k], axis=1, keepdims=True).clip(1e-12), axis=1)
            ).tolist()
            for k in args.ticks
        },
        "pairs": pairs,
        "explain": {
            "tick": args.explain_tick,
            "cold_newton_steps_histogram": np.bincount(steps_cold[:, args.explain_tick]).tolist(),
            "slowest": explain(
                qps, weight, y_ref, lam_ref, steps_cold, args.explain_tick, args.explain_count, row_names(cset)
            ),
        },
        "provenance": provenance.record(argv=provenance.script_argv(__file__, argv)),
    }
    io.atomic_write_json(pathlib.Path(args.out) / "qp_slowest.json", result)
    save_slowest(qps, steps_cold, args.explain_tick, pathlib.Path(args.out) / "slowest_qps.npz")
    return result


if __name__ == "__main__":
    main()
