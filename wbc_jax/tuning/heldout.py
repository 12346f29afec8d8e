"""Held-out evaluation of tuned gain sets, and the tuning figures.

What a gain set is judged on, none of which the tuning loss saw (S gain sets):

* the push grid of ``docs/sweep_h100`` (chest, 0.1 s at 0.5 s, M magnitudes x D directions, 3 s),
  on the sweep's backend: strict survival rate, envelope (largest survived impulse per direction)
  as a fraction of the feet-in-place LIP bound, min / median over directions;
* unseen variations (:data:`VARIATIONS`): pushes on the left hand (the forearm body ``l_elbow_1``,
  which carries the hand) and the right thigh, durations 0.02 s and 0.5 s, floor friction 0.5, and
  pushes during the single-support phase of the one-foot task;
* the 20 s CoM sinusoid of the seed (``balance``'s task): CoM RMSE (<= 1.5 mm to keep the seed's
  task), on C MuJoCo by default.

All gain sets of one controller setting run as one batch (one compiled program per task; gains
are data), in chunks written as Parquet parts (resumable). :func:`write_heldout` writes
heldout.json; the figures are the polar envelope, learning curves and survival against loss.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import pathlib
import time

import jax
import numpy as np

from wbc_jax.control.controller import ControllerConfig
from wbc_jax.control.gains import Gains
from wbc_jax.core import constants, io, provenance
from wbc_jax.jobs import sweep, sweep_config, sweep_table
from wbc_jax.report.tuning_plots import survival_vs_loss
from wbc_jax.sim import metrics as metrics_lib
from wbc_jax.sim import mjx_loop, physics, runner, scenario
from wbc_jax.sim.state import Push, Scenario, SimConfig
from wbc_jax.tuning import loss as tuning_loss
from wbc_jax.tuning import problem as tp

# name: (pushed body, push duration s, floor friction); magnitudes keep the grid's impulses.
VARIATIONS = {
    "l_hand": ("l_elbow_1", 0.1, 1.0),
    "r_upper_leg": ("r_upper_leg", 0.1, 1.0),
    "duration_0.02s": ("chest", 0.02, 1.0),
    "duration_0.5s": ("chest", 0.5, 1.0),
    "friction_0.5": ("chest", 0.1, 0.5),
}


@dataclasses.dataclass(frozen=True)
class HeldoutConfig:
    """Sizes of the held-out evaluation (defaults: the issue's; tiny ones for CPU checks).

    grid: (LO N, HI N, M magnitudes) x ``directions`` azimuths, chest pushes of ``duration`` s at
    ``onset`` s, ``horizon`` s. variations: ``variation_magnitudes`` x ``variation_directions``
    over the same impulse range. one_foot: pushes at ``one_foot_onset`` s of the one-foot task
    (horizon ``one_foot_horizon``). sinusoid_s: seconds of the CoM sinusoid (0: skip).
    tasks, angular_weight_soft: the contact file and soft-QP weight of every closed loop (as the
    tuning run's: :class:`wbc_jax.tuning.config.TuneConfig`)."""

    magnitudes: tuple[float, float, int] = (10.0, 400.0, 64)
    directions: int = 32
    duration: float = 0.1
    onset: float = 0.5
    horizon: float = 3.0
    variations: tuple[str, ...] = tuple(VARIATIONS)
    variation_magnitudes: int = 16
    variation_directions: int = 16
    one_foot: bool = True
    one_foot_onset: float = 7.5
    one_foot_horizon: float = 9.0
    sinusoid_s: float = 20.0
    sinusoid_backend: str = "mujoco"
    backend: str = "auto"
    chunk_size: int = 16384
    tasks: str | None = None
    angular_weight_soft: float = 1.0

    def __post_init__(self):
        lo, hi, m = self.magnitudes
        if not (0 <= lo <= hi and int(m) == m and m >= 1):
            raise ValueError(f"held-out magnitudes must be LO <= HI and a count >= 1, got {self.magnitudes}")
        for name in ("directions", "variation_magnitudes", "variation_directions", "chunk_size"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"held-out {name} must be >= 1, got {getattr(self, name)}")
        unknown = sorted(set(self.variations) - set(VARIATIONS))
        if unknown:
            raise ValueError(f"unknown held-out variations {unknown}; valid: {list(VARIATIONS)}")
        if self.horizon <= self.onset + max([self.duration] + [VARIATIONS[v][1] for v in self.variations]):
            raise ValueError(f"held-out horizon {self.horizon} s ends before the pushes")
        lo_of, hi_of = sweep_config.ONE_FOOT_WINDOW
        if self.one_foot and not (lo_of <= self.one_foot_onset and self.one_foot_onset + self.duration <= hi_of
                                  and self.one_foot_horizon > self.one_foot_onset + self.duration):  # fmt: skip
            raise ValueError(f"one-foot pushes must fall in the single-support phase {sweep_config.ONE_FOOT_WINDOW} s")
        physics.PhysicsConfig(backend=self.backend)
        physics.PhysicsConfig(backend=self.sinusoid_backend)
        ControllerConfig(angular_weight_soft=self.angular_weight_soft)
        if self.tasks is not None and not pathlib.Path(self.tasks).is_file():
            raise ValueError(f"held-out tasks file {self.tasks} is not a file")


def _groups(sets: dict) -> dict:
    """Gain sets grouped by their regularisation: {(pinv_damping, kp_postural_reg): [names]}."""
    groups: dict = {}
    for name, (_, reg) in sets.items():
        groups.setdefault(tuple(np.round(np.asarray(reg, float), 12).tolist()), []).append(name)
    return groups


def _controller(reg, hc: HeldoutConfig) -> ControllerConfig:
    return ControllerConfig(pinv_damping=float(reg[0]), kp_postural_reg=float(reg[1]),
                            angular_weight_soft=hc.angular_weight_soft)  # fmt: skip


def _scenarios(robot, rows: dict, gains: list, dtype) -> Scenario:
    """Scenarios (B,) from columns: azimuth_deg, magnitude_n, duration_s, body (ids), friction,
    gain_set (index into ``gains``); no joint noise, nominal masses, onset in ``rows['onset']``."""
    az = np.asarray(rows["azimuth_deg"], float)
    B = az.size
    u = np.stack([np.cos(np.deg2rad(az)), np.sin(np.deg2rad(az)), np.zeros(B)], 1)
    g = np.asarray(rows["gain_set"], int)
    return Scenario(
        push=Push(force=(np.asarray(rows["magnitude_n"])[:, None] * u)[:, None, :].astype(dtype),
                  onset=np.full((B, 1), rows["onset"], dtype), duration=np.asarray(rows["duration_s"], dtype)[:, None],
                  body=np.asarray(rows["body"], np.int32)[:, None]),
        gains=Gains(**{k: np.stack([np.asarray(getattr(gains[i], k), dtype) for i in g]) for k in
                       ("kp_com", "kd_com", "ki_com", "kp_ang", "ki_ang", "kp_postural", "kd_postural")}),
        joint_offset=np.zeros((B, robot.index.n), dtype), friction=np.asarray(rows["friction"], dtype),
        mass_scale=np.ones(B, dtype),
    )  # fmt: skip


def _run_table(st: scenario.Setup, scen: Scenario, cols: dict, folder: pathlib.Path, chunk: int, tag: str,
               progress: bool, push_end: float) -> tuple:  # fmt: skip
    """Run a batch in chunks (Parquet parts in ``folder``, reused when their tag matches):
    (DataFrame of columns + metrics, {compile_s, run_s, physics_steps_per_s})."""
    import pandas as pd
    from tqdm.auto import tqdm

    folder.mkdir(parents=True, exist_ok=True)
    B = len(cols["gain_set"])
    tables, compile_s, run_s, ran = [], 0.0, 0.0, 0
    with tqdm(total=B, unit="env", disable=not progress, desc=f"{folder.name} ({st.backend})") as bar:
        for c, lo in enumerate(range(0, B, chunk)):
            hi = min(lo + chunk, B)
            part = folder / f"part-{c:05d}-{tag}.parquet"
            if part.exists():
                table = pd.read_parquet(part)
            else:
                res = runner.run(
                    st,
                    jax.tree_util.tree_map(lambda x, lo=lo, hi=hi: np.asarray(x)[lo:hi], scen),
                    batch_size=min(chunk, B),
                )
                compile_s, run_s, ran = compile_s + res.compile_s, run_s + res.run_s, ran + hi - lo
                metrics = metrics_lib.summarize(res.metrics, push_end)
                table = pd.DataFrame({**{k: np.asarray(v)[lo:hi] for k, v in cols.items() if k != "onset"}, **metrics})
                io.atomic_write_parquet(part, table)
            tables.append(table)
            bar.update(hi - lo)
    steps = st.loop.n_ticks * st.loop.n_sub
    timing = {"compile_s": round(compile_s, 2), "run_s": round(run_s, 2), "envs": B,
              "physics_steps_per_s": ran * steps / run_s if run_s > 0 else None}  # fmt: skip
    return pd.concat(tables, ignore_index=True), timing


def _envelope(table, cfg: sweep_config.SweepConfig, robot) -> dict:
    """summarize_table of one gain set's rows: survival, envelope fractions (min / median)."""
    t = table.assign(gain_set=0)
    s = sweep_table.summarize_table(t, cfg, robot)
    frac = np.array([e["fraction_of_bound"] for e in s["envelope"].values()])
    mono = np.array([e["fraction_of_bound_monotone"] for e in s["envelope"].values()])
    return {"survival_rate": s["survival_rate"], "upright_rate": s["upright_rate"], "n_envs": s["n_envs"],
            "nan_envs": s["nan_envs"], "envelope_fraction_median": float(np.median(frac)),
            "envelope_fraction_min": float(np.min(frac)), "envelope_fraction_monotone_median": float(np.median(mono)),
            "envelope_fraction_monotone_min": float(np.min(mono)),
            "peak_torque_nm_median": float(np.median(table["max_abs_torque_nm"])),
            "envelope": {str(a): {"impulse_ns": e["largest_survived_impulse_ns"], "fraction": e["fraction_of_bound"],
                                  "bound_impulse_ns": e["bound_impulse_ns"]} for a, e in s["envelope"].items()}}  # fmt: skip


def heldout(sets: dict, hc: HeldoutConfig, out, *, progress: bool = True, robot_name: str = "icub") -> dict:
    """Evaluate gain sets {name: (Gains, regularisation (2,))} on the held-out grid, variations,
    one-foot task and sinusoid (module docstring), into ``out`` (resumable). Returns
    {name: {"grid": {...}, "variations": {name: {...}}, "one_foot": {...}, "sinusoid_com_rmse_m"}},
    plus "_timing"."""
    out = pathlib.Path(out)
    dtype = scenario.float_dtype()
    mags = np.linspace(hc.magnitudes[0], hc.magnitudes[1], int(hc.magnitudes[2]))
    impulses = mags * hc.duration
    result: dict = {name: {"variations": {}} for name in sets}
    timing: dict = {}
    for gi, (reg, names) in enumerate(_groups(sets).items()):
        gains = [sets[n][0] for n in names]
        tag = hashlib.sha256(json.dumps([dataclasses.asdict(hc), [_gains_list(g) for g in gains], reg],
                                        sort_keys=True).encode()).hexdigest()[:10]  # fmt: skip
        # Stand: the grid and the variations, one program (per-env plant: friction varies).
        cfg = sweep_config.SweepConfig(magnitudes=tuple(mags), directions=sweep_config._azimuths(hc.directions),
                                push_duration=hc.duration, push_onset=hc.onset, horizon=hc.horizon,
                                friction=(0.5, 1.0), backend=hc.backend, out=None, tasks=hc.tasks,
                                angular_weight_soft=hc.angular_weight_soft)  # fmt: skip
        st = sweep.make_setup(cfg, gains[0], robot_name=robot_name, controller=_controller(reg, hc))
        robot = st.robot
        blocks = [("grid", "chest", hc.duration, 1.0, impulses, sweep_config._azimuths(hc.directions))]
        vimp = np.linspace(impulses[0], impulses[-1], hc.variation_magnitudes)
        for v in hc.variations:
            body, dur, fr = VARIATIONS[v]
            blocks.append((v, body, dur, fr, vimp, sweep_config._azimuths(hc.variation_directions)))
        cols = _block_columns(robot, blocks, len(gains), hc.onset)
        table, timing[f"stand_{gi}"] = _run_table(st, _scenarios(robot, cols, gains, dtype), cols,
                                                  out / f"stand_{gi}", hc.chunk_size, tag, progress,
                                                  hc.onset + hc.duration)  # fmt: skip
        for s, name in enumerate(names):
            mine = table[table["gain_set"] == s]
            result[name]["grid"] = _envelope(mine[mine["block"] == "grid"], cfg, robot)
            for v in hc.variations:
                result[name]["variations"][v] = _envelope(mine[mine["block"] == v], cfg, robot)
        if hc.one_foot:
            of = dataclasses.replace(cfg, task="one-foot", push_onset=hc.one_foot_onset, horizon=hc.one_foot_horizon,
                                     friction=(1.0, 1.0))  # fmt: skip
            st1 = sweep.make_setup(of, gains[0], robot_name=robot_name, controller=_controller(reg, hc))
            blocks = [("one_foot", "chest", hc.duration, 1.0, vimp, sweep_config._azimuths(hc.variation_directions))]
            cols = _block_columns(robot, blocks, len(gains), hc.one_foot_onset)
            table1, timing[f"one_foot_{gi}"] = _run_table(st1, _scenarios(robot, cols, gains, dtype), cols,
                                                          out / f"one_foot_{gi}", hc.chunk_size, tag, progress,
                                                          hc.one_foot_onset + hc.duration)  # fmt: skip
            for s, name in enumerate(names):
                result[name]["one_foot"] = _envelope(table1[table1["gain_set"] == s], of, robot)
        if hc.sinusoid_s > 0:
            rmse, timing[f"sinusoid_{gi}"] = sinusoid(gains, reg, hc, robot_name)
            for s, name in enumerate(names):
                result[name]["sinusoid_com_rmse_m"] = rmse[s]
    result["_timing"] = timing
    return result


def _gains_list(g: Gains) -> list:
    return [np.asarray(getattr(g, k), float).round(9).tolist() for k in constants.GAIN_FIELDS]


def _block_columns(robot, blocks, n_sets: int, onset: float) -> dict:
    """Columns of every (block, gain set, impulse, azimuth) row."""
    cols: dict = {k: [] for k in ("block", "gain_set", "impulse_ns", "magnitude_n", "azimuth_deg", "duration_s",
                                  "body", "friction", "mass_scale")}  # fmt: skip
    for name, body, dur, fr, imps, azs in blocks:
        s, imp, az = (a.ravel() for a in np.meshgrid(np.arange(n_sets), imps, azs, indexing="ij"))
        cols["block"] += [name] * s.size
        cols["gain_set"] += s.tolist()
        cols["impulse_ns"] += imp.tolist()
        cols["magnitude_n"] += (imp / dur).tolist()
        cols["azimuth_deg"] += az.tolist()
        cols["duration_s"] += [dur] * s.size
        cols["body"] += [robot.index.body_id(body)] * s.size
        cols["friction"] += [fr] * s.size
        cols["mass_scale"] += [1.0] * s.size
    out = {k: np.asarray(v) for k, v in cols.items()}
    out["onset"] = onset
    return out


def sinusoid(gains: list, reg, hc: HeldoutConfig, robot_name: str = "icub") -> tuple[list, dict]:
    """CoM RMSE (m) of each gain set on the seed's CoM sinusoid (``hc.sinusoid_s`` s, no push),
    the closed loop of ``wbc-jax balance --task sinusoid`` (metrics only), all sets as one batch."""
    sim = SimConfig(record=False, physics=physics.PhysicsConfig(backend=hc.sinusoid_backend))
    st = scenario.setup("sinusoid", duration=hc.sinusoid_s, controller=_controller(reg, hc), sim=sim, gains=gains[0],
                        scene=scenario.load_scene(robot_name, hc.tasks))  # fmt: skip
    one = scenario.single(st)
    scen = jax.tree_util.tree_map(lambda x: np.repeat(np.asarray(x), len(gains), 0), one)
    scen = scen.replace(gains=Gains(**{k: np.stack([np.asarray(getattr(g, k), st.dtype) for g in gains])
                                       for k in constants.GAIN_FIELDS}))  # fmt: skip
    res = runner.run(st, scen)
    cols = metrics_lib.summarize(res.metrics)
    return [float(x) for x in cols["com_rmse_m"]], {"compile_s": round(res.compile_s, 2), "run_s": round(res.run_s, 2),
                                                    "backend": st.backend}  # fmt: skip


# ---------------------------------------------------------------------------------------------
# Held-out pushes of the training distribution, and whether the loss predicts survival


def evaluate_pushes(problem: tp.Problem, sets: dict, *, n: int | None = None, stream: int = 3,
                    progress: bool = True) -> dict:  # fmt: skip
    """Each gain set on ``n`` (default ``eval_pushes``) held-out pushes of the training distribution
    at ``eval_horizon``: loss, strict survival, CoM RMSE, torque RMS (MJX JAX physics)."""
    tc = problem.tc
    ev = tp.make_problem(tc, problem.lc, horizon=tc.eval_horizon, checkpoint=False)
    scen, _ = tp.sample_pushes(
        tc, ev.robot, ev.table, tp.batch_rng(tc.seed, stream, 0), n or tc.eval_pushes, ev.setup.dtype
    )
    fn = jax.jit(tp.make_batched_loss(ev, fixed_solver=False))
    results = {}
    for name, (gains, reg) in sets.items():
        regd = dict(zip(("pinv_damping", "kp_postural_reg"), np.asarray(reg, float)))
        t0 = time.perf_counter()
        obj, terms, metrics = fn(gains, regd, scen)
        cols = metrics_lib.summarize(metrics)
        results[name] = {"objective": float(obj), "survival_rate": float(np.mean(cols["survived"])),
                         "upright_rate": float(np.mean(cols["upright"])), "com_rmse_m": float(np.mean(cols["com_rmse_m"])),
                         "torque_rms_nm": float(np.sqrt(np.mean(terms["effort"]))) * problem.lc.torque_scale,
                         **{f"loss_{k}": float(np.mean(v)) for k, v in terms.items()},
                         "wall_s": round(time.perf_counter() - t0, 2)}  # fmt: skip
    return results


def survival_prediction(problem: tp.Problem, n: int, *, gains=None, reg=None, out=None) -> dict:
    """Does the loss predict strict survival? ``n`` held-out pushes of the training distribution
    (stream 4), rolled out for ``eval_horizon`` s with the given gains (default: the start of the
    search); strict survival at the end against the loss of the training horizon (the trace's
    first ticks) and of the whole rollout: Spearman correlation, ROC area, per-push values;
    survival_vs_loss.png and prediction.json in ``out``."""
    tc = problem.tc
    ev = tp.make_problem(tc, problem.lc, horizon=tc.eval_horizon, checkpoint=False)
    scen, cols = tp.sample_pushes(tc, ev.robot, ev.table, tp.batch_rng(tc.seed, 4, 0), n, ev.setup.dtype)
    gains = problem.init if gains is None else gains
    regd = dict(zip(("pinv_damping", "kp_postural_reg"), np.asarray(problem.reg0 if reg is None else reg, float)))
    n_train = problem.loop.n_ticks

    def both(g, r, s):
        metrics, trace = mjx_loop.rollout(ev.loop, *_env_args(ev, s), g, s.push, controller_overrides=r)
        return tuning_loss.loss_terms(trace, ev.lc, n_train), tuning_loss.loss_terms(trace, ev.lc), metrics

    t0 = time.perf_counter()
    terms, full_terms, metrics = jax.jit(jax.vmap(both, in_axes=(None, None, 0)))(gains, regd, scen)
    wall = time.perf_counter() - t0
    outcome = metrics_lib.summarize(metrics)
    survived = np.asarray(outcome["survived"])
    train_loss, full_loss = np.asarray(terms["total"]), np.asarray(full_terms["total"])
    per_term = {
        k: {"spearman": tuning_loss.spearman(np.asarray(v), survived), "auc": tuning_loss.auc(np.asarray(v), survived)}
        for k, v in terms.items()
        if k != "total"
    }
    rel = cols["impulse_ns"] / tp.interp_periodic(*problem.table, cols["azimuth_deg"])
    edges = np.linspace(*tc.magnitude_range, 5)
    bins = np.clip(np.searchsorted(edges, rel, side="right") - 1, 0, 3)
    by_size = [{"impulse_fraction": [float(edges[i]), float(edges[i + 1])], "n": int(np.sum(bins == i)),
                "survival_rate": float(survived[bins == i].mean()) if np.any(bins == i) else None} for i in range(4)]  # fmt: skip
    res = {"n": n, "survival_rate": float(survived.mean()), "horizon_s": tc.eval_horizon, "train_horizon_s": tc.horizon,
           "spearman_train_horizon": tuning_loss.spearman(train_loss, survived),
           "spearman_full": tuning_loss.spearman(full_loss, survived),
           "auc_train_horizon": tuning_loss.auc(train_loss, survived), "auc_full": tuning_loss.auc(full_loss, survived),
           "spearman_impulse_fraction": tuning_loss.spearman(rel, survived),
           "auc_impulse_fraction": tuning_loss.auc(rel, survived), "wall_s": round(wall, 1),
           "loss_train_horizon": train_loss.tolist(), "loss_full": full_loss.tolist(), "survived": survived.tolist(),
           "impulse_fraction_of_envelope": rel.tolist(), "per_term_train_horizon": per_term, "device": provenance.device_label(),
           "terms_train_horizon": {k: np.asarray(v).tolist() for k, v in terms.items()},
           "terms_full": {k: np.asarray(v).tolist() for k, v in full_terms.items()},
           "outcome": {k: np.asarray(v, float).tolist() for k, v in outcome.items()},
           "survival_by_impulse_fraction": by_size,
           "failure_rates": {k: float(np.mean(v)) for k, v in metrics_lib.failed_tests(outcome).items()}}  # fmt: skip
    if out is not None:
        out = pathlib.Path(out)
        io.atomic_write_json(out / "prediction.json", res)
        survival_vs_loss(train_loss, survived, res, out / "survival_vs_loss.png")
    return res


def _env_args(problem: tp.Problem, s):
    st, loop = problem.setup, problem.loop
    nominal = physics.device_model(st.robot.mj_model, "jax", loop.cfg.physics)
    return physics.plant_model(nominal, s.friction, s.mass_scale), loop.initial_qpos(jax.numpy.asarray(st.qpos0, st.dtype),
                                                                                     s.joint_offset)  # fmt: skip


# ---------------------------------------------------------------------------------------------
# heldout.json and figures


def targets(summary: dict) -> dict:
    """The issue's targets for the gradient-tuned set against the default and the best hand-set row
    (``critical``), from a heldout.json-like summary {name: {...}}."""
    g, d = summary.get("gradient"), summary.get("default")
    if g is None or d is None:
        return {}
    gd, dd = g["grid_envelope"], d["grid_envelope"]
    below = [a for a in gd if gd[a]["fraction"] < dd[a]["fraction"] - 1e-9]
    out = {"median_fraction_ge_0.8": g["envelope_fraction_median"] >= 0.8,
           "min_fraction_ge_0.6": g["envelope_fraction_min"] >= 0.6,
           "no_direction_below_default": not below, "directions_below_default": below,
           "survival_ge_1.5x_default": g["survival_rate"] >= 1.5 * d["survival_rate"],
           "sinusoid_rmse_le_1.5mm": (g.get("sinusoid_com_rmse_m") is not None
                                      and g["sinusoid_com_rmse_m"] <= constants.SINUSOID_MAX_COM_RMSE_M)}  # fmt: skip
    hand = [n for n in ("critical",) if n in summary]
    if hand:
        best = max(hand, key=lambda n: summary[n]["survival_rate"])
        out["survival_above_best_hand_set"] = g["survival_rate"] > summary[best]["survival_rate"]
    if "cmaes" in summary:
        out["envelope_median_ge_cmaes"] = g["envelope_fraction_median"] >= summary["cmaes"]["envelope_fraction_median"]
    return out


def write_heldout(path, results: dict, budgets: dict, *, extra: dict | None = None) -> dict:
    """heldout.json: one object per gain set (envelope_fraction_median/_min, survival_rate,
    sinusoid_com_rmse_m, sim_steps, wall_s, device, the per-direction envelope, the unseen
    variations and the one-foot task), the targets, and the survival criterion used.
    ``budgets``: {name: {"sim_steps", "wall_s"}} of the tuning runs (0 for hand-set rows)."""
    device = provenance.device_label()
    summary = {}
    for name, r in results.items():
        if name.startswith("_"):
            continue
        grid = r["grid"]
        summary[name] = {
            "envelope_fraction_median": grid["envelope_fraction_median"],
            "envelope_fraction_min": grid["envelope_fraction_min"],
            "survival_rate": grid["survival_rate"],
            "sinusoid_com_rmse_m": r.get("sinusoid_com_rmse_m"),
            "sim_steps": int(budgets.get(name, {}).get("sim_steps", 0)),
            "wall_s": float(budgets.get(name, {}).get("wall_s", 0.0)),
            "device": device,
            "effort_peak_torque_nm_median": grid["peak_torque_nm_median"],
            "upright_rate": grid["upright_rate"],
            "envelope_fraction_monotone_median": grid["envelope_fraction_monotone_median"],
            "envelope_fraction_monotone_min": grid["envelope_fraction_monotone_min"],
            "grid_envelope": grid["envelope"],
            "unseen": {v: {k: e[k] for k in ("survival_rate", "envelope_fraction_median", "envelope_fraction_min")}
                       for v, e in {**r["variations"], **({"one_foot": r["one_foot"]} if "one_foot" in r else {})}.items()},
        }  # fmt: skip
    report = {**summary, "targets": targets(summary), "survival_criterion": dict(constants.SURVIVAL_CRITERION),
              "timing": results.get("_timing", {}), **(extra or {})}  # fmt: skip
    io.atomic_write_json(pathlib.Path(path), report)
    return report
