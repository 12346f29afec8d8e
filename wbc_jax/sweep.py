"""[experiments] Batched push-recovery sweeps: scenarios -> batched closed loops -> table.

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
import json
import math
import pathlib

import jax
import numpy as np

from wbc_jax import constants, io, physics, runs, scenario, sweep_plots
from wbc_jax import metrics as metrics_lib
from wbc_jax import model as model_lib
from wbc_jax import rollout as rollout_lib
from wbc_jax.controller import FORCE_MODES, ControllerConfig, with_job_settings
from wbc_jax.gains import Gains, default_gains, gains_from_dict, gains_to_dict, load_gains, validate_gains
from wbc_jax.rollout import Push, Scenario
from wbc_jax.torques import POSTURAL_VARIANTS
from wbc_jax.types import option

SWEEP_TASKS = ("stand", "one-foot")
# The one-foot task (references.make_schedule) balances on the left foot from 7 to 9 s.
ONE_FOOT_WINDOW = (7.0, 9.0)
SUPPORTS = ("two-feet", "left-foot")
MAX_ENVS = 10_000_000  # a grid larger than this is a typo (its scenarios alone take ~3 GB of memory)


def _grid(values) -> tuple[float, ...]:
    """``--magnitudes LO HI N``: N evenly spaced values (N a whole number >= 1)."""
    lo, hi, n = (float(v) for v in values)
    if not (math.isfinite(lo) and math.isfinite(hi) and math.isfinite(n)):
        raise ValueError(f"--magnitudes LO HI N needs finite numbers, got {list(values)}")
    if n != int(n) or n < 1:
        raise ValueError(f"--magnitudes LO HI N: N must be a whole number >= 1, got {n:g}")
    return tuple(float(x) for x in np.linspace(lo, hi, int(n)))


def _show_grid(values) -> tuple:
    values = np.asarray(values, float)
    return (values[0], values[-1], len(values))


def _azimuths(count) -> tuple[float, ...]:
    """``--directions N``: N azimuths evenly spread over 360 deg from 0 (forward)."""
    n = float(count)
    if n != int(n) or n < 1:
        raise ValueError(f"--directions must be a whole number >= 1, got {count}")
    return tuple(float(x) for x in np.arange(int(n)) * 360.0 / int(n))


@dataclasses.dataclass(frozen=True)
class SweepConfig:
    """What a sweep covers; the defaults are the README's main job (a laptop CPU in a minute).
    The CLI flags of ``wbc-jax push-sweep`` are generated from these fields."""

    magnitudes: tuple[float, ...] = option(
        (20.0, 60.0, 100.0), "push force grid [N]: LO HI N", nargs=3, metavar=("LO", "HI", "N"),
        parse=_grid, show=_show_grid,
    )  # fmt: skip
    directions: tuple[float, ...] = option(
        (0.0, 90.0, 180.0, 270.0), "number of push azimuths over 360 deg (0 = forward, 90 = left)",
        metavar="N", parse=_azimuths, show=len,
    )  # fmt: skip
    elevation: float = option(0.0, "push elevation [deg]")
    push_duration: float = option(0.1, "push length [s]")
    push_onset: float = option(0.5, "push start [s]")
    body: str = option("chest", "pushed body")
    gains: str | None = option(None, "gains JSON file (the first gain set)", metavar="FILE")
    gain_sets: int = option(1, "gain sets: the first, then seeded log-uniform scalings of it")
    gain_scale_range: tuple[float, float] = option((0.5, 2.0), "range of those scalings", nargs=2)
    joint_noise: float = option(0.0, "initial joint noise std [rad]")
    friction: tuple[float, float] = option((1.0, 1.0), "floor friction range", nargs=2, metavar=("LO", "HI"))
    mass_scale: tuple[float, float] = option((1.0, 1.0), "plant mass scale range", nargs=2, metavar=("LO", "HI"))
    horizon: float = option(1.5, "seconds per rollout")
    task: str = option(
        "stand", "two feet (stand) or pushed in the single-support phase of the one-foot task "
        "(7-9 s: e.g. --push-onset 7.5 --horizon 9)", choices=SWEEP_TASKS,
    )  # fmt: skip
    forces: str = option("qp", "force distribution", choices=FORCE_MODES)
    postural: str = option("stable", "postural task variant", choices=POSTURAL_VARIANTS)
    angular_weight_soft: float = option(
        1.0, "soft momentum QP: weight of the angular-momentum rate against the linear one where a push asks for "
        "more than the feet can give (1: WBC; < 1: the CoM first, the upper body absorbs the rest)",
    )  # fmt: skip
    solver_iterations: int | None = option(None, "contact solver Newton iterations (default: the model's, 4)")
    seed: int = option(0, "seed of the random perturbations")
    tasks: str | None = option(None, "task/contact file (JSON/YAML), as balance --tasks", metavar="FILE")
    chunk_size: int = option(12, "environments per compiled batch")
    queue: int = option(
        1, "scenarios per batch slot (MJX backends): a fallen or diverged robot is retired and its slot "
        "starts the next scenario; same outcomes, fewer physics steps (1: off)",
    )  # fmt: skip
    backend: str = option("auto", "physics engine (auto: C MuJoCo on a CPU, MJX-Warp/JAX on a GPU)",
                          choices=physics.BACKENDS)  # fmt: skip
    out: str = option("runs/push_sweep", "output folder (a sweep resumes there)")

    def check(self) -> None:
        """Every check that needs no model or compilation (run first, before any file is written)."""
        if not self.magnitudes or not self.directions:
            raise ValueError("the grid is empty: give at least one magnitude and one direction")
        if any(not math.isfinite(m) or m < 0 for m in self.magnitudes):
            raise ValueError(f"--magnitudes: push forces must be finite and >= 0 N, got {list(self.magnitudes)}")
        if any(not math.isfinite(d) for d in self.directions):
            raise ValueError(f"--directions: azimuths must be finite, got {list(self.directions)}")
        for name in ("elevation", "push_duration", "push_onset", "horizon", "joint_noise"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value)):
                raise ValueError(f"--{name.replace('_', '-')} must be a finite number, got {value!r}")
            if name != "elevation" and value < 0:
                raise ValueError(f"--{name.replace('_', '-')} must be >= 0, got {value}")
        if self.horizon <= self.push_onset + self.push_duration:
            raise ValueError(
                f"--horizon {self.horizon} s must end after the push ({self.push_onset} + {self.push_duration} s)"
            )
        for name in ("gain_sets", "chunk_size", "queue"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"--{name.replace('_', '-')} must be a whole number >= 1, got {value!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"--seed must be a whole number >= 0, got {self.seed!r}")
        if self.size > MAX_ENVS:
            gb = self.size * 300 / 1e9  # bytes of scenario data per environment, roughly
            raise ValueError(f"the grid has {self.size:,} environments (about {gb:,.0f} GB of scenarios), more than "
                             f"{MAX_ENVS:,}; use a coarser grid")  # fmt: skip
        for name, path in (("tasks", self.tasks), ("gains", self.gains)):
            runs.check_input_file(path, name)
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
        for name in ("friction", "mass_scale", "gain_scale_range"):
            lo, hi = getattr(self, name)
            if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo <= hi):
                raise ValueError(f"--{name.replace('_', '-')} range must be positive and ordered, got {(lo, hi)}")
        self.controller_config()
        physics.PhysicsConfig(backend=self.backend, solver_iterations=self.solver_iterations)

    def controller_config(self, base: ControllerConfig | None = None) -> ControllerConfig:
        """``base`` (default: the defaults) with this sweep's controller settings."""
        return with_job_settings(base, self.forces, self.postural, self.angular_weight_soft)

    @property
    def size(self) -> int:
        return len(self.magnitudes) * len(self.directions) * self.gain_sets

    @property
    def perturbs_plant(self) -> bool:
        return self.friction != (1.0, 1.0) or self.mass_scale != (1.0, 1.0)


