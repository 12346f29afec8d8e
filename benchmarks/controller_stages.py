"""Where the controller's tick goes, stage by stage, for one robot on one core (issue 46).

    taskset -c 1 python benchmarks/controller_stages.py --out runs/controller_stages.json [--before REF]

The states are the 20 s sinusoid's own (``wbc-jax balance --task sinusoid``, C MuJoCo, recorded;
velocities from consecutive positions), so the QP sees the problems it solves in that run. Each
program is a ``lax.scan`` over those ticks of the tick's first stages, one stage more per program
(cumulative, so every stage runs on the data the stage before produced and XLA fuses across the
seams as it does in the tick):

1. dynamics terms (kinematics, Jacobians and their derivative, mass matrix, bias), all of them,
   and every later program returns them too: a program that returned only what its stage makes
   left the bias and Jdot nu (dead code to XLA before) to the torque law's stage, which was
   charged with them (the split recorded in results/cpu_targets/qp46);
2. + contact terms and the momentum task (L_dot*);
3. + the torque law with the ``seed`` postural task (Lambda, its damped pseudo-inverse, N_Lambda,
   Sigma, tau_model);
4. + the ``stable`` postural task instead (the projector pinv(N_Lambda Mbar) N_Lambda Mbar);
5. + the force distribution (the contact QPs);
6. the loop's whole control tick (``ClosedLoop.control``: the above, saturation, metrics, records),
   its state carried from tick to tick as in the loop (the force QP's warm start).

A stage's cost is its program's time less the previous one's. CPU microseconds per tick, the
median and the range of ``--repeats`` runs, the programs interleaved within each repeat (a shared
machine's load reaches them alike). Also: XLA's op counts of the whole tick's program (fusions,
dots, library calls, while loops) and the QP's Newton steps per tick. One thread of XLA's CPU pool
(``PJRT_NPROC=1``, as ``wbc-jax balance``). ``--before REF``: the same programs of commit REF's
controller (its package copied beside this one), timed in the same process, interleaved with these.
"""

from __future__ import annotations

import os

os.environ.setdefault("PJRT_NPROC", "1")

import argparse
import importlib
import importlib.util
import json
import pathlib
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parent.parent
STAGES = (
    "dynamics terms",
    "contact terms + momentum task",
    "torque law (seed postural)",
    "postural projector (stable)",
    "force distribution (QP)",
    "saturation, metrics, records",
)


def op_counts(compiled) -> dict:
    """What XLA runs: fusions, dots, library (custom) calls and while loops of a compiled program."""
    hlo = compiled.as_text()
    return {
        "fusions": hlo.count(" fusion("),
        "dots": hlo.count(" dot("),
        "library_calls": hlo.count(" custom-call("),
        "while_loops": hlo.count(" while("),
    }


def sinusoid_states(ticks: int):
    """(qpos (T, nq), qvel (T, nv), setup) of the sinusoid's ticks on C MuJoCo."""
    import mujoco
    import numpy as np

    from wbc_jax.sim import physics, runner, scenario
    from wbc_jax.sim.state import SimConfig

    sim = SimConfig(record=True, host_loop="compiled", physics=physics.PhysicsConfig(backend="mujoco"))
    st = scenario.setup("sinusoid", duration=ticks * 0.01, sim=sim)
    qpos = np.asarray(runner.run(st, scenario.single(st)).records.qpos, np.float64)[0]
    m = st.robot.mj_model
    qvel = np.zeros((len(qpos), m.nv))
    for k in range(1, len(qpos)):
        mujoco.mj_differentiatePos(m, qvel[k], 0.01, qpos[k - 1], qpos[k])
    return qpos, qvel, st


