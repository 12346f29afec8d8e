"""[experiments] Batched push-recovery sweeps: scenarios -> vmapped, sharded rollouts -> table.

A scenario per environment: one push on a body (azimuth, elevation, magnitude, duration, onset),
a gain set, initial joint noise, floor friction and a mass scale of the plant. The batch is a
pytree with a leading axis; it is split into chunks (each written atomically to a Parquet part,
so a run larger than memory resumes where it stopped) and each chunk is sharded over a
``jax.sharding.Mesh`` of all local devices along the batch axis (one CPU, one GPU or many;
multi-host: call ``jax.distributed.initialize()`` first and the same code shards over the global
mesh).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from wbc_jax import balance, io
from wbc_jax import controller as ctrl_lib
from wbc_jax import model as model_lib
from wbc_jax import rollout as rollout_lib
from wbc_jax.types import Array, pytree_dataclass


SWEEP_TASKS = ("stand", "one-foot")
# The one-foot task (references.make_schedule) balances on the left foot from 7 to 9 s.
ONE_FOOT_WINDOW = (7.0, 9.0)
SUPPORTS = ("two-feet", "left-foot")


@dataclasses.dataclass(frozen=True)
class SweepConfig:
    """What a sweep covers (all sizes small by default: a laptop CPU in a few minutes).

    Attributes:
      magnitudes: push forces (N). directions: azimuths (deg, 0 = +x forward, 90 = +y left).
      elevation: push elevation (deg). push_duration / push_onset: s. body: pushed body.
      gain_sets: number of gain sets (the first is the default; others scale it, seeded).
      gain_scale_range: log-uniform range of the per-group scale of the extra gain sets.
      joint_noise: std (rad) of the initial joint offsets. friction: floor friction range.
      mass_scale: range of the plant's mass scaling. horizon: s. task: balance task.
      forces / postural: controller variants. seed: RNG seed. chunk_size: envs per chunk.
      tasks_file: motion-task stack (JSON/YAML, as ``wbc-jax balance --tasks``); None: none.
    """

    magnitudes: tuple[float, ...] = (20.0, 40.0, 60.0, 80.0, 100.0, 120.0)
    directions: tuple[float, ...] = (0.0, 45.0, 90.0, 135.0, 180.0, 225.0, 270.0, 315.0)
    elevation: float = 0.0
    push_duration: float = 0.1
    push_onset: float = 0.5
    body: str = "chest"
    gain_sets: int = 1
    gain_scale_range: tuple[float, float] = (0.5, 2.0)
    joint_noise: float = 0.0
    friction: tuple[float, float] = (1.0, 1.0)
    mass_scale: tuple[float, float] = (1.0, 1.0)
    horizon: float = 2.0
    task: str = "stand"
    forces: str = "qp"
    postural: str = "stable"
    seed: int = 0
    chunk_size: int = 64
    solver_iterations: int | None = None
    tasks_file: str | None = None

    def __post_init__(self):
        if not self.magnitudes or not self.directions or self.gain_sets < 1:
            raise ValueError("the grid is empty: give at least one magnitude, direction, gain set")
        if any(not math.isfinite(m) or m < 0 for m in self.magnitudes):
            raise ValueError(f"push magnitudes must be finite and >= 0, got {self.magnitudes}")
        for name in ("push_duration", "push_onset", "horizon", "joint_noise"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {value}")
        if self.horizon <= self.push_onset + self.push_duration:
            raise ValueError("horizon must end after the push")
        if self.chunk_size < 1:
            raise ValueError(f"chunk_size must be >= 1, got {self.chunk_size}")
        if self.tasks_file is not None and not pathlib.Path(self.tasks_file).exists():
            raise FileNotFoundError(f"task file {self.tasks_file} does not exist")
        if self.task not in SWEEP_TASKS:
            raise ValueError(f"unknown sweep task {self.task!r}; valid: {list(SWEEP_TASKS)}")
        if self.task == "one-foot":
            lo, hi = ONE_FOOT_WINDOW
            if not (lo <= self.push_onset and self.push_onset + self.push_duration <= hi):
                raise ValueError(
                    f"one-foot sweeps push during the single-support phase {lo}-{hi} s of the "
                    f"one-foot task: push onset {self.push_onset} s + duration "
                    f"{self.push_duration} s is outside it (e.g. --push-onset 7.5 --horizon 9)"
                )
        lo, hi = self.friction
        if not 0 < lo <= hi:
            raise ValueError(f"friction range must be positive and ordered, got {self.friction}")
        lo, hi = self.mass_scale
        if not 0 < lo <= hi:
            raise ValueError(f"mass_scale range must be positive and ordered, got {self.mass_scale}")

    @property
    def size(self) -> int:
        return len(self.magnitudes) * len(self.directions) * self.gain_sets

    def key(self) -> str:
        """Hash of the sweep definition (resuming is refused if it changed), task file included."""
        definition = dataclasses.asdict(self)
        if self.tasks_file is not None:
            definition["tasks_file"] = pathlib.Path(self.tasks_file).read_text()
        return hashlib.sha256(json.dumps(definition, sort_keys=True).encode()).hexdigest()[:16]


@pytree_dataclass
class Scenario:
    """One environment's scenario (a leading batch axis in a sweep).

    push: :class:`rollout.Push` with one push; gains: :class:`controller.Gains`;
    joint_offset (n,) rad; friction (); mass_scale ().
    """

    push: rollout_lib.Push
    gains: ctrl_lib.Gains
    joint_offset: Array
    friction: Array
    mass_scale: Array


def gain_sets(base: ctrl_lib.Gains, count: int, scale_range, rng: np.random.Generator) -> list:
    """``count`` gain sets: the base one, then per-group log-uniform scalings of it."""
    sets = [base]
    lo, hi = np.log(scale_range[0]), np.log(scale_range[1])
    for _ in range(count - 1):
        scaled = {
            name: np.asarray(getattr(base, name)) * np.exp(rng.uniform(lo, hi))
            for name in ctrl_lib.GAIN_FIELDS
        }
        sets.append(ctrl_lib.Gains(**scaled))
    return sets


def build_scenarios(cfg: SweepConfig, base_gains: ctrl_lib.Gains, n: int, dtype=np.float32):
    """The full grid magnitude x direction x gain set, with seeded random perturbations.

    Returns (Scenario with a leading axis of size cfg.size, dict of numpy columns)."""
    rng = np.random.default_rng(cfg.seed)
    sets = gain_sets(base_gains, cfg.gain_sets, cfg.gain_scale_range, rng)
    mag, azi, gset = np.meshgrid(
        np.asarray(cfg.magnitudes, float), np.asarray(cfg.directions, float),
        np.arange(cfg.gain_sets), indexing="ij",
    )  # fmt: skip
    mag, azi, gset = mag.ravel(), azi.ravel(), gset.ravel()
    B = mag.size
    el = np.deg2rad(cfg.elevation)
    direction = np.stack(
        [np.cos(np.deg2rad(azi)) * np.cos(el), np.sin(np.deg2rad(azi)) * np.cos(el),
         np.full(B, np.sin(el))], axis=1,
    )  # fmt: skip
    force = mag[:, None] * direction
    stacked = {
        name: np.stack([np.asarray(sets[g].__getattribute__(name)) for g in gset])
        for name in ctrl_lib.GAIN_FIELDS
    }
    columns = {
        "magnitude_n": mag,
        "azimuth_deg": azi,
        "elevation_deg": np.full(B, cfg.elevation),
        "impulse_ns": mag * cfg.push_duration,
        "gain_set": gset,
        "friction": rng.uniform(*cfg.friction, B),
        "mass_scale": rng.uniform(*cfg.mass_scale, B),
    }
    joint_offset = rng.normal(scale=cfg.joint_noise, size=(B, n)) if cfg.joint_noise else np.zeros((B, n))
    scen = Scenario(
        push=rollout_lib.Push(
            force=force[:, None, :].astype(dtype),
            onset=np.full((B, 1), cfg.push_onset, dtype),
            duration=np.full((B, 1), cfg.push_duration, dtype),
        ),
        gains=ctrl_lib.Gains(**{k: v.astype(dtype) for k, v in stacked.items()}),
        joint_offset=joint_offset.astype(dtype),
        friction=columns["friction"].astype(dtype),
        mass_scale=columns["mass_scale"].astype(dtype),
    )
    return scen, columns


FLOOR_GEOM = 0  # the floor is the model's first geom (assets/build_icub_mjcf.py; tested)


def plant_model(mx, friction: Array, mass_scale: Array):
    """The simulated plant of one environment: floor friction (sliding) and scaled masses. Pairs
    with scene objects (a table) keep their own friction."""
    floor = (np.asarray(mx.pair_geom1) == FLOOR_GEOM) | (np.asarray(mx.pair_geom2) == FLOOR_GEOM)
    pair_friction = mx.pair_friction.at[floor, :2].set(friction)
    return mx.replace(
        pair_friction=pair_friction,
        body_mass=mx.body_mass * mass_scale,
        body_inertia=mx.body_inertia * mass_scale,
    )


def make_batched_runner(robot: model_lib.Robot, cfg: SweepConfig):
    """jit(vmap(env)) of the closed loop over a Scenario batch -> (Metrics, final CoM error).

    With a ``tasks_file`` that lists contacts, the robot is that file's scene (same robot name)."""
    stack = contact_set = qpos = None
    if cfg.tasks_file is not None:
        robot, stack, contact_set, qpos = balance.load_scenario(robot.index.robot, cfg.tasks_file)
    rollout, d0, _, consts, _ = balance.setup(
        robot, cfg.task, duration=cfg.horizon, forces=cfg.forces, postural=cfg.postural,
        sim=dict(record=False, push_body=cfg.body, solver_iterations=cfg.solver_iterations),
        stack=stack, contact_set=contact_set, qpos=qpos,
    )  # fmt: skip
    mx = robot.mjx_model
    idx = robot.index

    def env(scen: Scenario):
        qpos = d0.qpos.at[idx.qpos_joints].add(scen.joint_offset)
        d = d0.replace(qpos=qpos)
        plant = plant_model(mx, scen.friction, scen.mass_scale)
        metrics, _ = rollout(mx, d, scen.gains, consts, scen.push, mx_plant=plant)
        return metrics

    return jax.jit(jax.vmap(env)), rollout


