"""One worker process per core (:func:`run_parallel`), and the baseline on the benchmark's scenario
(:func:`benchmark`)."""

from __future__ import annotations

import os
import pathlib
import sys
import time

import mujoco
import numpy as np

from .loop import simulate, summary_columns
from .spec import BaselineSpec
from .tasks import gains_to_numpy, make_spec, push_to_numpy

WORKER_RUN_NAME = "__wbc_baseline_cpu_worker__"  # the run name of worker.py in a worker process
WORKER_SCRIPT = pathlib.Path(__file__).resolve().parent / "worker.py"
_THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS")


def worker_main(job: dict, conn, start_event) -> None:
    """Body of a worker (runs in the child: worker.py, executed by runpy, calls it)."""
    import traceback

    try:
        t_ready = time.monotonic()
        spec = BaselineSpec(**job["spec"])
        info = {"worker": job["worker"], "jax_imported": "jax" in sys.modules, "startup_s": t_ready - job["t_launch"]}
        conn.send(("ready", info))
        if not start_event.wait(job["timeout"]):
            raise TimeoutError("start signal never came")
        t0 = time.monotonic()
        res = simulate(
            spec,
            job["gains"],
            job["push"],
            n_envs=job["n_envs"],
            record=job["record"],
            timing=True,
            n_ticks=job["n_ticks"],
        )
        t1 = time.monotonic()
        res.update(info, t_start=t0, t_end=t1, sim_wall_s=t1 - t0)
        conn.send(("ok", res))
    except BaseException:
        conn.send(("error", traceback.format_exc()))
    finally:
        conn.close()


def _collect(procs, conns, expected: str, deadline: float, timeout: float) -> list:
    """One message of kind ``expected`` from every worker before ``deadline`` (monotonic)."""
    out: list = [None] * len(procs)
    pending = set(range(len(procs)))
    while pending:
        for w in sorted(pending):
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise TimeoutError(
                    f"run_parallel: workers {sorted(pending)} did not answer ({expected!r}) "
                    f"within the {timeout} s timeout; terminated"
                )
            if conns[w].poll(min(0.02, remaining)):
                status, payload = conns[w].recv()
                if status == "error":
                    raise RuntimeError(f"run_parallel: worker {w} failed:\n{payload}")
                if status != expected:
                    raise RuntimeError(f"run_parallel: worker {w} sent {status!r}")
                out[w] = payload
                pending.discard(w)
            elif not procs[w].is_alive() and not conns[w].poll(0):
                raise RuntimeError(f"run_parallel: worker {w} died (exit code {procs[w].exitcode})")
    return out


def run_parallel(
    n_envs: int,
    n_workers: int | None = None,
    *,
    spec: BaselineSpec | None = None,
    task: str = "stand",
    duration: float | None = 1.0,
    forces: str = "qp",
    postural: str = "stable",
    gains=None,
    push=None,
    n_ticks: int | None = None,
    record: bool = False,
    timeout: float = 600.0,
) -> dict:
    """Simulate ``n_envs`` environments split over ``n_workers`` processes (default: one per core).

    Each worker simulates its share with :func:`simulate` (its environments batched in the
    NumPy controller, one BLAS thread); the workers start simulating together once all have
    started up, and ``wall_s`` is the simulation phase, from the first start to the last end.
    Workers run worker.py through runpy and import only numpy/mujoco/quadprog, but ``spawn``
    re-imports the parent's ``__main__`` script in each: a driver script that imports JAX at
    its top costs every worker ~3 s of start-up (``workers[i]["jax_imported"]`` says so;
    start-up is excluded from ``wall_s``).

    Args:
      spec: task spec; None: built with :func:`make_spec` from task/duration/forces/postural.
      gains, push: batched (n_envs leading axis) or shared, as in :func:`simulate`.
      timeout: seconds for the whole run; on expiry the workers are terminated and
        TimeoutError is raised (a crashed worker raises RuntimeError with its traceback).

    Returns:
      dict: wall_s, total_wall_s (with process start-up), physics_steps, steps_per_s,
      steps_per_s_per_worker, timing (worker 0: controller_us_per_env_tick,
      physics_us_per_mj_step, ...), workers (per-worker start-up, wall, jax_imported),
      metrics (concatenated, (n_envs,) each), and com (n_envs, T, 3) when ``record``.
    """
    import multiprocessing as mp
    import runpy

    t_launch_wall = time.monotonic()
    if spec is None:
        spec, _ = make_spec(task, duration=duration, forces=forces, postural=postural)
    n_workers = int(n_workers or os.cpu_count() or 1)
    if n_envs < 1 or n_workers < 1:
        raise ValueError(f"n_envs and n_workers must be >= 1, got {n_envs}, {n_workers}")
    n_workers = min(n_workers, n_envs)
    g = gains_to_numpy(gains, n_envs, spec.n)
    pu = push_to_numpy(push, n_envs)
    shares = np.array_split(np.arange(n_envs), n_workers)
    ctx = mp.get_context("spawn")
    start_event = ctx.Event()
    spec_dict = spec.to_dict()
    # The whole run's deadline starts before the first launch: each worker's own wait for the start signal (the same
    # timeout) starts at its launch, so a deadline taken after the launches (slow on a loaded machine) let a worker
    # give up first and report an error where the timeout was due.
    deadline = time.monotonic() + timeout
    procs, conns = [], []
    # One BLAS thread per worker (set before the children import numpy).
    old_env = {k: os.environ.get(k) for k in _THREAD_ENV}
    try:
        os.environ.update({k: "1" for k in _THREAD_ENV})
        for w, share in enumerate(shares):
            job = {
                "worker": w,
                "spec": spec_dict,
                "n_envs": len(share),
                "gains": {k: v[share] for k, v in g.items()},
                "push": {k: v[share] for k, v in pu.items()},
                "record": record,
                "n_ticks": n_ticks,
                "timeout": timeout,
                "t_launch": time.monotonic(),
            }
            parent_conn, child_conn = ctx.Pipe(duplex=False)
            p = ctx.Process(
                target=runpy.run_path,
                args=(str(WORKER_SCRIPT),),
                kwargs={
                    "run_name": WORKER_RUN_NAME,
                    "init_globals": {"_WORKER_JOB": job, "_WORKER_CONN": child_conn, "_WORKER_START": start_event},
                },
                daemon=True,
            )
            p.start()
            child_conn.close()
            procs.append(p)
            conns.append(parent_conn)
    finally:
        for k, v in old_env.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    results: list = [None] * len(procs)
    ok = False
    try:
        _collect(procs, conns, "ready", deadline, timeout)  # every worker started up...
        start_event.set()  # ...then all start simulating together
        results = _collect(procs, conns, "ok", deadline, timeout)
        ok = True
    finally:
        for p in procs:  # only the processes started here, by handle
            p.join(timeout=5.0 if ok else 0.1)
            if p.is_alive():
                p.terminate()
                p.join(timeout=5.0)
        for c in conns:
            c.close()
    total_wall = time.monotonic() - t_launch_wall
    wall = max(r["t_end"] for r in results) - min(r["t_start"] for r in results)
    steps = sum(r["physics_steps"] for r in results)
    out = {
        "n_envs": n_envs,
        "n_workers": len(procs),
        "n_ticks": results[0]["n_ticks"],
        "wall_s": wall,
        "total_wall_s": total_wall,
        "physics_steps": steps,
        "steps_per_s": steps / wall if wall > 0 else float("nan"),
        "steps_per_s_per_worker": [r["physics_steps"] / r["sim_wall_s"] for r in results],
        "timing": results[0]["timing"],
        "workers": [
            {k: r[k] for k in ("worker", "n_envs", "startup_s", "sim_wall_s", "jax_imported", "timing")}
            for r in results
        ],
        "metrics": {k: np.concatenate([r["metrics"][k] for r in results]) for k in results[0]["metrics"]},
    }
    if record:
        out["com"] = np.concatenate([r["com"] for r in results])
    return out