def stage_prefix(ticks: int, pkg: str = "wbc_jax", settings: dict | None = None):
    """``(prefix, st, state0)``: ``prefix(depth, q, v, k)`` the tick's first ``depth`` stages (module
    docstring) of the sinusoid's controller built by the package ``pkg`` (``settings``: ControllerConfig fields
    other than the defaults); with ``force_inputs``, depth 5 returns the arguments ``(cset, activation, A, wrench,
    tt, W_R, settings)`` of the force distribution."""
    import jax.numpy as jnp

    constraints, forces, momentum, torques = (
        importlib.import_module(f"{pkg}.control.{name}") for name in ("constraints", "forces", "momentum", "torques")
    )
    contacts = importlib.import_module(f"{pkg}.robot.contacts")
    scenario = importlib.import_module(f"{pkg}.sim.scenario")
    physics, state = importlib.import_module(f"{pkg}.sim.physics"), importlib.import_module(f"{pkg}.sim.state")
    sim = state.SimConfig(record=True, host_loop="compiled", physics=physics.PhysicsConfig(backend="mujoco"))
    controller = importlib.import_module(f"{pkg}.control.controller")
    config = controller.ControllerConfig(**settings) if settings else None
    st = scenario.setup("sinusoid", duration=ticks * 0.01, sim=sim, controller=config)
    loop, ctrl, dtype = st.loop, st.loop.controller, st.dtype
    cset, cfg, gains = ctrl.contact_set, ctrl.config, st.gains
    state0 = loop.init(jnp.asarray(st.qpos0, dtype))
    mass = st.robot.index.mass

    def prefix(depth: int, q, v, k, force_inputs: bool = False):
        time_now = k * loop.cfg.control_dt
        t = loop.terms(q, v)
        if depth == 1:
            return t
        ref = loop.schedule.at(time_now, dtype)
        ct = contacts.contact_terms(cset, t, time_now, jnp.clip(ref.activation, 0.0, 1.0))
        Ldot_star = momentum.momentum_rate_reference(
            mass=mass,
            W_p_CoM=t.W_p_CoM,
            W_v_CoM=t.W_v_CoM,
            L_ang=t.L_G[3:],
            com_pos_des=ref.com_pos,
            com_vel_des=ref.com_vel,
            com_acc_des=ref.com_acc,
            com_err_integral=jnp.zeros(3, dtype),
            ang_integral=state0.controller.centroidal_jacobian_ref[0] @ (t.s - ref.s_des),
            kp_com=gains.kp_com,
            kd_com=gains.kd_com,
            ki_com=gains.ki_com,
            kp_ang=gains.kp_ang,
            ki_ang=gains.ki_ang,
        )
        if depth == 2:
            return t, Ldot_star, ct.J
        rows = contacts.row_activation(cset, ct.activation)
        tt = torques.torque_terms(
            t,
            ct.J * rows[:, None],
            ct.Jdot_nu * rows,
            postural="seed" if depth == 3 else cfg.postural,
            kp_postural=gains.kp_postural,
            kd_postural=gains.kd_postural,
            s_des=ref.s_des,
            pinv_damping=cfg.pinv_damping,
            pinv_tol=cfg.pinv_tol,
            kp_postural_reg=cfg.kp_postural_reg,
            compensate_passive=cfg.compensate_passive,
        )
        if depth <= 4:
            return t, Ldot_star, tt.Sigma, tt.tau_model
        A = constraints.wrench_map(cset, ct.W_p, t.W_p_CoM).astype(dtype)
        wrench = Ldot_star - constraints.gravity_wrench(mass, dtype)
        if force_inputs:
            return cset, ct.activation, A, wrench, tt, ct.W_R, cfg.force_settings
        # Cold QP starts (the whole tick, stage 6, starts from the last tick's); [:2]: a commit before
        # the warm start (--before) returns no third item.
        f, infeasible = forces.distribute(cset, ct.activation, A, wrench, tt, ct.W_R, cfg.force_settings)[:2]
        return t, tt.tau_model + tt.Sigma @ f, infeasible

    return prefix, st, state0


def programs(ticks: int, pkg: str = "wbc_jax", settings: dict | None = None):
    """The cumulative stage programs (module docstring) of the sinusoid's controller built by the
    package ``pkg`` (this checkout's, or a copy of another commit's: :func:`import_commit`), each
    ``(qpos (T, nq), qvel (T, nv)) -> ()``."""
    import jax
    import jax.numpy as jnp

    prefix, st, state0 = stage_prefix(ticks, pkg, settings)
    scenario = importlib.import_module(f"{pkg}.sim.scenario")
    loop, dtype = st.loop, st.dtype
    one = jax.tree_util.tree_map(lambda x: x[0], scenario.single(st))

    def scanned(depth: int):
        def run(qs, vs):
            def tick(carry, x):
                acc, state = carry
                q, v, k = x
                if depth == len(STAGES):  # the loop's state carried, as in the loop (the QP's warm start)
                    state, ctrl_out, rec = loop.control(one.gains, state, q, v, k, jnp.bool_(True), one.push)
                    out = (ctrl_out, rec.com)
                else:
                    out = prefix(depth, q, v, k)
                total = sum(jnp.sum(jnp.asarray(leaf, dtype)) for leaf in jax.tree_util.tree_leaves(out))
                return (acc + total, state), None

            ks = jnp.arange(qs.shape[0], dtype=jnp.int32)
            return jax.lax.scan(tick, (jnp.zeros((), dtype), state0), (qs, vs, ks))[0][0]

        return run

    return [scanned(d) for d in range(1, len(STAGES) + 1)]