def default_config() -> SweepConfig:
    return SweepConfig()


def gain_sets(base: Gains, count: int, scale_range, rng: np.random.Generator) -> list:
    """``count`` gain sets: the base one, then per-group log-uniform scalings of it."""
    sets = [base]
    lo, hi = np.log(scale_range[0]), np.log(scale_range[1])
    for _ in range(count - 1):
        scaled = {name: np.asarray(getattr(base, name)) * np.exp(rng.uniform(lo, hi)) for name in constants.GAIN_FIELDS}
        sets.append(Gains(**scaled))
    return sets


def scenarios_at(cfg: SweepConfig, sets: list, mag, azi, gset, friction, mass_scale, joint_offset,
                 dtype=np.float32) -> tuple[Scenario, dict]:  # fmt: skip
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


def make_setup(cfg: SweepConfig, base_gains: Gains | None = None, *, robot_name: str = "icub",
               loss_trace: bool = False, checkpoint: bool = False, record: bool = False,
               controller: ControllerConfig | None = None) -> scenario.Setup:  # fmt: skip
    """The closed loop of a sweep's environments (tuning uses it with a LossTrace, replays with
    ``record``). ``controller``: further controller settings (forces, postural, angular_weight_soft
    from ``cfg``)."""
    scene = scenario.load_scene(robot_name, cfg.tasks)
    sim = rollout_lib.SimConfig(
        record=record, loss_trace=loss_trace, checkpoint=checkpoint, push_body=cfg.body,
        perturb_plant=cfg.perturbs_plant,
        physics=physics.PhysicsConfig(backend="jax" if loss_trace else cfg.backend, solver_iterations=cfg.solver_iterations),
    )  # fmt: skip
    return scenario.setup(
        cfg.task, duration=cfg.horizon,
        controller=cfg.controller_config(controller),
        sim=sim, gains=base_gains, scene=scene,
    )  # fmt: skip


