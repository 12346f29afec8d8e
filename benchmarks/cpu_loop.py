"""The one-robot CPU targets (issue 36): where a tick's time goes, the compiled loop, re-runs.

    python benchmarks/cpu_loop.py --out results/cpu_loop.json [--parts profile sinusoid rerun notebook]

* ``profile`` (in this process): the 20 s sinusoid's ticks on C MuJoCo, trajectories recorded (what
  ``wbc-jax balance`` runs), split by where the time goes: in the Python loop of ticks
  (``--host-loop python``: reading the state, the controller's call and its XLA time, the pushes'
  wrenches, C MuJoCo's steps, the contact slots, the measured wrenches, and the Python between
  them), in the compiled loop (one XLA program; C MuJoCo's steps timed inside it by the native
  step, ``mj_step1`` and ``mj_step2`` as physics; the dynamics terms it reads out of C MuJoCo for
  the controller are part of the rest, and shown apart) and the controller's tick alone in a
  ``lax.scan`` (no physics, no calls between ticks; its dynamics terms computed in XLA); wall and
  CPU microseconds per tick, the fastest of ``--repeats``.
* ``sinusoid``: ``wbc-jax balance --task sinusoid --duration 20`` with ``--host-loop compiled`` and
  ``python``, and the compiled loop with XLA's CPU pool of a thread per core, each in its own
  process with a warm compilation cache (run once before): loop time, real-time factor, CoM RMSE
  (targets: loop <= 1 s, i.e. 20x real time; RMSE 1.00 mm).
* ``rerun``: ``wbc-jax balance``, ``wbc-jax push-sweep`` (the README's main job) and a small
  ``wbc-jax envelope``, each twice with an empty compilation cache: seconds from the process's start
  to its first tick (``started_s``; target for the second run: <= 3 s) and the command's wall time
  (target for the main job's second run: <= 10 s).
* ``notebook`` (in this process): ``wbc_jax.run`` again with new gains, as a notebook cell re-run:
  seconds compiling (target 0).
* ``acceptance``: ``experiments/acceptance/balance_acceptance.py`` (every scenario, now the compiled loop) into a
  new summary (or ``--acceptance-summary``, one made before), each figure against
  ``--acceptance-baseline`` (results/balance_acceptance.json as committed): the largest relative
  differences per scenario (target: float noise).

One robot runs with XLA's CPU thread pool of one thread (``PJRT_NPROC=1`` unless set, as
``wbc-jax balance`` does). Writes ``--out`` (merged by part) with each figure's command, the machine, its load average and the
date. Timings on a shared machine are inflated: compare figures of one run; CPU times suffer less.
"""

from __future__ import annotations

import os

# One robot, as `wbc-jax balance` runs it: XLA's CPU pool of one thread (read when JAX starts).
os.environ.setdefault("PJRT_NPROC", "1")

import argparse
import json
import pathlib
import platform
import subprocess
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parent.parent
PARTS = ("profile", "sinusoid", "rerun", "notebook", "acceptance")
# not figures of the controller: timings, and labels whose format or meaning changed (device, driver)
TIMINGS = {"compile_s", "loop_s", "real_time_factor", "wall_time_s", "started_s", "command", "device", "host_loop"}


class Timers:
    """Wall and CPU seconds of wrapped calls, by name."""

    def __init__(self):
        self.total: dict[str, list[float]] = {}

    def wrap(self, name: str, fn, block: bool = False):
        import jax

        def timed(*args, **kwargs):
            wall, cpu = time.perf_counter(), time.process_time()
            out = fn(*args, **kwargs)
            if block:
                jax.block_until_ready(out)
            t = self.total.setdefault(name, [0.0, 0.0])
            t[0] += time.perf_counter() - wall
            t[1] += time.process_time() - cpu
            return out

        return timed


def _best(fn, repeats: int):
    """(wall, cpu, result) of the repeat with the least CPU time."""
    best = None
    for _ in range(repeats):
        wall, cpu = time.perf_counter(), time.process_time()
        out = fn()
        row = (time.perf_counter() - wall, time.process_time() - cpu, out)
        best = row if best is None or row[1] < best[1] else best
    return best