def import_commit(ref: str) -> str:
    """Make the package of git commit ``ref`` importable beside this checkout's, as
    ``wbc_jax_<short hash>`` (a ``git archive`` copy, its imports renamed); returns the name."""
    sha = subprocess.run(["git", "rev-parse", "--short", ref], cwd=ROOT, capture_output=True, text=True)
    if sha.returncode != 0:
        raise SystemExit(f"--before: {ref!r} is not a commit of {ROOT} ({sha.stderr.strip()})")
    name = f"wbc_jax_{sha.stdout.strip()}"
    work = pathlib.Path(tempfile.mkdtemp(prefix="wbc_before_"))
    archive = subprocess.run(["git", "archive", ref, "wbc_jax"], cwd=ROOT, capture_output=True, check=True).stdout
    subprocess.run(["tar", "-x", "-C", str(work)], input=archive, check=True)
    shutil.move(work / "wbc_jax", work / name)
    for path in (work / name).rglob("*.py"):
        text = path.read_text()
        path.write_text(re.sub(r"\bwbc_jax\b", name, text))
    (work / "assets").symlink_to(ROOT / "assets")  # the model files, read beside the package
    # Imported by location (the scripts leave sys.path alone): its submodules follow the package's path.
    spec = importlib.util.spec_from_file_location(
        name, work / name / "__init__.py", submodule_search_locations=[str(work / name)]
    )
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return name


def qp_newton_steps(st, qs, vs) -> dict:
    """Newton steps of the tick's first QP (both feet, the equality QP) over the ticks."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from wbc_jax.control import constraints, forces, torques
    from wbc_jax.robot import contacts

    loop, ctrl, dtype = st.loop, st.loop.controller, st.dtype
    cset, cfg, gains = ctrl.contact_set, ctrl.config, st.gains

    def steps(q, v, k):
        t = loop.terms(q, v)
        ref = loop.schedule.at(k * loop.cfg.control_dt, dtype)
        ct = contacts.contact_terms(cset, t, k * loop.cfg.control_dt, jnp.clip(ref.activation, 0.0, 1.0))
        tt = torques.torque_terms(
            t,
            ct.J,
            ct.Jdot_nu,
            postural=cfg.postural,
            kp_postural=gains.kp_postural,
            kd_postural=gains.kd_postural,
            s_des=ref.s_des,
        )
        A = constraints.wrench_map(cset, ct.W_p, t.W_p_CoM).astype(dtype)
        w = jnp.asarray([0.0, 0.0, 9.81 * st.robot.index.mass, 0.0, 0.0, 0.0], dtype)
        _, info = forces.momentum_equality_qp(
            cset, jnp.ones(len(cset.contacts), dtype), A, w, tt, ct.W_R, cfg.force_settings
        )
        return info.iterations, info.converged

    it, conv = jax.jit(jax.vmap(steps))(qs, vs, jnp.arange(qs.shape[0], dtype=jnp.int32))
    it = np.asarray(it)
    return {"mean": round(float(it.mean()), 2), "max": int(it.max()), "converged": float(np.mean(conv))}


def split(cpu_us: list[list[float]]) -> dict:
    """Per stage: the median and range over the repeats of its program's time less the previous one's."""
    medians = [statistics.median(c) for c in cpu_us]
    stages = {}
    for i, name in enumerate(STAGES):
        diffs = [c - (cpu_us[i - 1][r] if i else 0.0) for r, c in enumerate(cpu_us[i])]
        stages[name] = {
            "median_us": round(medians[i] - (medians[i - 1] if i else 0.0), 1),
            "range_us": [round(min(diffs), 1), round(max(diffs), 1)],
        }
    stages["whole tick"] = {
        "median_us": round(medians[-1], 1),
        "range_us": [round(min(cpu_us[-1]), 1), round(max(cpu_us[-1]), 1)],
    }
    return stages


def timing_parser(
    script: str, doc: str, ticks: int, repeats: int, out_required: bool = False
) -> argparse.ArgumentParser:
    """The sinusoid timing scripts' common flags (this one, force_build, force_qp_alone, torque_law_alone,
    dynamics_terms_parts): ``--out`` (default runs/SCRIPT.json), ``--ticks`` of the sinusoid, ``--repeats``."""
    p = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    if out_required:
        p.add_argument("--out", required=True)
    else:
        p.add_argument("--out", default=str(ROOT / "runs" / f"{script}.json"))
    p.add_argument("--ticks", type=int, default=ticks, help="ticks of the sinusoid (10 ms each)")
    p.add_argument("--repeats", type=int, default=repeats)
    return p


def parse_timing_args(p: argparse.ArgumentParser, argv: list[str]) -> argparse.Namespace:
    """``p``'s arguments, ``--ticks`` < 2 or ``--repeats`` < 1 refused in one line."""
    args = p.parse_args(argv)
    if args.ticks < 2 or args.repeats < 1:
        p.error("--ticks must be >= 2 and --repeats >= 1")
    return args