_COMPILED: dict = {}  # (sweep key, robot, batch shape, devices) -> (compiled runner, rollout)


def run_batch(robot: model_lib.Robot, cfg: SweepConfig, scen: Scenario):
    """Closed loop over a Scenario batch, sharded over all devices, compiled once per shape.

    Returns (Metrics with a batch axis, rollout, seconds spent compiling (0 if cached))."""
    mesh = device_mesh()
    size = int(np.asarray(scen.friction).shape[0])
    sharded, _ = _shard(scen, mesh, size)
    key = (cfg.key(), robot.index.robot, sharded.friction.shape, mesh.devices.size)
    compile_s = 0.0
    if key not in _COMPILED:  # ahead-of-time, so that compilation is timed apart
        runner, rollout = make_batched_runner(robot, cfg)
        t0 = time.perf_counter()
        _COMPILED[key] = (runner.lower(sharded).compile(), rollout)
        compile_s = time.perf_counter() - t0
    compiled, rollout = _COMPILED[key]
    metrics = compiled(sharded)
    metrics = jax.tree_util.tree_map(lambda x: np.asarray(x)[:size], metrics)
    return metrics, rollout, compile_s


def device_mesh() -> Mesh:
    """1-D mesh over all (local, or global after jax.distributed) devices, axis 'batch'."""
    return Mesh(np.asarray(jax.devices()), ("batch",))


