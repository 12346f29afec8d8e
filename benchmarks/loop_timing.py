"""The timed parts of ``benchmarks/benchmark.py``: the stand task's closed loop on a batch of pushes
(:func:`time_closed_loop`) and the same physics with the torques held (:func:`time_physics_only`).

Imported from the benchmarks/ folder (``import loop_timing``), as ``baseline_cpu``; heavy imports
(JAX, wbc_jax) stay inside functions, so that run_parallel's worker processes stay JAX-free."""

from __future__ import annotations

import time

PUSH_MAGNITUDE = 40.0  # N, horizontal, azimuths spread over 360 deg


def add_qp_arguments(parser, recorded_loop: bool = False, engine_default: str = "auto") -> None:
    """``--qp-unrolled-steps``, ``--qp-engine``, ``--mass-solve-engine`` and ``--ritz-engine`` (ControllerConfig's) on
    a benchmark's parser; check them after parsing with :func:`check_qp_arguments`. ``recorded_loop``: say that they
    also hold in the loop the states come from (profile_tick.py). ``engine_default``: the QP's and the M solve's
    default, ``auto`` (the controller's own: the engines it names on this machine) or ``jax``."""
    from wbc_jax.control import qp

    also = ", in the recorded loop too" if recorded_loop else ""
    parser.add_argument(
        "--qp-unrolled-steps",
        type=int,
        default=0,
        help="the force QP's first Newton steps written out before its while loop (ControllerConfig.qp_unrolled_steps)"
        + also,
    )
    parser.add_argument(
        "--qp-engine",
        choices=qp.ENGINE_CHOICES,
        default=engine_default,
        help="the force QP's solver (ControllerConfig.qp_engine; auto: the controller's default, "
        "qp.resolve_engine; warp: the interior point as one Warp kernel, "
        "warp_active_set: the dual active-set method as one; eiquadprog: that method by eiquadprog on the CPU)" + also,
    )
    from wbc_jax.control.torques import MASS_SOLVE_CHOICES, RITZ_ENGINES

    parser.add_argument(
        "--mass-solve-engine",
        choices=MASS_SOLVE_CHOICES,
        default=engine_default,
        help="who factorises M and solves with it in the torque law (ControllerConfig.mass_solve_engine; auto: the "
        "controller's default, warp on a GPU with warp-lang; warp: one "
        "Warp tile kernel, a block per environment, wbc_jax/control/cholesky_warp.py)" + also,
    )
    parser.add_argument(
        "--ritz-engine",
        choices=RITZ_ENGINES,
        default="jax",
        help="who computes the postural projector's Ritz decomposition (ControllerConfig.ritz_engine; warp: one Warp "
        "kernel, a thread per environment, wbc_jax/control/ritz_warp.py)" + also,
    )


def add_warp_terms_argument(parser) -> None:
    """``--warp-terms`` (PhysicsConfig.warp_terms) on a benchmark's parser."""
    from wbc_jax.sim.warp_split import TERMS_CHOICES

    parser.add_argument(
        "--warp-terms",
        choices=TERMS_CHOICES,
        default="auto",
        help="on the warp backend, the controller's dynamics terms computed in MJX-JAX (jax) or read off MuJoCo "
        "Warp's first phase of the tick's first step (step1, wbc_jax/sim/warp_split.py); auto (default): step1 there; "
        "other backends: jax",
    )


