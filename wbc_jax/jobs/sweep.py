"""Batched push-recovery sweeps: scenarios -> batched closed loops -> table.

A scenario per environment: one push on a body (azimuth, elevation, magnitude, duration, onset),
a gain set, initial joint noise, floor friction and a mass scale of the plant. The batch is
split into chunks of one compiled shape, each written atomically to a Parquet part listed in the
run's manifest, so a run larger than memory resumes where it stopped; each chunk runs on the
setup's physics backend (MJX: sharded over a ``jax.sharding.Mesh`` of all devices along the batch
axis; multi-host: call ``jax.distributed.initialize()`` first and the same code shards over the
global mesh. C MuJoCo: the jitted controller and threaded C physics).
"""

from __future__ import annotations

import dataclasses
import math
import pathlib

import jax
import numpy as np

from wbc_jax.control.controller import ControllerConfig
from wbc_jax.control.gains import Gains, default_gains, gains_from_dict, gains_to_dict, load_gains, validate_gains
from wbc_jax.core import constants, io, loader, options, provenance
from wbc_jax.core.options import check_options
from wbc_jax.jobs import chunks, runs
from wbc_jax.jobs.sweep_config import SweepConfig, default_config
from wbc_jax.jobs.sweep_table import summarize_table
from wbc_jax.robot import model as model_lib
from wbc_jax.robot.robots import describe
from wbc_jax.sim import metrics as metrics_lib
from wbc_jax.sim import physics, runner, scenario, watchdog
from wbc_jax.sim.state import Push, Scenario, SimConfig


def gain_sets(base: Gains, count: int, scale_range, rng: np.random.Generator) -> list:
    """``count`` gain sets: the base one, then per-group log-uniform scalings of it."""
    sets = [base]
    lo, hi = np.log(scale_range[0]), np.log(scale_range[1])
    for k in range(1, count):
        scaled = Gains(
            **{name: np.asarray(getattr(base, name)) * np.exp(rng.uniform(lo, hi)) for name in constants.GAIN_FIELDS}
        )
        try:  # a scaling can take a gain out of its range: named before anything compiles
            validate_gains(scaled, np.asarray(base.kp_postural).shape[-1])
        except ValueError as err:
            raise ValueError(f"--gain-scale-range {list(scale_range)}: gain set {k}: {err}") from None
        sets.append(scaled)
    return sets


def scenarios_at(
    cfg: SweepConfig, sets: list, mag, azi, gset, friction, mass_scale, joint_offset, dtype=np.float32
) -> tuple[Scenario, dict]:
    """Scenarios (leading axis B) of pushes of magnitude ``mag`` (B,) N at azimuth ``azi`` (B,) deg
    (the config's elevation, duration, onset, body) with gain set ``gset`` (B,) of ``sets``, and the
    plant and initial-posture perturbations given. Returns (Scenario, dict of numpy columns)."""
    mag, azi, gset = np.asarray(mag, float), np.asarray(azi, float), np.asarray(gset, int)
    B = mag.size
    el = np.deg2rad(cfg.elevation)
    direction = np.stack(
        [np.cos(np.deg2rad(azi)) * np.cos(el), np.sin(np.deg2rad(azi)) * np.cos(el), np.full(B, np.sin(el))], axis=1
    )
    stacked = {name: np.stack([np.asarray(getattr(sets[g], name)) for g in gset]) for name in constants.GAIN_FIELDS}
    columns = {
        "magnitude_n": mag,
        "azimuth_deg": azi,
        "elevation_deg": np.full(B, cfg.elevation),
        "impulse_ns": mag * cfg.push_duration,
        "gain_set": gset,
        "friction": np.asarray(friction, float),
        "mass_scale": np.asarray(mass_scale, float),
    }
    scen = Scenario(
        push=Push(
            force=(mag[:, None] * direction)[:, None, :].astype(dtype),
            onset=np.full((B, 1), cfg.push_onset, dtype),
            duration=np.full((B, 1), cfg.push_duration, dtype),
            body=np.full((B, 1), -1, np.int32),  # the setup's push body, cfg.body
        ),
        gains=Gains(**{k: v.astype(dtype) for k, v in stacked.items()}),
        joint_offset=np.asarray(joint_offset).astype(dtype),
        friction=columns["friction"].astype(dtype),
        mass_scale=columns["mass_scale"].astype(dtype),
    )
    return scen, columns