def benchmark(
    n_envs: int = 64,
    n_workers: int | None = None,
    horizon: float = 1.0,
    *,
    magnitude: float = 40.0,
    push_onset: float = 0.2,
    push_duration: float = 0.1,
    solver_iterations: int | None = None,
    timeout: float = 1800.0,
) -> dict:
    """The CPU baseline on the scenario of benchmarks/benchmark.py (JSON-ready dict).

    Stand task over ``horizon`` s, default gains, one ``magnitude`` N horizontal push on the
    chest per environment, azimuths spread evenly over 360 deg (sweep.build_scenarios with one
    magnitude), at ``push_onset`` for ``push_duration`` s; ``n_workers`` processes (default:
    one per core)."""
    import platform

    spec, gains = make_spec("stand", duration=horizon, solver_iterations=solver_iterations)
    azimuth = np.deg2rad(np.linspace(0.0, 360.0, n_envs, endpoint=False))
    force = magnitude * np.stack([np.cos(azimuth), np.sin(azimuth), np.zeros(n_envs)], 1)
    push = {
        "force": force[:, None, :],
        "onset": np.full((n_envs, 1), push_onset),
        "duration": np.full((n_envs, 1), push_duration),
    }
    r = run_parallel(n_envs, n_workers, spec=spec, gains=gains, push=push, timeout=timeout)
    cols = summary_columns(r["metrics"], push_onset + push_duration)
    t0 = r["timing"]
    return {
        "baseline": "C MuJoCo mj_step + NumPy controller (quadprog), one process per worker",
        "cpu": cpu_name(),
        "cpu_count": os.cpu_count(),
        "mujoco": mujoco.__version__,
        "numpy": np.__version__,
        "python": platform.python_version(),
        "batch": n_envs,
        "n_workers": r["n_workers"],
        "envs_per_worker": [w["n_envs"] for w in r["workers"]],
        "solver_iterations": int(spec.mj_model.opt.iterations),
        "horizon_s": horizon,
        "run_s": round(r["wall_s"], 4),
        "total_s_with_startup": round(r["total_wall_s"], 3),
        "physics_steps_per_s": r["steps_per_s"],
        "physics_steps_per_s_per_worker": r["steps_per_s_per_worker"],
        "control_ticks_per_s": r["steps_per_s"] / spec.n_sub,
        "worker0_controller_us_per_env_tick": t0["controller_us_per_env_tick"],
        "worker0_mj_step_us": t0["physics_us_per_mj_step"],
        "worker0_controller_share": t0["controller_s"] / t0["loop_s"],
        "worker_startup_s": [w["startup_s"] for w in r["workers"]],
        "workers_imported_jax": [w["jax_imported"] for w in r["workers"]],
        # Names of constants.METRIC_NAMES: the rates of its booleans, medians of the others.
        "survived_rate": float(np.mean(cols["survived"])),
        "upright_rate": float(np.mean(cols["upright"])),
        "com_max_err_m_median": float(np.median(cols["com_max_err_m"])),
        "max_abs_torque_nm_median": float(np.median(cols["max_abs_torque_nm"])),
        "qp_infeasible_ticks_total": int(np.sum(cols["qp_infeasible_ticks"])),
    }


def cpu_name() -> str:
    """The host CPU's model name (Linux /proc/cpuinfo; else platform)."""
    import platform

    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()