def profile(repeats: int, ticks: int, qp_engine: str = "auto") -> dict:
    """The ``profile`` part (module docstring); ``qp_engine``: the controller's force QP engine
    (``ControllerConfig.qp_engine``; ``auto`` recorded as the engine it resolves to here)."""
    import jax
    import jax.numpy as jnp

    from wbc_jax.control.controller import ControllerConfig
    from wbc_jax.sim import host_loop, native, physics, runner, scenario
    from wbc_jax.sim.loop import PROGRAMS
    from wbc_jax.sim.state import SimConfig

    runner.enable_compilation_cache()
    us = lambda s: round(1e6 * s / ticks, 1)  # noqa: E731
    controller = ControllerConfig(qp_engine=qp_engine)
    out: dict = {
        "ticks": ticks,
        "task": f"sinusoid, {ticks * 0.01:g} s, trajectories recorded, one robot",
        "qp_engine": controller.qp_engine,
    }

    def setup(driver: str):
        sim = SimConfig(record=True, host_loop=driver, physics=physics.PhysicsConfig(backend="mujoco"))
        return scenario.setup("sinusoid", duration=ticks * 0.01, sim=sim, controller=controller)

    # The Python loop of ticks, its stages timed by wrapping what run_host calls.
    st = setup("python")
    runner.run(st, scenario.single(st))  # compile (or load)
    timers = Timers()
    key = next(k for k in PROGRAMS if k[0] == "host" and k[1] == st.loop.structure_key)
    saved = dict(PROGRAMS[key])
    PROGRAMS[key] = {
        **saved,
        "control": timers.wrap("controller call (dispatch + XLA)", saved["control"], True),
        "measure": timers.wrap("measured wrenches (XLA call)", saved["measure"], True),
    }
    originals = {name: getattr(physics.HostBatch, name) for name in ("state", "step", "contacts")}
    labels = {"state": "read the state", "step": "C MuJoCo: 10 mj_step", "contacts": "contact slots"}
    original_xfrc = host_loop.host_xfrc
    try:
        for name, fn in originals.items():
            setattr(physics.HostBatch, name, timers.wrap(labels[name], fn))
        host_loop.host_xfrc = timers.wrap("push wrenches (numpy)", original_xfrc)
        timers.total.clear()
        wall, cpu = time.perf_counter(), time.process_time()
        runner.run(st, scenario.single(st))
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    finally:
        for name, fn in originals.items():
            setattr(physics.HostBatch, name, fn)
        host_loop.host_xfrc = original_xfrc
        PROGRAMS[key] = saved
    stages = {name: {"wall_us": us(t[0]), "cpu_us": us(t[1])} for name, t in timers.total.items()}
    stages["the Python between (casts to JAX arrays, trees, the loop)"] = {
        "wall_us": us(wall - sum(t[0] for t in timers.total.values())),
        "cpu_us": us(cpu - sum(t[1] for t in timers.total.values())),
    }
    out["python_loop"] = {"per_tick_wall_us": us(wall), "per_tick_cpu_us": us(cpu), "stages": stages}

    # The compiled loop: the whole horizon in one program, C MuJoCo timed inside it.
    st = setup("compiled")
    runner.run(st, scenario.single(st))

    def compiled_run():
        native.physics_cpu(reset=True)
        runner.run(st, scenario.single(st))
        return native.physics_cpu()[0], native.terms_cpu()

    wall, cpu, (physics_cpu, terms_cpu) = _best(compiled_run, repeats)
    out["compiled_loop"] = {
        "per_tick_wall_us": us(wall),
        "per_tick_cpu_us": us(cpu),
        "physics_cpu_us": us(physics_cpu),
        "rest_cpu_us": us(cpu - physics_cpu),
        # of the rest: the controller's dynamics terms read out of C MuJoCo's data (native.step_terms)
        "terms_from_c_mujoco_cpu_us": us(terms_cpu),
    }

    # The controller's tick alone (controller, metrics, records) in a scan: no physics, no calls.
    loop, dtype = st.loop, st.dtype
    one = jax.tree_util.tree_map(lambda x: x[0], scenario.single(st))
    q0 = jnp.asarray(st.qpos0, dtype)

    def ticks_alone(q):
        state = loop.init(q)

        def tick(carry, k):
            state, q = carry
            state, ctrl, record = loop.control(
                one.gains, state, q, jnp.zeros(loop.idx.nv, dtype), k, jnp.bool_(True), one.push
            )
            return (state, q.at[0].add(1e-9 * ctrl[0])), record.com

        return jax.lax.scan(tick, (state, q), jnp.arange(ticks, dtype=jnp.int32))[1]

    alone = jax.jit(ticks_alone).lower(q0).compile()
    wall, cpu, _ = _best(lambda: jax.block_until_ready(alone(q0)), repeats)
    hlo = alone.as_text()  # what XLA runs: many small kernels, each a call of the CPU runtime
    out["controller_alone"] = {
        "per_tick_wall_us": us(wall),
        "per_tick_cpu_us": us(cpu),
        "what": "loop.control at the standing state in a lax.scan, records kept",
        "program": {
            "fusions": hlo.count(" fusion("),
            "dots": hlo.count(" dot("),
            "library_calls": hlo.count(" custom-call("),
            "while_loops": hlo.count(" while("),
        },
    }
    return out