def _shard(tree, mesh: Mesh, size: int):
    """Pad the batch to a multiple of the device count and shard it along 'batch'."""
    n_dev = mesh.devices.size
    pad = (-size) % n_dev
    if pad:
        tree = jax.tree_util.tree_map(lambda x: np.concatenate([x, np.repeat(x[-1:], pad, 0)]), tree)
    sharding = NamedSharding(mesh, PartitionSpec("batch"))
    return jax.device_put(tree, sharding), pad


def metrics_columns(metrics, push_end: float) -> dict:
    m = jax.tree_util.tree_map(np.asarray, metrics)
    ticks = np.maximum(m.ticks, 1)
    survived = ~m.fell & ~m.nan
    return {
        "survived": survived,
        "fell": m.fell,
        "nan": m.nan,
        "com_rmse_m": np.sqrt(m.com_sq_err_sum / ticks),
        "com_max_dev_m": m.com_max_err,
        "time_to_recover_s": np.where(survived, np.maximum(m.last_time_off - push_end, 0.0), np.nan),
        "peak_torque_nm": m.max_abs_torque,
        "max_qp_violation": m.max_violation,
        "max_foot_slip_m": m.max_slip,
        "qp_infeasible_ticks": m.qp_infeasible_ticks,
        "min_com_height_m": m.min_com_height,
    }


