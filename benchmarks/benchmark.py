"""Closed-loop throughput of wbc_jax (MJX + controller) vs the CPU baseline, in one run.

    python experiments/benchmark.py --out runs/bench [--batches 1 256 1024 4096 16384]
        [--horizon 1.0] [--iterations 4 2 1] [--cpu-baseline-envs 64]

For each batch size: compile time, closed-loop physics steps/s and control ticks/s
(controller included, 1 kHz physics, 100 Hz control), peak device memory per environment, and
the share of time spent in the controller (closed loop vs the same physics with the torques
held fixed). For each solver iteration count: the standing/push balance figures at a small
batch, to see which settings keep them. Then the CPU baseline (C MuJoCo + the NumPy controller,
one worker per core) on the same task. Writes bench.json into --out.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import sys
import time

ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from mujoco import mjx  # noqa: E402

from wbc_jax import io, sweep  # noqa: E402
from wbc_jax import model as model_lib  # noqa: E402


def scenario_batch(batch: int, horizon: float, seed: int = 0, onset: float = 0.2, duration: float = 0.1):
    """Lateral/sagittal pushes of moderate size (all survivable), batch of `batch`."""
    cfg = sweep.SweepConfig(
        magnitudes=(40.0,), directions=tuple(np.linspace(0, 360, max(batch, 1), endpoint=False)),
        horizon=horizon, push_onset=onset, push_duration=duration, chunk_size=batch, seed=seed,
    )  # fmt: skip
    return cfg


def peak_memory() -> float | None:
    stats = jax.devices()[0].memory_stats() or {}
    return stats.get("peak_bytes_in_use")


def time_closed_loop(robot, batch: int, horizon: float, iterations: int | None, **push):
    cfg = scenario_batch(batch, horizon, **push)
    cfg = sweep.SweepConfig(**{**cfg.__dict__, "solver_iterations": iterations})
    scen, _ = sweep.build_scenarios(cfg, __import__("wbc_jax.controller").controller.default_gains(), robot.index.n)
    runner, rollout = sweep.make_batched_runner(robot, cfg)
    mesh = sweep.device_mesh()
    sharded, _ = sweep._shard(scen, mesh, cfg.size)
    t0 = time.perf_counter()
    compiled = runner.lower(sharded).compile()
    compile_s = time.perf_counter() - t0
    jax.block_until_ready(compiled(sharded))  # warm
    t0 = time.perf_counter()
    metrics = compiled(sharded)
    jax.block_until_ready(metrics)
    run_s = time.perf_counter() - t0
    steps = cfg.size * rollout.n_ticks * rollout.n_sub
    survived = float(np.mean(~np.asarray(metrics.fell) & ~np.asarray(metrics.nan)))
    return {
        "batch": cfg.size, "solver_iterations": iterations, "compile_s": round(compile_s, 2),
        "run_s": round(run_s, 4), "physics_steps_per_s": steps / run_s,
        "control_ticks_per_s": cfg.size * rollout.n_ticks / run_s,
        "survival": survived,
        "com_max_dev_m_median": float(np.median(np.asarray(metrics.com_max_err))),
    }, (rollout, scen)


def time_physics_only(robot, batch: int, horizon: float, iterations: int | None):
    """Same physics, torques held at gravity compensation: the controller's share."""
    mx = robot.mjx_model
    if iterations is not None:
        mx = mx.replace(opt=mx.opt.replace(iterations=iterations))
    idx = robot.index
    d0 = mjx.make_data(robot.mj_model).replace(qpos=jnp.asarray(robot.home_qpos(), jnp.zeros(()).dtype))
    n_steps = int(round(horizon / robot.mj_model.opt.timestep))

    def env(offset):
        d = d0.replace(qpos=d0.qpos.at[2].add(offset))
        tau = jnp.zeros(idx.nu)

        def step(d, _):
            return mjx.step(mx, d.replace(ctrl=tau)), None

        return jax.lax.scan(step, d, None, length=n_steps)[0].qpos

    fn = jax.jit(jax.vmap(env))
    x = jnp.zeros(batch)
    jax.block_until_ready(fn(x))
    t0 = time.perf_counter()
    jax.block_until_ready(fn(x))
    run_s = time.perf_counter() - t0
    return batch * n_steps / run_s