def _cli(args: list[str], env: dict) -> tuple[float, dict]:
    """Run ``wbc-jax ARGS`` (this checkout); (wall seconds, its JSON line)."""
    t0 = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-m", "wbc_jax.cli", *args], capture_output=True, text=True, env=env, cwd=ROOT, timeout=3600
    )
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"wbc-jax {' '.join(args)} failed:\n{proc.stderr[-3000:]}")
    return wall, json.loads([line for line in proc.stdout.splitlines() if line.startswith("{")][-1])


def _env(cache: pathlib.Path) -> dict:
    return {**os.environ, "JAX_PLATFORMS": "cpu", "WBC_JAX_CACHE": str(cache), "PYTHONPATH": str(ROOT)}


def sinusoid(work: pathlib.Path) -> dict:
    """The ``sinusoid`` part: each loop after a warm-up run that fills the cache; the compiled loop
    also with XLA's CPU pool of one thread per core (``PJRT_NPROC`` = the core count)."""
    out = {}
    variants = {
        "compiled": ("compiled", "1"),
        "python": ("python", "1"),
        "compiled, a pool thread per core": ("compiled", str(os.cpu_count() or 1)),
    }
    for name, (driver, threads) in variants.items():
        args = ["balance", "--task", "sinusoid", "--duration", "20", "--host-loop", driver, "--no-plots", "--quiet"]
        env = {**_env(work / "xla"), "PJRT_NPROC": threads}
        _cli([*args, "--out", str(work / f"sin_{driver}_{threads}_0")], env)
        wall, s = _cli([*args, "--out", str(work / f"sin_{driver}_{threads}_1")], env)
        out[name] = {
            "command": f"PJRT_NPROC={threads} wbc-jax " + " ".join(args),
            "loop_s": s["loop_s"],
            "real_time_factor": s["real_time_factor"],
            "com_rmse_mm": round(1e3 * s["com_rmse_m"], 5),
            "compile_s": s["compile_s"],
            "started_s": s["started_s"],
            "wall_s": round(wall, 2),
            "host_loop": s["host_loop"],
        }
    c = out["compiled"]
    out["target"] = "compiled loop <= 1 s (20x real time), CoM RMSE 1.00 mm"
    out["met"] = bool(c["loop_s"] <= 1.0 and abs(c["com_rmse_mm"] - 1.00) < 0.01)
    return out


RERUN = {
    "balance": ["balance", "--task", "sinusoid", "--duration", "20", "--no-plots", "--quiet"],
    "push-sweep (README main job)": ["push-sweep", "--quiet"],
    "envelope": ["envelope", "--directions", "8", "--horizon", "1.5", "--quiet"],
}


def rerun(work: pathlib.Path) -> dict:
    """The ``rerun`` part: each job twice, from an empty compilation cache."""
    out = {}
    for name, args in RERUN.items():
        cache = work / f"xla_{args[0]}"
        rows = []
        for k in range(2):
            wall, s = _cli([*args, "--out", str(work / f"{args[0]}_{k}")], _env(cache))
            rows.append({"wall_s": round(wall, 2), "started_s": s.get("started_s"), "compile_s": s.get("compile_s")})
        out[name] = {
            "command": "wbc-jax " + " ".join(args) + " (empty cache, then again)",
            "first": rows[0],
            "second": rows[1],
        }
    main = out["push-sweep (README main job)"]["second"]
    out["target"] = "a second run starts simulating within 3 s; the main job's second run within 10 s"
    out["met"] = bool(
        all(v["second"]["started_s"] <= 3.0 for v in out.values() if isinstance(v, dict)) and main["wall_s"] <= 10.0
    )
    return out


def notebook() -> dict:
    """The ``notebook`` part: ``wbc_jax.run`` again with new gains."""
    import jax
    import numpy as np

    import wbc_jax
    from wbc_jax.sim import runner

    runner.enable_compilation_cache()
    st = wbc_jax.setup("sinusoid", duration=5.0)
    first = wbc_jax.run(st, wbc_jax.single(st))
    gains = jax.tree_util.tree_map(lambda g: np.asarray(g) * 1.2, st.gains)
    t0 = time.perf_counter()
    again = wbc_jax.run(st, wbc_jax.single(st, gains=gains))
    return {
        "command": "wbc_jax.run(st, wbc_jax.single(st, gains=new)) after a first run (5 s sinusoid)",
        "first_compile_s": round(first.compile_s, 2),
        "again_compile_s": again.compile_s,
        "again_wall_s": round(time.perf_counter() - t0, 3),
        "com_moved_m": float(np.abs(again.records.com - first.records.com).max()),
        "target": "no compilation (compile_s 0)",
        "met": again.compile_s == 0.0,
    }