def build_scenarios(cfg: SweepConfig, base_gains: Gains, n: int, dtype=np.float32):
    """The full grid magnitude x direction x gain set, with seeded random perturbations.

    Returns (Scenario with a leading axis of size cfg.size, dict of numpy columns)."""
    rng = np.random.default_rng(cfg.seed)
    sets = gain_sets(base_gains, cfg.gain_sets, cfg.gain_scale_range, rng)
    mag, azi, gset = np.meshgrid(
        np.asarray(cfg.magnitudes, float), np.asarray(cfg.directions, float), np.arange(cfg.gain_sets), indexing="ij"
    )
    B = mag.size
    friction, mass_scale = rng.uniform(*cfg.friction, B), rng.uniform(*cfg.mass_scale, B)
    joint_offset = rng.normal(scale=cfg.joint_noise, size=(B, n)) if cfg.joint_noise else np.zeros((B, n))
    return scenarios_at(cfg, sets, mag.ravel(), azi.ravel(), gset.ravel(), friction, mass_scale, joint_offset, dtype)


def make_setup(
    cfg: SweepConfig,
    base_gains: Gains | None = None,
    *,
    record: bool = False,
    controller: ControllerConfig | None = None,
) -> scenario.Setup:
    """The closed loop of a sweep's environments (replays with ``record``; the limit job composes a
    traced loop from it). ``controller``: further controller settings (forces, postural, angular_weight_soft
    from ``cfg``)."""
    scene = scenario.load_scene(cfg.robot, cfg.controller.tasks)
    sim = SimConfig(
        record=record,
        push_body=cfg.body,
        perturb_plant=cfg.perturbs_plant,
        host_loop=cfg.host_loop,
        # the engine as it resolves here: "auto" and the engine it picks build the same programs (one cache entry)
        physics=physics.PhysicsConfig(
            backend=physics.resolve_backend(cfg.backend),
            solver_iterations=cfg.solver_iterations,
            warp_graph_mode=cfg.warp_graph_mode,
            warp_graph_cache=cfg.warp_graph_cache,
        ),
    )
    return scenario.setup(
        cfg.task,
        duration=cfg.horizon,
        controller=cfg.controller_config(controller),
        sim=sim,
        gains=base_gains,
        scene=scene,
    )


def base_gains(cfg: SweepConfig, n: int, dtype) -> Gains:
    gains = load_gains(cfg.gains, n, dtype) if cfg.gains else default_gains(describe(cfg.robot), dtype)
    validate_gains(gains, n)
    return gains


def fingerprint(cfg: SweepConfig) -> dict:
    return cfg.fingerprint()