def equivalence_check(robot, horizon: float = 1.0, iterations: int | None = None) -> dict:
    """Same scenario, both simulators: the MJX closed loop (this device, its dtype) and the C
    MuJoCo + NumPy baseline (float64), stand task with a 40 N lateral chest push at 0.3 s for
    0.1 s. The issue's bar: CoM within 1 mm over 1 s."""
    from wbc_jax import balance, baseline_cpu
    from wbc_jax import rollout as rollout_lib

    sim = {} if iterations is None else {"solver_iterations": int(iterations)}
    rollout, d0, gains, consts, _ = balance.setup(robot, "stand", duration=horizon, sim=sim)
    dtype = d0.qpos.dtype
    push = rollout_lib.Push(force=jnp.array([[0.0, 40.0, 0.0]], dtype),
                            onset=jnp.array([0.3], dtype), duration=jnp.array([0.1], dtype))  # fmt: skip
    _, traj = jax.jit(rollout)(robot.mjx_model, d0, gains, consts, push)
    spec, np_gains = baseline_cpu.make_spec(robot, "stand", duration=horizon, sim=sim)
    base = baseline_cpu.simulate(spec, np_gains, jax.tree_util.tree_map(np.asarray, push))
    com_mjx, com_cpu = np.asarray(traj.com, float), base["com"][0]
    diff = np.linalg.norm(com_mjx - com_cpu, axis=1)
    return {
        "horizon_s": horizon, "mjx_dtype": str(dtype), "solver_iterations": iterations,
        "com_max_diff_m": float(diff.max()),
        "com_excursion_m": float(np.abs(com_cpu - com_cpu[0]).max()),
        "same_within_1mm": bool(diff.max() < 1e-3),
    }  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", default=str(ROOT / "runs" / "bench"))
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 64])
    parser.add_argument("--horizon", type=float, default=1.0)
    parser.add_argument("--iterations", type=int, nargs="+", default=[4])
    parser.add_argument("--cpu-baseline-envs", type=int, default=0,
                        help="environments per CPU worker (0: no CPU baseline)")
    parser.add_argument("--cpu-workers", type=int, nargs="+", default=[os.cpu_count()],
                        help="worker counts to time (scaling over cores); the largest is the baseline")
    parser.add_argument("--push-onset", type=float, default=0.2, help="s (GPU side)")
    parser.add_argument("--push-duration", type=float, default=0.1, help="s (GPU side)")
    parser.add_argument("--skip-physics-only", action="store_true")
    parser.add_argument("--skip-equivalence", action="store_true",
                        help="skip the MJX vs C MuJoCo trajectory check")
    parser.add_argument("--find-largest", type=int, default=0, metavar="K",
                        help="after --batches, up to K doublings of the largest, until one fails")
    args = parser.parse_args()
    out = pathlib.Path(args.out)
    robot = model_lib.load_robot("icub")
    result = {"device": str(jax.devices()[0]), "n_devices": len(jax.devices()),
              "jax": jax.__version__, "date": time.strftime("%Y-%m-%d"), "runs": []}  # fmt: skip
    if not args.skip_equivalence:
        for it in args.iterations:
            eq = equivalence_check(robot, 1.0, it)
            print(json.dumps(eq), flush=True)
            result.setdefault("equivalence", []).append(eq)
            io.atomic_write_json(out / "bench.json", result)
    for it in args.iterations:
        batches = list(args.batches)
        if args.find_largest:  # doublings past the last requested size, until one fails
            batches += [max(args.batches) * 2**k for k in range(1, args.find_largest + 1)]
        for batch in batches:
            try:
                row, _ = time_closed_loop(robot, batch, args.horizon, it, onset=args.push_onset,
                                          duration=args.push_duration)  # fmt: skip
                row["peak_memory_bytes"] = peak_memory()
                row["memory_per_env_bytes"] = (row["peak_memory_bytes"] / batch) if row["peak_memory_bytes"] else None
                if not args.skip_physics_only:
                    phys = time_physics_only(robot, batch, args.horizon, it)
                    row["physics_only_steps_per_s"] = phys
                    row["controller_share"] = 1.0 - row["physics_steps_per_s"] / phys
            except Exception as err:  # out of memory: report the size that failed
                row = {"batch": batch, "solver_iterations": it, "error": repr(err)[:400]}
            print(json.dumps(row), flush=True)
            result["runs"].append(row)
            io.atomic_write_json(out / "bench.json", result)
            if "error" in row and batch > max(args.batches):
                break  # the largest batch that fits is the one before
    if args.cpu_baseline_envs:
        from wbc_jax import baseline_cpu

        # The baseline runs the same solver settings as the GPU side: once per iteration count
        # (the worker scaling only for the first), the ratio per iteration count.
        for k, it in enumerate(args.iterations):
            scaling = []
            for workers in sorted(set(args.cpu_workers)) if k == 0 else [max(args.cpu_workers)]:
                base = baseline_cpu.benchmark(
                    n_envs=args.cpu_baseline_envs * workers, n_workers=workers, horizon=args.horizon,
                    solver_iterations=it,
                )
                base["solver_iterations"] = it
                scaling.append(base)
                print(json.dumps(base), flush=True)
            if k == 0:
                result["cpu_scaling"] = scaling
                result["cpu_baseline"] = base  # the largest worker count
            result.setdefault("cpu_baseline_by_iterations", {})[str(it)] = base
            io.atomic_write_json(out / "bench.json", result)
            ok = [r for r in result["runs"] if "physics_steps_per_s" in r and r["solver_iterations"] == it]
            if ok:
                best = max(ok, key=lambda r: r["physics_steps_per_s"])
                ratio = {
                    "solver_iterations": it, "gpu_batch": best["batch"],
                    "gpu_steps_per_s": best["physics_steps_per_s"], "cpu_workers": base["n_workers"],
                    "cpu_steps_per_s": base["physics_steps_per_s"],
                    "ratio": best["physics_steps_per_s"] / base["physics_steps_per_s"],
                }  # fmt: skip
                if k == 0:
                    result["ratio_gpu_to_cpu"] = ratio
                result.setdefault("ratio_by_iterations", {})[str(it)] = ratio
                print(json.dumps(ratio), flush=True)
                io.atomic_write_json(out / "bench.json", result)


if __name__ == "__main__":
    main()