def _differences(a, b, path: list) -> list:
    """(relative difference, figure, a, b) of every figure two summaries share (timings and labels
    left out; a changed flag or string counts as 1)."""
    if isinstance(a, dict) and isinstance(b, dict):
        return [row for k in sorted(set(a) & set(b) - TIMINGS) for row in _differences(a[k], b[k], [*path, k])]
    if isinstance(a, (bool, str)) or isinstance(b, (bool, str)):
        return [] if a == b else [(1.0, ".".join(path), a, b)]
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        return [(abs(a - b) / max(abs(a), 1e-12), ".".join(path), a, b)]
    return []


def compare_figures(old: dict, new: dict, top: int = 3) -> dict:
    """Per scenario of two acceptance summaries: the ``top`` figures that differ most, relatively."""
    out = {}
    for name in sorted(set(old) & set(new)):
        rows = sorted(_differences(old[name], new[name], []), key=lambda r: r[0], reverse=True)
        out[name] = [
            {"figure": p, "relative": float(f"{r:.3g}"), "committed": a, "now": b} for r, p, a, b in rows[:top]
        ]
    return out


def acceptance(work: pathlib.Path, baseline: pathlib.Path, summary: pathlib.Path | None) -> dict:
    """The ``acceptance`` part."""
    if summary is None:
        summary = work / "balance_acceptance.json"
        cmd = [
            sys.executable,
            str(ROOT / "experiments" / "acceptance" / "balance_acceptance.py"),
            "--out",
            str(work / "acceptance"),
            "--summary",
            str(summary),
        ]
        proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=7200, env=_env(work / "xla"))
        if proc.returncode != 0:
            raise RuntimeError(f"balance_acceptance.py failed:\n{proc.stderr[-3000:]}")
    old, new = json.loads(baseline.read_text()), json.loads(summary.read_text())
    return {
        "command": "python experiments/acceptance/balance_acceptance.py (every scenario), compared with "
        + str(baseline),
        "largest_differences": compare_figures(old, new),
        "drivers": sorted({v.get("host_loop") for v in new.values() if isinstance(v, dict) and "task" in v}),
    }


def main(argv=None) -> dict:
    argv = list(sys.argv[1:] if argv is None else argv)
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default=str(ROOT / "runs" / "cpu_loop.json"))
    p.add_argument("--parts", nargs="+", default=list(PARTS), choices=PARTS)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--ticks", type=int, default=2000, help="ticks of the profiled sinusoid")
    p.add_argument(
        "--qp-engine",
        default="auto",
        help="the profiled controller's force QP engine (ControllerConfig.qp_engine: auto, the controller's default; "
        "jax, eiquadprog, ...)",
    )
    p.add_argument("--acceptance-baseline", default=str(ROOT / "results" / "balance_acceptance.json"))
    p.add_argument("--acceptance-summary", default=None, help="compare this summary instead of running the scenarios")
    args = p.parse_args(argv)
    if args.repeats < 1 or args.ticks < 1:
        p.error("--repeats and --ticks must be >= 1")
    from wbc_jax.control.qp import ENGINE_CHOICES

    if args.qp_engine not in ENGINE_CHOICES:
        p.error(f"--qp-engine must be one of {list(ENGINE_CHOICES)}, got {args.qp_engine!r}")
    out = pathlib.Path(args.out)
    result = json.loads(out.read_text()) if out.exists() else {}
    result.update(
        {
            "command": "python benchmarks/cpu_loop.py " + " ".join(argv),
            "date": time.strftime("%Y-%m-%d"),
            "machine": {
                "cpu": platform.processor() or platform.machine(),
                "cores": os.cpu_count(),
                "xla_flags": os.environ.get("XLA_FLAGS", ""),
            },
        }
    )
    work = pathlib.Path(tempfile.mkdtemp(prefix="wbc_cpu_loop_"))

    def save(part, value):
        from wbc_jax.core import io, provenance

        result[part] = value
        result["machine"]["cpu"] = provenance.device_label()
        result["provenance"] = provenance.record(
            {"acceptance baseline": args.acceptance_baseline}, argv=[__file__, *argv]
        )
        result.setdefault("load_average", {})[part] = [round(x, 2) for x in os.getloadavg()]
        io.atomic_write_json(out, result)
        print(json.dumps({part: value}), flush=True)

    if "profile" in args.parts:
        save("profile", profile(args.repeats, args.ticks, args.qp_engine))
    if "sinusoid" in args.parts:
        save("sinusoid", sinusoid(work))
    if "rerun" in args.parts:
        save("rerun", rerun(work))
    if "notebook" in args.parts:
        save("notebook", notebook())
    if "acceptance" in args.parts:
        made = None if args.acceptance_summary is None else pathlib.Path(args.acceptance_summary)
        save("acceptance", acceptance(work, pathlib.Path(args.acceptance_baseline), made))
    return result


if __name__ == "__main__":
    main()