def check_qp_arguments(parser, args) -> None:
    """Refuse, as argparse does, what :func:`add_qp_arguments`' flags cannot take."""
    from wbc_jax.control.qp import DEFAULT_ITERATIONS  # the controller's QP budget

    if not 0 <= args.qp_unrolled_steps <= DEFAULT_ITERATIONS:
        parser.error(
            f"--qp-unrolled-steps must be from 0 to {DEFAULT_ITERATIONS} (the QP's iterations), got {args.qp_unrolled_steps}"
        )
    if args.qp_engine not in ("jax", "auto") and args.qp_unrolled_steps:
        parser.error(
            f"--qp-engine {args.qp_engine} takes --qp-unrolled-steps 0 (the Warp kernel has no while loop to unroll)"
        )
    from wbc_jax.control.qp import ACTIVE_SET_ENGINES

    if args.qp_engine in ACTIVE_SET_ENGINES and getattr(args, "qp_warm_start", False):
        parser.error(f"--qp-engine {args.qp_engine} takes no --qp-warm-start (the active-set method starts cold)")


def make_setup(
    backend: str,
    horizon: float,
    iterations: int | None,
    *,
    record: bool = False,
    qp_warm_start: bool = False,
    qp_unrolled_steps: int = 0,
    qp_engine: str = "jax",
    warp_terms: str = "jax",
    mass_solve_engine: str = "jax",
    ritz_engine: str = "jax",
):
    """The stand task's closed loop on ``backend`` (default gains, the two feet; ``qp_warm_start``: the
    controller's force QP warm-started, ``ControllerConfig.qp_warm_start``; ``qp_unrolled_steps``: its first
    Newton steps written out before the while loop, ``ControllerConfig.qp_unrolled_steps``; ``qp_engine``:
    its solver, ``ControllerConfig.qp_engine``; ``warp_terms``: where the controller's dynamics terms come from on
    the warp backend, ``PhysicsConfig.warp_terms``; ``mass_solve_engine``, ``ritz_engine``: ControllerConfig's)."""
    from wbc_jax.control.controller import ControllerConfig
    from wbc_jax.sim import physics, scenario
    from wbc_jax.sim.state import SimConfig

    sim = SimConfig(
        record=record,
        physics=physics.PhysicsConfig(backend=backend, solver_iterations=iterations, warp_terms=warp_terms),
    )
    controller = ControllerConfig(
        qp_warm_start=qp_warm_start,
        qp_unrolled_steps=qp_unrolled_steps,
        qp_engine=qp_engine,
        mass_solve_engine=mass_solve_engine,
        ritz_engine=ritz_engine,
    )
    return scenario.setup("stand", duration=horizon, sim=sim, controller=controller)


def push_batch(st, batch: int, onset: float, duration: float):
    """A Scenario batch: one PUSH_MAGNITUDE N horizontal push per environment, azimuths evenly
    over 360 deg (sweep.build_scenarios), nominal plant, default gains."""
    import numpy as np

    from wbc_jax.jobs import sweep, sweep_config

    cfg = sweep_config.SweepConfig(
        magnitudes=(PUSH_MAGNITUDE,),
        directions=tuple(float(a) for a in np.linspace(0, 360, batch, endpoint=False)),
        horizon=st.loop.cfg.duration,
        push_onset=onset,
        push_duration=duration,
        chunk_size=batch,
    )
    scen, _ = sweep.build_scenarios(cfg, st.gains, st.robot.index.n, st.dtype)
    return scen


def peak_memory() -> int | None:
    import jax

    stats = jax.devices()[0].memory_stats() or {}
    return stats.get("peak_bytes_in_use")


def time_closed_loop(st, scen, push_end: float, repeats: int = 1) -> dict:
    """Compile + first run, then ``repeats`` timed runs of the same batch (runner.run,
    compiled programs cached on the setup); the fastest counts."""
    import numpy as np

    from wbc_jax.sim import metrics as metrics_lib
    from wbc_jax.sim import runner

    first = runner.run(st, scen)
    timed = [runner.run(st, scen) for _ in range(repeats)]
    run_s = min(r.run_s for r in timed)
    B = int(np.asarray(scen.friction).shape[0])
    steps = B * st.loop.n_ticks * st.loop.n_sub
    cols = metrics_lib.summarize(timed[-1].metrics, push_end)
    return {
        "compile_s": round(first.compile_s, 2),
        "first_run_s": round(first.run_s, 4),
        "run_s": round(run_s, 4),
        "closed_loop_steps_per_s": steps / run_s,
        "control_ticks_per_s": B * st.loop.n_ticks / run_s,
        # Names of constants.METRIC_NAMES: the rates of its booleans, medians of the others.
        "survived_rate": float(np.mean(cols["survived"])),
        "upright_rate": float(np.mean(cols["upright"])),
        "com_max_err_m_median": float(np.median(cols["com_max_err_m"])),
        "qp_infeasible_ticks_total": int(np.sum(cols["qp_infeasible_ticks"])),
    }