def base_gains(cfg: SweepConfig, n: int, dtype) -> Gains:
    gains = load_gains(cfg.gains, n, dtype) if cfg.gains else default_gains(n, dtype)
    validate_gains(gains, n)
    return gains


def fingerprint(cfg: SweepConfig) -> dict:
    return runs.fingerprint({**dataclasses.asdict(cfg), "dtype": str(scenario.float_dtype())}, [cfg.gains, cfg.tasks])


def _part_name(c: int) -> str:
    return f"part-{c:05d}.parquet"


def _read_part(path: pathlib.Path, lo: int, hi: int):
    """A part file if it holds exactly envs lo..hi-1, else None (missing, unreadable or wrong)."""
    import pandas as pd

    if not path.exists():
        return None
    try:
        table = pd.read_parquet(path)
    except Exception:
        return None
    if "env" not in table or not np.array_equal(table["env"].to_numpy(), np.arange(lo, hi)):
        return None
    return table


def run_sweep(cfg: SweepConfig | None = None, *, progress: bool = True, robot_name: str = "icub", **overrides) -> dict:
    """Run (or resume) a sweep into ``cfg.out``: parts/*.parquet, results.parquet, summary.json, plots.

    ``overrides``: fields of :class:`SweepConfig`. A resumed run must have the same fingerprint
    (config, input file contents, model, version); each part file is checked against the env
    range it must hold and recomputed if it does not."""
    import pandas as pd
    from tqdm.auto import tqdm

    cfg = dataclasses.replace(default_config() if cfg is None else cfg, **overrides)
    cfg.check()
    runs.check_output_dir(cfg.out, "sweep")
    out = pathlib.Path(cfg.out)
    dtype = scenario.float_dtype()
    robot = model_lib.load_robot(robot_name)
    base = base_gains(cfg, robot.index.n, dtype)
    robot.index.body_id(cfg.body)
    st = make_setup(cfg, base, robot_name=robot_name)
    scenario.check_queue(cfg.queue, st.backend)
    scen, columns = build_scenarios(cfg, base, robot.index.n, dtype)
    # With several processes (jax.distributed), each computes every chunk with its devices' share
    # and gathers the results; the first process writes them.
    writer = jax.process_index() == 0
    if writer:
        runs.claim_output_dir(out, "sweep", fingerprint(cfg), resume=True)

    push_end = cfg.push_onset + cfg.push_duration
    n_chunks = math.ceil(cfg.size / cfg.chunk_size)
    parts = out / "parts"
    compile_s = run_s = 0.0
    done_envs = simulated_ticks = 0
    tables = []
    with tqdm(total=cfg.size, unit="env", disable=not progress, desc=f"sweep ({st.backend})") as bar:
        for c in range(n_chunks):
            lo, hi = c * cfg.chunk_size, min((c + 1) * cfg.chunk_size, cfg.size)
            part = parts / _part_name(c)
            table = _read_part(part, lo, hi)
            if table is None:
                chunk = jax.tree_util.tree_map(lambda x, lo=lo, hi=hi: np.asarray(x)[lo:hi], scen)
                result = scenario.run(st, chunk, batch_size=cfg.chunk_size, queue=cfg.queue)
                compile_s += result.compile_s
                run_s += result.run_s
                done_envs += hi - lo
                simulated_ticks += int(np.sum(result.metrics.ticks))
                cols = metrics_lib.summarize(result.metrics, push_end)
                table = pd.DataFrame({"env": np.arange(lo, hi), **{k: v[lo:hi] for k, v in columns.items()}, **cols})
                if writer:
                    io.atomic_write_parquet(part, table)
            tables.append(table)
            bar.update(hi - lo)
    table = pd.concat(tables, ignore_index=True)
    if writer:
        io.atomic_write_parquet(out / "results.parquet", table)
    steps_per_env = st.loop.n_ticks * st.loop.n_sub
    summary = summarize_table(table, cfg, st.robot)
    devices = scenario.batch_devices() if st.backend != "mujoco" else jax.devices()[:1]  # C MuJoCo: host only
    summary.update({
        "config": dataclasses.asdict(cfg),
        "backend": st.backend,
        "survival_criterion": constants.SURVIVAL_CRITERION,
        "device": [str(d) for d in devices],
        "n_devices": len(devices),
        "versions": {"jax": jax.__version__, "mujoco": __import__("mujoco").__version__,
                     "wbc_jax": __import__("wbc_jax").__version__},
        "compile_s": round(compile_s, 2),
        "run_s": round(run_s, 2),
        # Steps of the whole grid per second of run (with a queue, fewer were simulated).
        "physics_steps_per_s": (done_envs * steps_per_env / run_s) if run_s > 0 else None,
        "physics_steps_simulated": simulated_ticks * st.loop.n_sub,
        "gains": gains_to_dict(base),
    })  # fmt: skip
    if writer:
        io.atomic_write_json(out / "summary.json", summary)
        sweep_plots.survival_map(table, out / "survival.png", summary["envelope"])
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
    omega = math.sqrt(constants.GRAVITY / com[2])
    out = {}
    for az in directions_deg:
        u = np.array([math.cos(math.radians(az)), math.sin(math.radians(az))])
        # Distance along u from the CoM to the hull boundary: min over facets a.x + b <= 0.
        dist = min((-(eq[:2] @ com[:2] + eq[2]) / (eq[:2] @ u)) for eq in hull.equations if eq[:2] @ u > 1e-12)
        out[float(az)] = {"edge_distance_m": dist, "velocity_bound_mps": omega * dist,
                          "impulse_bound_ns": robot.index.mass * omega * dist}  # fmt: skip
    return out