def run_sweep(cfg: SweepConfig | None = None, *, progress: bool = True, **overrides) -> dict:
    """Run (or resume) a sweep into ``cfg.out``: parts/*.parquet, results.parquet, summary.json, plots.

    ``overrides``: fields of :class:`SweepConfig`. A resumed run must have the same fingerprint
    (config, input file contents, model, version); each part file is checked against the env
    range it must hold and recomputed if it does not."""
    import pandas as pd

    cfg = options.replace(default_config() if cfg is None else cfg, **overrides)
    cfg.check()
    devices = runner.batch_devices() if physics.resolve_backend(cfg.backend) != "mujoco" else jax.devices("cpu")[:1]
    local = [d for d in devices if d.process_index == jax.process_index()]  # the devices this process runs on
    check_simulated_stall(cfg, math.ceil(cfg.size / cfg.batch_size), len(local))
    out = pathlib.Path(cfg.out)
    dtype = scenario.float_dtype()
    robot = model_lib.load_robot(cfg.robot)
    base = base_gains(cfg, robot.index.n, dtype)
    st = make_setup(cfg, base)
    runner.check_memory(st, cfg.batch_size, envs=cfg.size, queue=cfg.queue, flag="--chunk-size")
    scen, columns = build_scenarios(cfg, base, robot.index.n, dtype)
    # With several processes (jax.distributed), each computes every chunk with its devices' share
    # and gathers the results; the first process writes them.
    writer = jax.process_index() == 0
    if writer:
        runs.claim_output_dir(out, "sweep", cfg.fingerprint(), resume=True)

    timeline: list[dict] = []

    def record_timeline(watch, host_s: float, wall_s: float, todo: list[bool]) -> None:
        nonlocal timeline
        timeline += watchdog.timeline_rows(watch, host_s, wall_s)
        _write_timeline(out, st.backend, devices, timeline, todo)

    ran = chunks.run_chunks(
        st,
        scen,
        columns,
        out / "parts",
        batch=cfg.batch_size,
        push_end=cfg.push_onset + cfg.push_duration,
        queue=cfg.queue,
        watch=cfg.watchdog,
        timeline=record_timeline,
        writer=writer,
        progress=progress,
        label="sweep",
    )
    tables, compile_s, run_s, done_envs, started = ran.tables, ran.compile_s, ran.run_s, ran.done_envs, ran.started
    replaced = ran.replaced
    if writer and done_envs == 0 and _finished(out):
        # A re-run of a finished run: its summary (the timings measured when it ran) stays as it is.
        stored = loader.read_json(out / "summary.json", "sweep summary")
        stored["envelope"] = {float(az): e for az, e in stored["envelope"].items()}  # keyed as summarize_table keys it
        return stored
    table = pd.concat(tables, ignore_index=True)
    if writer:
        io.atomic_write_parquet(out / "results.parquet", table)
        runs.record_output(out / "results.parquet")
    steps_per_env = st.loop.n_ticks * st.loop.n_sub
    summary = summarize_table(table, cfg, st.robot)
    summary.update(
        {
            "config": options.flat_dict(cfg),
            "backend": st.backend,
            "survival_criterion": constants.SURVIVAL_CRITERION,
            "device": provenance.device_label(),
            "n_devices": len(devices),
            "versions": {
                "jax": jax.__version__,
                "mujoco": __import__("mujoco").__version__,
                "wbc_jax": __import__("wbc_jax").__version__,
            },
            # Seconds of this process's simulation (None: nothing was simulated, every part was on disk).
            "compile_s": round(compile_s, 2) if done_envs else None,
            # from the process's start to the first chunk's first tick (None: every chunk was on disk)
            "started_s": None if started is None else round(started - provenance.process_started(), 2),
            "run_s": round(run_s, 2) if done_envs else None,
            # Steps of the grid run now per second of run (with a queue, fewer were simulated).
            "physics_steps_per_s": (done_envs * steps_per_env / run_s) if run_s > 0 else None,
            # Over every part, those of an earlier (interrupted) run included; resumed_envs came from there.
            "physics_steps_simulated": int(table["ticks_simulated"].sum()) * st.loop.n_sub,
            "resumed_envs": int(cfg.size - done_envs),
            "recomputed_parts": replaced,
            "gains": gains_to_dict(base),
            "provenance": provenance.record({"gains": cfg.gains, "tasks": cfg.controller.tasks}),
        }
    )
    if writer:
        io.atomic_write_json(out / "summary.json", summary)
        runs.record_output(out / "summary.json")
        from wbc_jax.report import sweep_plots  # matplotlib: imported after the simulation

        sweep_plots.survival_map(table, out / "survival.png", summary["envelope"])
        sweep_plots.envelope(table, summary["envelope"], out / "envelope.png")
    return summary


def check_simulated_stall(cfg: SweepConfig, n_chunks: int, n_devices: int) -> None:
    """``--simulate-stall CHUNK DEVICE`` names a chunk and a device of this run (else it would test nothing)."""
    if cfg.simulate_stall is None:
        return
    chunk, device = cfg.simulate_stall
    if chunk >= n_chunks or device >= n_devices:
        raise ValueError(
            f"--simulate-stall {chunk} {device}: this run has chunks 0..{n_chunks - 1} and devices 0..{n_devices - 1}"
        )


def _write_timeline(out: pathlib.Path, backend: str, devices: list, rows: list[dict], todo: list[bool]) -> None:
    """timeline.json: one row per chunk run by this process and device (:func:`watchdog.timeline_rows`),
    each device's totals, and the chunks read back from disk instead."""
    totals: dict = {}
    for row in rows:
        device = totals.setdefault(row["device"], dict.fromkeys(watchdog.TIMED, 0.0))
        for key in watchdog.TIMED:
            device[key] = round(device[key] + row[key], 4)
    io.atomic_write_json(
        out / "timeline.json",
        {
            "backend": backend,
            "device": provenance.device_label(),
            "devices": [watchdog.device_label(d) for d in devices],
            "chunks_on_disk": [c for c, t in enumerate(todo) if not t],
            "rows": rows,
            "totals_by_device": totals,
        },
    )