def run_sweep(cfg: SweepConfig, out: str | pathlib.Path, *, gains_file: str | None = None,
              progress: bool = True, robot_name: str = "icub") -> dict:  # fmt: skip
    """Run (or resume) a sweep into ``out``: parts/*.parquet, results.parquet, summary.json, plots."""
    import pandas as pd
    from tqdm.auto import tqdm

    out = pathlib.Path(out)
    robot = model_lib.load_robot(robot_name)
    dtype = np.dtype(jnp.zeros(()).dtype)  # float32 unless x64 is enabled
    base = ctrl_lib.load_gains(gains_file, robot.index.n) if gains_file else ctrl_lib.default_gains(robot.index.n)
    ctrl_lib.validate_gains(base, robot.index.n)
    robot.index.body_id(cfg.body)  # unknown body: error listing the valid names, before compiling
    scen, columns = build_scenarios(cfg, base, robot.index.n, dtype)
    manifest = out / "manifest.json"
    key = cfg.key()
    if manifest.exists() and json.loads(manifest.read_text()).get("key") != key:
        raise ValueError(f"{out} holds a different sweep (config changed); use another --out")
    io.atomic_write_json(manifest, {"key": key, "config": dataclasses.asdict(cfg)})

    push_end = cfg.push_onset + cfg.push_duration
    n_chunks = math.ceil(cfg.size / cfg.chunk_size)
    parts = out / "parts"
    compile_s = run_s = 0.0
    done_envs = 0
    rollout = None
    with tqdm(total=cfg.size, unit="env", disable=not progress) as bar:
        for c in range(n_chunks):
            part = parts / f"part-{c:05d}.parquet"
            lo, hi = c * cfg.chunk_size, min((c + 1) * cfg.chunk_size, cfg.size)
            if part.exists():  # resumed: this chunk is on disk
                bar.update(hi - lo)
                continue
            chunk = jax.tree_util.tree_map(lambda x: np.asarray(x)[lo:hi], scen)
            t0 = time.perf_counter()
            metrics, rollout, compiling = run_batch(robot, cfg, chunk)
            compile_s += compiling
            run_s += time.perf_counter() - t0 - compiling
            done_envs += hi - lo
            cols = metrics_columns(metrics, push_end)
            table = pd.DataFrame({"env": np.arange(lo, hi), **{k: v[lo:hi] for k, v in columns.items()}, **cols})
            buf = __import__("io").BytesIO()
            table.to_parquet(buf, index=False)
            io.atomic_write_bytes(part, buf.getvalue())
            bar.update(hi - lo)
    table = pd.concat([pd.read_parquet(p) for p in sorted(parts.glob("part-*.parquet"))], ignore_index=True)
    buf = __import__("io").BytesIO()
    table.to_parquet(buf, index=False)
    io.atomic_write_bytes(out / "results.parquet", buf.getvalue())
    steps_per_env = int(round(cfg.horizon / 0.01)) * 10 if rollout is None else rollout.n_ticks * rollout.n_sub
    summary = summarize_table(table, cfg, robot)
    summary.update({
        "config": dataclasses.asdict(cfg),
        "device": [str(d) for d in jax.devices()],
        "n_devices": len(jax.devices()),
        "versions": {"jax": jax.__version__, "mujoco": __import__("mujoco").__version__,
                     "wbc_jax": __import__("wbc_jax").__version__},
        "compile_s": round(compile_s, 2),
        "run_s": round(run_s, 2),
        "physics_steps_per_s": (done_envs * steps_per_env / run_s) if run_s > 0 else None,
        "gains": ctrl_lib.gains_to_dict(base),
    })  # fmt: skip
    io.atomic_write_json(out / "summary.json", summary)
    from wbc_jax import sweep_plots

    sweep_plots.survival_map(table, out / "survival.png")
    sweep_plots.envelope(table, summary["envelope"], out / "envelope.png")
    return summary