def envelope_of(group, survived: str = "survived") -> tuple[float, float, int]:
    """(largest survived impulse, largest impulse below the first failure, survival islands above
    it) of one direction's rows."""
    alive = group[group[survived]]
    best = float(alive["impulse_ns"].max()) if len(alive) else 0.0
    by_mag = group.groupby("magnitude_n")[survived].mean().sort_index()
    failed = by_mag[by_mag < 1.0]
    islands = int((by_mag[by_mag.index > failed.index.min()] > 0).sum()) if len(failed) else 0
    # Islands: outcomes near the fall boundary that flip with float32/float64 or the solver's
    # iterations (experiments/island_check.py); the monotone envelope excludes them.
    below = group[group["magnitude_n"] < failed.index.min()] if len(failed) else group
    monotone = float(below["impulse_ns"].max()) if len(below) else 0.0
    return best, monotone, islands


def summarize_table(table, cfg: SweepConfig, robot: model_lib.Robot) -> dict:
    """Survival rate (strict, and the lax ``upright`` count), envelope (largest survived impulse
    per direction) and its feet-in-place LIP bound."""
    support = "left-foot" if cfg.task == "one-foot" else "two-feet"
    bound = lip_bound(robot, sorted(set(table["azimuth_deg"])), support)
    envelope = {}
    default = table[table["gain_set"] == 0]
    for az, group in default.groupby("azimuth_deg"):
        best, monotone, islands = envelope_of(group)
        best_upright, _, _ = envelope_of(group, "upright")
        b = bound[float(az)]["impulse_bound_ns"]
        envelope[float(az)] = {"largest_survived_impulse_ns": best, "bound_impulse_ns": b,
                               "fraction_of_bound": best / b, "survival_islands": islands,
                               "monotone_impulse_ns": monotone, "fraction_of_bound_monotone": monotone / b,
                               "largest_upright_impulse_ns": best_upright}  # fmt: skip
    return {
        "support": support,
        "n_envs": int(len(table)),
        "survival_rate": float(table["survived"].mean()),
        "upright_rate": float(table["upright"].mean()),
        "nan_envs": int(table["nan"].sum()),
        "qp_infeasible_envs": int((table["qp_infeasible_ticks"] > 0).sum()),
        "envelope": envelope,
    }