def _finished(out: pathlib.Path) -> bool:
    """Are the run's table and summary on disk, as it wrote them (and its plots)?"""
    tables = ("results.parquet", "summary.json")
    return all(runs.output_changed(out / name) is None for name in tables) and all(
        (out / name).exists() for name in ("survival.png", "envelope.png")
    )


def load_sweep(run_dir) -> tuple[SweepConfig, dict]:
    """The config and summary of a finished sweep in ``run_dir`` (clear errors when not)."""
    run_dir = pathlib.Path(run_dir)
    if not run_dir.exists():
        raise FileNotFoundError(f"{run_dir} does not exist")
    if not run_dir.is_dir():
        raise ValueError(f"{run_dir} is a file; give the folder of a push sweep")
    path = run_dir / "summary.json"
    if not path.exists():
        raise FileNotFoundError(f"{path} is missing: the sweep has not finished; rerun it with the same --out")
    summary = loader.read_json(path, "sweep summary")
    foreign = f"{path} is not the summary of a push sweep (wbc-jax push-sweep writes it)"
    if not (
        isinstance(summary, dict)
        and isinstance(summary.get("config"), dict)
        and isinstance(summary.get("gains"), dict)
        and summary.get("backend") in physics.BACKENDS
    ):
        raise ValueError(f"{foreign}: it lacks the sweep's config, gains or backend")
    values = {k: tuple(v) if isinstance(v, list) else v for k, v in summary["config"].items()}
    try:
        cfg = options.from_flat(SweepConfig, values)  # a summary without "robot": the default robot's
        check_options(options.replace(cfg, out=None, gains=None, tasks=None))  # files: checked by the replay
    except (TypeError, ValueError) as err:
        raise ValueError(f"{foreign}: its config does not hold ({err})") from None
    return cfg, summary


def replay_env(run_dir, env: int, *, backend: str | None = None):
    """Re-simulate env ``env`` of a finished push sweep, recording its trajectory.

    The scenario is rebuilt deterministically from the stored config, seed and base gains
    (:func:`build_scenarios`): same push, gain set, joint offset, friction and mass scale, on the
    sweep's backend (or ``backend``). Run in the dtype the sweep ran in, the replay equals the
    sweep's metrics (tests/test_viz.py).

    Returns:
      (setup, trajectory dict of numpy (T, ...), replay metrics dict, the sweep's row dict).
    """
    import pandas as pd

    cfg, summary = load_sweep(run_dir)
    results = pathlib.Path(run_dir) / "results.parquet"
    if not results.exists():
        raise FileNotFoundError(f"{results} is missing: the sweep has not finished; rerun it with the same --out")
    table = pd.read_parquet(results)
    if not (isinstance(env, int) and 0 <= env < len(table)):
        raise ValueError(f"env {env} is out of range: this sweep has envs 0..{len(table) - 1}")
    cfg = dataclasses.replace(cfg, backend=backend or summary.get("backend", cfg.backend))
    dtype = scenario.float_dtype()
    robot = model_lib.load_robot(cfg.robot)
    base = gains_from_dict(summary["gains"], robot.index.n, dtype)
    scen, columns = build_scenarios(cfg, base, robot.index.n, dtype)
    row = table[table["env"] == env].iloc[0].to_dict()
    for key in ("magnitude_n", "azimuth_deg", "gain_set"):
        if not np.isclose(columns[key][env], row[key]):
            raise ValueError(
                f"the rebuilt scenario of env {env} differs from the sweep's ({key}); "
                "the sweep was written by another version"
            )
    st = make_setup(cfg, base, record=True)
    one = jax.tree_util.tree_map(lambda x: np.asarray(x)[env : env + 1], scen)
    result = runner.run(st, one)
    traj = {name: np.asarray(v)[0] for name, v in dataclasses.asdict(result.records).items()}
    metrics = metrics_lib.summarize(
        jax.tree_util.tree_map(lambda x: x[0], result.metrics), cfg.push_onset + cfg.push_duration
    )
    return st, traj, metrics, row