def lip_bound(robot: model_lib.Robot, directions_deg, support: str = "two-feet") -> dict:
    """Feet-in-place bound per direction: the LIP with the CoP at the support-polygon edge
    survives a CoM velocity up to omega d (omega = sqrt(g / z_CoM)); as an impulse: m omega d.

    support: "two-feet" (home posture, CoM between the feet) or "left-foot" (the single-support
    phase of the one-foot task: the left sole's contact points, CoM over the left sole)."""
    import mujoco
    from scipy.spatial import ConvexHull

    if support not in SUPPORTS:
        raise ValueError(f"unknown support {support!r}; valid: {list(SUPPORTS)}")
    m = robot.mj_model
    d = mujoco.MjData(m)
    d.qpos[:] = robot.home_qpos()
    mujoco.mj_forward(m, d)
    feet = robot.index.foot_geoms.ravel() if support == "two-feet" else robot.index.foot_geoms[0]
    pts = d.geom_xpos[feet, :2]
    hull = ConvexHull(pts)
    com = d.subtree_com[robot.index.base_body].copy()
    if support == "left-foot":  # references.make_schedule("one-foot"): CoM y over the left sole
        com[1] = d.site_xpos[robot.index.foot_sites[0], 1]
    omega = math.sqrt(9.81 / com[2])
    out = {}
    for az in directions_deg:
        u = np.array([math.cos(math.radians(az)), math.sin(math.radians(az))])
        # Distance along u from the CoM to the hull boundary: min over facets a.x + b <= 0.
        dist = min(
            (-(eq[:2] @ com[:2] + eq[2]) / (eq[:2] @ u)) for eq in hull.equations if eq[:2] @ u > 1e-12
        )
        out[float(az)] = {"edge_distance_m": dist, "velocity_bound_mps": omega * dist,
                          "impulse_bound_ns": robot.index.mass * omega * dist}  # fmt: skip
    return out


def summarize_table(table, cfg: SweepConfig, robot: model_lib.Robot) -> dict:
    """Survival rate, envelope (largest survived impulse per direction) and its bound."""
    support = "left-foot" if cfg.task == "one-foot" else "two-feet"
    bound = lip_bound(robot, sorted(set(table["azimuth_deg"])), support)
    envelope = {}
    default = table[table["gain_set"] == 0]
    for az, group in default.groupby("azimuth_deg"):
        alive = group[group["survived"]]
        best = float(alive["impulse_ns"].max()) if len(alive) else 0.0
        b = bound[float(az)]["impulse_bound_ns"]
        # Monotone-ish: survivals above the first failure (islands) are counted.
        by_mag = group.groupby("magnitude_n")["survived"].mean().sort_index()
        failed = by_mag[by_mag < 1.0]
        islands = int((by_mag[by_mag.index > failed.index.min()] > 0).sum()) if len(failed) else 0
        # Largest impulse below the first failure: islands (outcomes near the fall boundary that
        # flip with float32/float64 or the solver's iterations; experiments/island_check.py) excluded.
        below = group[group["magnitude_n"] < failed.index.min()] if len(failed) else group
        monotone = float(below["impulse_ns"].max()) if len(below) else 0.0
        envelope[float(az)] = {"largest_survived_impulse_ns": best, "bound_impulse_ns": b,
                               "fraction_of_bound": best / b, "survival_islands": islands,
                               "monotone_impulse_ns": monotone,
                               "fraction_of_bound_monotone": monotone / b}  # fmt: skip
    return {
        "support": support,
        "n_envs": int(len(table)),
        "survival_rate": float(table["survived"].mean()),
        "nan_envs": int(table["nan"].sum()),
        "qp_infeasible_envs": int((table["qp_infeasible_ticks"] > 0).sum()),
        "envelope": envelope,
    }