def result_header(script: str, argv: list[str], args: argparse.Namespace, dtype) -> dict:
    """What every timing script's result holds: the command, date, device, dtype, ticks, repeats, the
    process's cores, the machine's load and the provenance."""
    from wbc_jax.core import provenance

    return {
        "command": f"python benchmarks/{script}.py " + " ".join(argv),
        "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "device": provenance.device_label(),
        "dtype": str(dtype),
        "ticks": args.ticks,
        "repeats": args.repeats,
        "affinity": sorted(os.sched_getaffinity(0)),
        "load_average": [round(x, 2) for x in os.getloadavg()],
        "provenance": provenance.record(argv=[str(ROOT / "benchmarks" / f"{script}.py"), *argv]),
    }


def main(argv=None) -> dict:
    argv = list(sys.argv[1:] if argv is None else argv)
    p = timing_parser("controller_stages", __doc__, ticks=2000, repeats=7)
    p.add_argument(
        "--before",
        default=None,
        metavar="REF",
        help="also the stages of git commit REF's controller, interleaved with this checkout's",
    )
    p.add_argument(
        "--qp-warm-start",
        action="store_true",
        help="also this checkout's controller with qp_warm_start (the force QP from the last tick's solution)",
    )
    p.add_argument(
        "--qp-engine",
        default=None,
        help="also this checkout's controller with this force QP engine (ControllerConfig.qp_engine, e.g. eiquadprog)",
    )
    args = parse_timing_args(p, argv)
    import jax
    import jax.numpy as jnp

    from wbc_jax.control.qp import QP_ENGINES
    from wbc_jax.core import io
    from wbc_jax.sim import runner

    if args.qp_engine is not None and args.qp_engine not in QP_ENGINES:
        p.error(f"--qp-engine must be one of {list(QP_ENGINES)}, got {args.qp_engine!r}")
    variants = {"now": ("wbc_jax", None)}
    if args.qp_warm_start:
        variants["now, qp_warm_start"] = ("wbc_jax", {"qp_warm_start": True})
    if args.qp_engine:
        variants[f"now, qp_engine {args.qp_engine}"] = ("wbc_jax", {"qp_engine": args.qp_engine})
    if args.before:
        variants[f"before ({args.before})"] = (import_commit(args.before), None)
    runner.enable_compilation_cache()
    qpos, qvel, st = sinusoid_states(args.ticks)
    qs, vs = jnp.asarray(qpos, st.dtype), jnp.asarray(qvel, st.dtype)
    compiled = {}
    with jax.default_matmul_precision(st.loop.cfg.matmul_precision):  # as the loop's programs
        for name, (pkg, settings) in variants.items():
            compiled[name] = [jax.jit(fn).lower(qs, vs).compile() for fn in programs(args.ticks, pkg, settings)]
    cpu_us = {name: [[] for _ in STAGES] for name in variants}
    for _ in range(args.repeats):  # interleaved: the machine's load reaches every program alike
        for i in range(len(STAGES)):
            for name in variants:
                t0 = time.process_time()
                jax.block_until_ready(compiled[name][i](qs, vs))
                cpu_us[name][i].append(1e6 * (time.process_time() - t0) / args.ticks)
    result = {
        **result_header("controller_stages", argv, args, st.dtype),
        "stages_cpu_us_per_tick": {name: split(cpu_us[name]) for name in variants},
        "whole_tick_program": {name: op_counts(compiled[name][-1]) for name in variants},
        "qp_newton_steps": qp_newton_steps(st, qs, vs),
    }
    io.atomic_write_json(pathlib.Path(args.out), result)
    print(json.dumps(result), flush=True)
    return result


if __name__ == "__main__":
    main()