def hold_torques(st):
    """(nu,) torques to hold in the physics-only run: the controller's first tick at the initial
    posture (NumPy baseline, C MuJoCo: no compilation), so that the robot stands as in the loop."""
    import baseline_cpu
    import mujoco
    import numpy as np

    spec = baseline_cpu.spec_from_setup(st)
    ctrl = baseline_cpu.NumpyController(spec)
    d = mujoco.MjData(spec.mj_model)
    d.qpos[:] = spec.qpos0
    mujoco.mj_forward(spec.mj_model, d)
    out, _ = ctrl([d], baseline_cpu.gains_to_numpy(st.gains, 1, spec.n), spec.reference(0), ctrl.init_state(1))
    tau = np.zeros(spec.mj_model.nu)
    tau[spec.actuators] = out["tau"][0]
    return tau


def time_physics_only(st, batch: int, tau, repeats: int = 1) -> dict:
    """The closed loop's physics alone: ``batch`` environments from the initial posture, the
    torques ``tau`` held, no push, the same number of steps (MJX: one jitted, vmapped scan of
    physics.step on device_model/device_data; C MuJoCo: physics.HostBatch, as the host loop);
    the fastest of ``repeats`` timed runs counts."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from wbc_jax.sim import physics

    loop, robot = st.loop, st.robot
    cfg = loop.cfg.physics
    steps = loop.n_ticks * loop.n_sub
    qpos = np.repeat(np.asarray(st.qpos0, float)[None], batch, 0)
    if loop.backend == "mujoco":
        model = physics.solver_mj_model(robot.mj_model, cfg)
        ctrl = np.repeat(np.asarray(tau, float)[None], batch, 0)
        xfrc = np.zeros((batch, loop.n_sub, robot.mj_model.nbody, 6))
        times = []
        for _ in range(repeats):
            host = physics.HostBatch(model, qpos)
            try:
                t0 = time.perf_counter()
                for _ in range(loop.n_ticks):
                    host.step(ctrl, xfrc)
                times.append(time.perf_counter() - t0)
            finally:
                host.close()
        return {
            "physics_only_steps_per_s": batch * steps / min(times),
            "physics_only_compile_s": 0.0,
            "physics_only_threads": host.threads,
        }
    dtype = st.dtype
    m = physics.device_model(robot.mj_model, loop.backend, cfg)
    ctrl = jnp.asarray(tau, dtype)
    xfrc = jnp.zeros((robot.mj_model.nbody, 6), dtype)

    def env(q):
        d = physics.device_data(robot.mj_model, loop.backend, cfg, q, dtype, batch=batch)
        d, _ = jax.lax.scan(lambda dd, _: (physics.step(m, dd, ctrl, xfrc), None), d, None, length=steps)
        return d.qpos

    q = jnp.asarray(qpos, dtype)
    t0 = time.perf_counter()
    with jax.default_matmul_precision(loop.cfg.matmul_precision):  # as the closed loop's physics
        fn = jax.jit(jax.vmap(env)).lower(q).compile()
    compile_s = time.perf_counter() - t0
    jax.block_until_ready(fn(q))  # warm
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(q))
        times.append(time.perf_counter() - t0)
    return {"physics_only_steps_per_s": batch * steps / min(times), "physics_only_compile_s": round(compile_s, 2)}
