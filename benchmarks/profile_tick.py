"""Where a control tick's time goes (issue 46), on the states the benchmark's closed loop visits.

    python benchmarks/profile_tick.py --batch 65536 --out runs/profile_tick [--states loop|synthetic]
        [--loop-envs 256] [--ticks 15 25 40] [--trace DIR]

The states (``--states``):

* ``loop`` (default): benchmarks/benchmark.py's closed loop (the stand task, ``--horizon`` 0.5 s, one
  40 N push per environment at ``--push-onset`` 0.2 s for ``--push-duration`` 0.1 s, azimuths
  over 360 deg) on ``--loop-envs`` environments, run by ``runner.run`` on MJX (JAX) on this device
  with a recorder of the tick's inputs (qpos, qvel, the loop state); the controller's inputs at
  each of ``--ticks`` (default: before, during and after the push) are tiled to ``--batch``.
* ``synthetic``: the standing posture with random joint offsets (0.02 rad) and velocities
  (0.05), the initial loop state, at 0.5 s (the profile before issue 46's GPU run: some robot of
  65,536 left the postural projector uncertified, BENCHMARKS.md).

Per group of states (one tick of the loop, or the synthetic batch), each stage jitted and vmapped
alone, on this device: the dynamics terms, the torque law, the force distribution (the contact
QPs; and its first QP alone, without the soft fallback), the controller's whole tick
(``Controller.step``), and ten MJX physics steps for scale; the fastest of --repeats runs after a
warm-up, microseconds per environment. And what the batch's branches cost: the fraction of
environments whose postural projector is not certified (``torques.projector_certified``: the
whole ``eigh`` then runs for the whole batch, ``batch_any``), the first QP's Newton steps per
problem (mean, and max: the while loop runs until the slowest problem converged), its infeasible
fraction, and the fraction that switch to the soft QP (its branch then runs for the whole batch). ``stage_tau_error``: the stages' torques (torque law
plus distribution) against the whole tick's, so the stages are the tick's computation.
``us_per_env``: the mean over the groups. ``--trace DIR``: a JAX profiler (Perfetto) trace of three
whole ticks of each group in DIR/tick_K, summarised in the group's ``trace``: the device's time per source file,
function, opcode and op, µs per environment (benchmarks/trace_summary.py).
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time

STATE_SETS = ("loop", "synthetic")
TRACE_CALLS = 3  # whole ticks per group in a --trace
SYNTHETIC_TIME_S = 0.5


def parse_args(argv=None) -> argparse.Namespace:
    from wbc_jax.core import constants
    from wbc_jax.sim import physics

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batch", type=int, default=1024)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--states", default="loop", choices=STATE_SETS, help="the controller's inputs (module docstring)")
    p.add_argument("--loop-envs", type=int, default=256, help="environments of the loop run (--states loop)")
    p.add_argument("--horizon", type=float, default=0.5, help="s, the loop run's (benchmark.py's GPU runs)")
    p.add_argument("--push-onset", type=float, default=0.2, help="s")
    p.add_argument("--push-duration", type=float, default=0.1, help="s")
    p.add_argument("--ticks", type=int, nargs="+", default=None, help="ticks of the loop (default: before, in, after)")
    p.add_argument("--backend", default="jax", help="physics backend of the scale step")
    p.add_argument("--out", default="runs/profile_tick")
    p.add_argument("--trace", default=None)
    p.add_argument(
        "--qp-warm-start",
        action="store_true",
        help="the controller's force QP warm-started (ControllerConfig.qp_warm_start), in the recorded loop too",
    )
    from loop_timing import add_qp_arguments, check_qp_arguments

    add_qp_arguments(p, recorded_loop=True, engine_default="jax")  # the stages of the JAX interior point by default
    args = p.parse_args(argv)
    check_qp_arguments(p, args)
    for name in ("batch", "repeats", "loop_envs"):
        if getattr(args, name) < 1:
            p.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    if not (args.horizon > 0 and 0 <= args.push_onset and args.push_duration > 0):
        p.error("--horizon and --push-duration must be > 0 s and --push-onset >= 0 s")
    if args.push_onset + args.push_duration >= args.horizon:
        p.error(f"--push-onset + --push-duration must end before --horizon {args.horizon} s (ticks after the push)")
    try:
        physics.resolve_backend(args.backend)
    except ValueError as err:
        p.error(f"--backend: {err}")
    dt = constants.CONTROL_DT
    n_ticks = round(args.horizon / dt)
    if args.ticks is None:  # before, in the middle of and after the push
        onset, end = round(args.push_onset / dt), round((args.push_onset + args.push_duration) / dt)
        args.ticks = [max(0, onset - 5), (onset + end) // 2, min(n_ticks - 1, end + 10)]
    if any(not 0 <= k < n_ticks for k in args.ticks):
        p.error(f"--ticks must lie in 0..{n_ticks - 1} (the ticks of --horizon {args.horizon} s), got {args.ticks}")
    return args


def timed(fn, *args, repeats: int) -> float:
    import jax

    jax.block_until_ready(fn(*args))
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        best = min(best, time.perf_counter() - t0)
    return best


def staged(loop, fn, in_axes=0):
    """jit(vmap(fn, in_axes)) called and lowered at the loop's matmul precision (``SimConfig.matmul_precision``), as
    the loop's own programs are traced (``wbc_jax.sim.state.traced_at_matmul_precision``): at JAX's default a GPU
    runs float32 products in TF32, another controller than the loop's (on an H100 every environment's postural
    projector then missed its certificate and the whole ``eigh`` ran, 2026-11-27)."""
    import jax

    program = jax.jit(jax.vmap(fn, in_axes=in_axes))

    def at_precision(method):
        def call(*args):
            with jax.default_matmul_precision(loop.cfg.matmul_precision):
                return method(*args)

        return call

    run = at_precision(program)
    run.lower = at_precision(program.lower)
    return run


def record_tick_inputs(record, new_state, state, qpos, qvel):
    """The loop's recorder (``wbc_jax.sim.loop.Recorder``) of what the controller's tick starts from."""
    return record, (qpos, qvel, state)


def loop_run_inputs(st, envs: int, onset: float, duration: float):
    """(qpos (E, T, nq), qvel (E, T, nv), LoopState (E, T, ...)): the inputs of every tick of
    benchmark.py's closed loop on ``st`` (loop_timing.make_setup), E = ``envs`` pushes, by
    ``runner.run`` (the loop's own program) with :func:`record_tick_inputs`."""
    import dataclasses

    from loop_timing import push_batch

    from wbc_jax.sim import loop as loop_lib
    from wbc_jax.sim import runner

    recording = dataclasses.replace(st, loop=loop_lib.compose(st.loop, recorder=record_tick_inputs))
    _, (qpos, qvel, state) = runner.run(recording, push_batch(st, envs, onset, duration)).records
    return qpos, qvel, state


def stage_functions(st) -> dict:
    """The tick's stages of one environment, as the controller's ``step`` runs them, each from the
    tick's inputs (qpos, qvel, loop state, tick k) or the stage before; ``diagnostics``: the
    projector's certification, the first QP's Newton steps and infeasibility, the stages' torques
    against the tick's."""
    import jax.numpy as jnp

    from wbc_jax.control import constraints, forces, torques
    from wbc_jax.robot import contacts

    loop, ctrl, dtype = st.loop, st.loop.controller, st.dtype
    cset, cfg, gains = ctrl.contact_set, ctrl.config, st.gains
    if loop.observes_contacts or ctrl.stack is not None:
        raise ValueError("profile_tick's stages are those of the stand task: no contact detection, no motion tasks")
    f_grav = constraints.gravity_wrench(st.robot.index.mass, dtype)

    def at(k):
        t_now = k * loop.cfg.control_dt  # as ClosedLoop.control
        return t_now, loop.schedule.at(t_now, dtype)

    def tick(q, v, state, k):
        t_now, ref = at(k)
        return ctrl.step(gains, state.controller, loop.terms(q, v), ref, t_now, state.measured_normal)[0]

    def contact_rows(t, k):
        t_now, ref = at(k)
        ct = contacts.contact_terms(cset, t, t_now, jnp.clip(ref.activation, 0.0, 1.0))
        return ct, contacts.row_activation(cset, ct.activation)

    def torque_law(t, state, k):
        ref = at(k)[1]
        ct, rows = contact_rows(t, k)
        return torques.torque_terms(
            t,
            ct.J * rows[:, None],
            ct.Jdot_nu * rows,
            postural=cfg.postural,
            kp_postural=gains.kp_postural,
            kd_postural=gains.kd_postural,
            s_des=ref.s_des,
            pinv_damping=state.controller.pinv_damping,
            pinv_tol=cfg.pinv_tol,
            kp_postural_reg=state.controller.kp_postural_reg,
            compensate_passive=cfg.compensate_passive,
            freeze_projector=cfg.freeze_postural_projector,
            mass_solve_engine=cfg.mass_solve_engine,
            ritz_engine=cfg.ritz_engine,
        )

    def force_inputs(t, k, Ldot_star):
        ct = contact_rows(t, k)[0]
        A = constraints.wrench_map(cset, ct.W_p, t.W_p_CoM).astype(dtype)
        return ct.activation, A, Ldot_star - f_grav, ct.W_R

    def distribution(tt, state, act, A, wrench, W_R):
        return forces.distribute(cset, act, A, wrench, tt, W_R, cfg.force_settings, state.controller.qp_start)[0]

    def engaged_mask(act):  # as forces.distribute's
        act = jnp.clip(act, 0.0, 1.0)
        return jnp.where(jnp.any(act > 0), act > 0, True).astype(dtype)

    def first_qp(tt, state, act, A, wrench, W_R):  # the engaged contacts' equality QP, as distribute's
        engaged = engaged_mask(act)
        start = state.controller.qp_start if cfg.qp_warm_start else None
        return forces.momentum_equality_qp(cset, engaged, A, wrench, tt, W_R, cfg.force_settings, start)

    def first_qp_data(tt, act, A, wrench, W_R):  # that QP's (H, g, C, b), as momentum_equality_qp builds it
        data = forces.equality_qp_data(cset, engaged_mask(act), A, wrench, tt, W_R, cfg.force_settings)
        return data.H, data.g, data.C, data.b

    def diagnostics(q, v, state, k):
        t, out = loop.terms(q, v), tick(q, v, state, k)
        tt = torque_law(t, state, k)
        inputs = force_inputs(t, k, out.Ldot_star)
        f_first, info = first_qp(tt, state, *inputs)
        # wbc_qp's switch to the soft QP (batch_any: then run for the whole batch): the first QP
        # infeasible, or its wrenches beyond a contact's constraints.
        mask = engaged_mask(inputs[0])
        violation = jnp.where(mask > 0, constraints.contact_violation(cset, f_first, inputs[3], mask), 0.0)
        soft = info.infeasible | (jnp.max(violation) > cfg.force_settings.tolerance(dtype))
        tau = tt.tau_model + tt.Sigma @ distribution(tt, state, *inputs)
        ct, rows = contact_rows(t, k)
        certified = torques.projector_certified(
            t,
            ct.J * rows[:, None],
            pinv_damping=state.controller.pinv_damping,
            pinv_tol=cfg.pinv_tol,
            compensate_passive=cfg.compensate_passive,
        )
        return {
            "certified": certified if cfg.postural == "stable" else jnp.ones((), bool),
            "newton_steps": info.iterations,
            "qp_infeasible": info.infeasible,
            "soft_qp": soft,
            "tau_error": jnp.max(jnp.abs(tau - out.tau_unsat)),
            "Ldot_star": out.Ldot_star,
        }

    return dict(
        tick=tick,
        torque_law=torque_law,
        force_inputs=force_inputs,
        distribution=distribution,
        first_qp=lambda *a: first_qp(*a)[0],
        first_qp_data=first_qp_data,
        diagnostics=diagnostics,
    )


def state_groups(st, args) -> list[dict]:
    """The groups of controller inputs, each ``{tick, qpos (B, nq), qvel (B, nv), state (B, ...)}``
    with B = --batch (the loop's environments tiled)."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    B, dtype = args.batch, st.dtype
    if args.states == "synthetic":
        rng = np.random.default_rng(0)
        qpos = np.repeat(st.qpos0[None], B, 0)
        qpos[:, st.robot.index.qpos_joints] += rng.normal(scale=0.02, size=(B, st.robot.index.n))
        qvel = rng.normal(scale=0.05, size=(B, st.robot.index.nv))
        state0 = jax.jit(st.loop.init)(jnp.asarray(st.qpos0, dtype))
        state = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (B, *x.shape)), state0)
        tick = round(SYNTHETIC_TIME_S / st.loop.cfg.control_dt)
        return [dict(tick=tick, qpos=jnp.asarray(qpos, dtype), qvel=jnp.asarray(qvel, dtype), state=state)]
    qpos, qvel, state = loop_run_inputs(st, args.loop_envs, args.push_onset, args.push_duration)
    rows = np.arange(B) % args.loop_envs  # the loop's environments tiled to the batch
    return [
        dict(
            tick=k,
            qpos=jnp.asarray(qpos[rows, k], dtype),
            qvel=jnp.asarray(qvel[rows, k], dtype),
            state=jax.tree_util.tree_map(lambda x, k=k: jnp.asarray(x[rows, k]), state),
        )
        for k in args.ticks
    ]


def trace_tick(program, args: tuple, where: pathlib.Path, batch: int) -> dict:
    """The whole tick's ops per source file, function, opcode and op (trace_summary.py), from TRACE_CALLS calls
    traced into ``where``, and that program's untraced wall time (``wall_us_per_env``); {"error": ...} where the
    trace has none of its ops (the timings stand without it). On a
    GPU the tick is compiled for the trace without XLA's command buffers: inside a CUDA graph a kernel loses its HLO
    op in the trace (openxla/xprof issue 3070)."""
    import jax
    from trace_summary import summarize

    lowered = program.lower(*args)
    options = {"xla_gpu_enable_command_buffer": ""} if jax.default_backend() == "gpu" else None
    try:
        compiled, command_buffers = lowered.compile(compiler_options=options), "off" if options else "n/a"
    except Exception as err:  # an XLA that refuses the option: the default program, attributed as far as it goes
        compiled, command_buffers = lowered.compile(), f"default ({type(err).__name__})"
    # The traced program's own wall time, untraced: beside whole_tick (the default program) it says what XLA's
    # command buffers change (on a GPU they can cost: a CUDA graph updated where buffers moved).
    wall = {"wall_us_per_env": round(1e6 * timed(compiled, *args, repeats=TRACE_CALLS) / batch, 3)}
    with jax.profiler.trace(str(where), create_perfetto_trace=True):
        for _ in range(TRACE_CALLS):
            jax.block_until_ready(compiled(*args))
    try:
        return {
            "command_buffers": command_buffers,
            **wall,
            **summarize(where, compiled.as_text(), calls=TRACE_CALLS, batch=batch),
        }
    except (OSError, ValueError) as err:
        return {"command_buffers": command_buffers, **wall, "error": f"{type(err).__name__}: {err}"}


def profile_group(st, fns: dict, group: dict, args, trace: str | None = None) -> dict:
    """The stages' µs per environment and the branch diagnostics of one group of states."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from wbc_jax.sim import physics

    loop, dtype, B, reps = st.loop, st.dtype, args.batch, args.repeats
    q, v, state, k = group["qpos"], group["qvel"], group["state"], jnp.asarray(group["tick"], jnp.int32)
    per_env = (0, 0, 0, None)  # the tick k is the batch's, as in the loop's scan
    diag = staged(loop, fns["diagnostics"], per_env)(q, v, state, k)
    vt = staged(loop, loop.terms)
    t = vt(q, v)
    vtt = staged(loop, fns["torque_law"], (0, 0, None))
    tt = vtt(t, state, k)
    inputs = staged(loop, fns["force_inputs"], (0, None, 0))(t, k, diag["Ldot_star"])
    us = lambda s: round(1e6 * s / B, 3)  # noqa: E731
    figures = {
        "dynamics_terms": us(timed(vt, q, v, repeats=reps)),
        "torque_law": us(timed(vtt, t, state, k, repeats=reps)),
        "force_distribution": us(timed(staged(loop, fns["distribution"]), tt, state, *inputs, repeats=reps)),
        # Under vmap the soft QP runs for the whole batch where some environment needs it
        # (batch_any); the difference between these two figures is what that costs.
        "force_distribution_first_qp_only": us(timed(staged(loop, fns["first_qp"]), tt, state, *inputs, repeats=reps)),
    }
    vw = staged(loop, fns["tick"], per_env)
    figures["whole_tick"] = us(timed(vw, q, v, state, k, repeats=reps))
    # Ten physics steps of the same batch from its postures, for scale (a tick holds 10).
    m = physics.device_model(st.robot.mj_model, loop.backend, loop.cfg.physics)
    tau = jnp.zeros(st.robot.mj_model.nu, dtype)
    xfrc = jnp.zeros((st.robot.mj_model.nbody, 6), dtype)

    def ten_steps(qp):
        d = physics.device_data(st.robot.mj_model, loop.backend, loop.cfg.physics, qp, dtype, batch=B)
        return jax.lax.scan(lambda dd, _: (physics.step(m, dd, tau, xfrc), None), d, None, length=10)[0].qpos

    figures[f"physics_10_steps_{loop.backend}"] = us(timed(staged(loop, ten_steps), q, repeats=reps))
    traced = trace_tick(vw, (q, v, state, k), pathlib.Path(trace) / f"tick_{int(group['tick'])}", B) if trace else None
    uncertified = ~np.asarray(diag["certified"])
    steps = np.asarray(diag["newton_steps"])
    return {
        "tick": int(group["tick"]),
        "time_s": round(group["tick"] * loop.cfg.control_dt, 4),
        "us_per_env": figures,
        "projector_uncertified_fraction": float(uncertified.mean()),
        "projector_eigh_branch_taken": bool(uncertified.any()),
        "qp_newton_steps": {"mean": round(float(steps.mean()), 3), "max": int(steps.max())},
        "qp_infeasible_fraction": float(np.mean(diag["qp_infeasible"])),
        "soft_qp_fraction": float(np.mean(diag["soft_qp"])),
        "soft_qp_branch_taken": bool(np.any(diag["soft_qp"])),
        "stage_tau_error_nm": float(np.max(diag["tau_error"])),
        **({"trace": traced} if traced else {}),
    }


def main(argv=None) -> dict:
    args = parse_args(argv)  # bad flags refused before anything compiles
    from loop_timing import PUSH_MAGNITUDE, make_setup

    from wbc_jax.core import io, provenance
    from wbc_jax.sim import runner

    runner.enable_compilation_cache()
    # benchmark.py's closed loop (the JAX engine: the states are recorded), at the scale step's backend.
    qp_flags = dict(
        qp_warm_start=args.qp_warm_start,
        qp_unrolled_steps=args.qp_unrolled_steps,
        qp_engine=args.qp_engine,
        mass_solve_engine=args.mass_solve_engine,
        ritz_engine=args.ritz_engine,
    )
    st = make_setup("jax", args.horizon, None, **qp_flags)
    fns = stage_functions(st)
    groups = state_groups(st, args)
    if args.backend != "jax":
        st = make_setup(args.backend, args.horizon, None, **qp_flags)
    result = {
        "batch": args.batch,
        "qp_warm_start": args.qp_warm_start,
        "qp_unrolled_steps": args.qp_unrolled_steps,
        "qp_engine": args.qp_engine,
        "mass_solve_engine": args.mass_solve_engine,
        "ritz_engine": args.ritz_engine,
        "device": provenance.device_label(),
        "dtype": str(st.dtype),
        "matmul_precision": st.loop.cfg.matmul_precision,
        "states": args.states,
        "groups": [profile_group(st, fns, g, args, args.trace) for g in groups],
    }
    if args.states == "loop":
        result["loop"] = {
            "envs": args.loop_envs,
            "horizon_s": args.horizon,
            "push": {"magnitude_n": PUSH_MAGNITUDE, "onset_s": args.push_onset, "duration_s": args.push_duration},
            "azimuths": "evenly over 360 deg (benchmarks/loop_timing.push_batch)",
            "engine": "jax",
        }
    stages = result["groups"][0]["us_per_env"]
    result["us_per_env"] = {
        s: round(sum(g["us_per_env"][s] for g in result["groups"]) / len(groups), 3) for s in stages
    }
    result["provenance"] = provenance.record(argv=provenance.script_argv(__file__, argv))
    io.atomic_write_json(pathlib.Path(args.out) / "profile_tick.json", result)
    print(json.dumps(result), flush=True)
    return result


if __name__ == "__main__":
    main()