# ---------------------------------------------------------------------------------------------
# Replays of one environment


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
    try:
        summary = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise ValueError(f"{path} is not valid JSON ({err})") from None
    values = {k: tuple(v) if isinstance(v, list) else v for k, v in summary.get("config", {}).items()}
    known = {f.name for f in dataclasses.fields(SweepConfig)}
    return SweepConfig(**{k: v for k, v in values.items() if k in known}), summary


def replay_env(run_dir, env: int, *, robot_name: str = "icub", backend: str | None = None):
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
    robot = model_lib.load_robot(robot_name)
    base = gains_from_dict(summary["gains"], robot.index.n, dtype)
    scen, columns = build_scenarios(cfg, base, robot.index.n, dtype)
    row = table[table["env"] == env].iloc[0].to_dict()
    for key in ("magnitude_n", "azimuth_deg", "gain_set"):
        if not np.isclose(columns[key][env], row[key]):
            raise ValueError(f"the rebuilt scenario of env {env} differs from the sweep's ({key}); "
                             "the sweep was written by another version")  # fmt: skip
    st = make_setup(cfg, base, robot_name=robot_name, record=True)
    one = jax.tree_util.tree_map(lambda x: np.asarray(x)[env : env + 1], scen)
    result = scenario.run(st, one)
    traj = {name: np.asarray(v)[0] for name, v in dataclasses.asdict(result.records).items()}
    metrics = metrics_lib.summarize(
        jax.tree_util.tree_map(lambda x: x[0], result.metrics), cfg.push_onset + cfg.push_duration
    )
    return st, traj, metrics, row
