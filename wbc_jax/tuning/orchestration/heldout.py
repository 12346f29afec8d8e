"""Held-out evaluation of tuned gain sets (``wbc-jax heldout``, the phase ``heldout`` of ``wbc-jax tune``).

What a gain set is judged on, none of which the tuning loss saw (S gain sets; :class:`HeldoutConfig`):

* the push grid of ``results/sweep_h100`` (the trunk, 0.1 s at 0.5 s, M magnitudes x D directions, 3 s),
  on the held-out backend: strict survival rate, envelope (largest survived impulse per direction)
  as a fraction of the feet-in-place LIP bound, min / median over directions;
* unseen variations (:data:`wbc_jax.tuning.heldout_config.VARIATIONS`): pushes on the left hand (the body of
  the robot's ``left_hand`` role) and the right thigh, durations 0.02 s and 0.5 s, floor
  friction 0.5, and pushes during the single-support phase of the one-foot task;
* the 20 s CoM sinusoid of the seed (``balance``'s task): CoM RMSE (<= 1.5 mm to keep the seed's
  task), on C MuJoCo by default.

A gain set is a Gains or a :class:`~wbc_jax.tuning.algorithms.schedule.GainSchedule` with its regularisation;
all sets of one kind and regularisation run as one batch (one compiled program per task; gains are
data), in chunks written as Parquet parts (resumable).
:func:`~wbc_jax.tuning.orchestration.heldout_report.write_heldout` writes heldout.json with its provenance;
:func:`run` is the ``wbc-jax heldout`` job on gains files.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import pathlib

import jax
import numpy as np

from wbc_jax.control.controller import ControllerConfig
from wbc_jax.control.gains import Gains, default_gains, load_gains
from wbc_jax.core import io, loader
from wbc_jax.core.options import flat_dict
from wbc_jax.jobs import chunks, grids, runs, sweep, sweep_config, sweep_table
from wbc_jax.report import tuning_plots
from wbc_jax.robot.description import RobotDescription
from wbc_jax.robot.robots import describe
from wbc_jax.sim import metrics as metrics_lib
from wbc_jax.sim import physics, runner, scenario
from wbc_jax.sim.state import Push, Scenario, SimConfig
from wbc_jax.tuning import store
from wbc_jax.tuning.algorithms import params as tuning_params
from wbc_jax.tuning.algorithms import schedule as gain_schedule
from wbc_jax.tuning.heldout_config import VARIATIONS, HeldoutConfig, heldout_default_config
from wbc_jax.tuning.orchestration.heldout_report import SUMMARY_KEYS, write_heldout


def load_sets(specs, robot: RobotDescription, dtype, regularisation=None) -> dict:
    """{name: (Gains or GainSchedule, regularisation (2,))} of ``--sets`` entries: 'default' (the
    robot's), 'critical' (its hand-set row) or NAME=FILE (a gains file or a gain-schedule file);
    checked before anything compiles."""
    n = len(robot.joints)
    reg0 = tuning_params.default_regularisation() if regularisation is None else np.asarray(regularisation, float)
    sets = {}
    for spec in specs:
        name, _, path = spec.partition("=")
        if name in sets:
            raise ValueError(f"gain set {name!r} given twice")
        if not path and name == "default":
            sets[name] = (default_gains(robot, dtype), reg0)
        elif not path and name == "critical":
            sets[name] = (load_gains(hand_set_gains(robot), n, dtype), reg0)
        elif not path:
            raise ValueError(f"--sets entries are 'default', 'critical' or NAME=FILE, got {spec!r}")
        elif gain_schedule.is_schedule_file(path):
            sets[name] = (gain_schedule.load_schedule(path, dtype), reg0)
        else:
            sets[name] = (load_gains(path, n, dtype), reg0)  # load_gains checks the file and its values
    return sets


def hand_set_gains(robot: RobotDescription):
    """The robot's hand-set gains file (the 'critical' set); one line where it has none."""
    if robot.hand_set_gains is None:
        raise ValueError(f"--sets critical: robot {robot.name} has no hand-set gains file; give NAME=FILE")
    return robot.asset_path(robot.hand_set_gains)


def set_files(specs, robot: RobotDescription) -> dict:
    """{name: path} of the files among ``--sets`` entries (for provenance)."""
    files = {name: path for name, _, path in (s.partition("=") for s in specs) if path}
    if any(s == "critical" for s in specs):
        files["critical"] = str(hand_set_gains(robot))
    return files


def _kind(controls) -> str:
    return "gains" if isinstance(controls, Gains) else "schedule"


def _groups(sets: dict) -> dict:
    """Gain sets grouped by kind and regularisation: {(kind, pinv_damping, kp_postural_reg): [names]}."""
    groups: dict = {}
    for name, (controls, reg) in sets.items():
        key = (_kind(controls), *np.round(np.asarray(reg, float), 12).tolist())
        groups.setdefault(key, []).append(name)
    return groups


def _controller(reg, hc: HeldoutConfig) -> ControllerConfig:
    return hc.controller.config(ControllerConfig(pinv_damping=float(reg[0]), kp_postural_reg=float(reg[1])))


def _stack(controls: list, dtype):
    """(S, ...) the gain sets of one kind stacked (numpy, floats in ``dtype``)."""
    return jax.tree_util.tree_map(lambda *xs: np.stack([np.asarray(x, dtype) for x in xs]), *controls)


def _nominal(controls, dtype) -> Gains:
    """The plain gains of a set (a schedule's at rest), numpy: the set-up's nominal gains."""
    g = controls if isinstance(controls, Gains) else controls.at_rest()
    return jax.tree_util.tree_map(lambda x: np.asarray(x, dtype), g)


def _with_kind(st: scenario.Setup, kind: str) -> scenario.Setup:
    """The set-up whose loop takes this kind of gain set (a schedule: evaluated at every tick)."""
    return dataclasses.replace(st, loop=gain_schedule.scheduled_loop(st.loop)) if kind == "schedule" else st


def _scenarios(robot, rows: dict, stacked, dtype) -> Scenario:
    """Scenarios (B,) from columns: azimuth_deg, magnitude_n, duration_s, body (ids), friction,
    gain_set (index into ``stacked``, the sets (S, ...)); no joint noise, nominal masses, onset in
    ``rows['onset']``."""
    az = np.asarray(rows["azimuth_deg"], float)
    B = az.size
    u = np.stack([np.cos(np.deg2rad(az)), np.sin(np.deg2rad(az)), np.zeros(B)], 1)
    g = np.asarray(rows["gain_set"], int)
    return Scenario(
        push=Push(
            force=(np.asarray(rows["magnitude_n"])[:, None] * u)[:, None, :].astype(dtype),
            onset=np.full((B, 1), rows["onset"], dtype),
            duration=np.asarray(rows["duration_s"], dtype)[:, None],
            body=np.asarray(rows["body"], np.int32)[:, None],
        ),
        gains=jax.tree_util.tree_map(lambda x: x[g], stacked),
        joint_offset=np.zeros((B, robot.index.n), dtype),
        friction=np.asarray(rows["friction"], dtype),
        mass_scale=np.ones(B, dtype),
    )


def _run_table(
    st: scenario.Setup,
    scen: Scenario,
    cols: dict,
    folder: pathlib.Path,
    chunk: int,
    tag: str,
    progress: bool,
    push_end: float,
) -> tuple:
    """Run a batch with the sweep's chunk runner (:func:`wbc_jax.jobs.chunks.run_chunks`: Parquet
    parts in ``folder``, named by ``tag`` and reused when they are the run's own): (DataFrame of
    columns + metrics, {compile_s, run_s, envs, physics_steps_per_s})."""
    import pandas as pd

    B = len(cols["gain_set"])
    columns = {k: v for k, v in cols.items() if k != "onset"}
    ran = chunks.run_chunks(
        st, scen, columns, folder, batch=min(chunk, B), push_end=push_end, tag=tag, progress=progress, label=folder.name
    )
    steps = st.loop.n_ticks * st.loop.n_sub
    timing = {
        "compile_s": round(ran.compile_s, 2),
        "run_s": round(ran.run_s, 2),
        "envs": B,
        "physics_steps_per_s": ran.done_envs * steps / ran.run_s if ran.run_s > 0 else None,
    }
    return pd.concat(ran.tables, ignore_index=True), timing


def _envelope(table, cfg: sweep_config.SweepConfig, robot) -> dict:
    """summarize_table of one gain set's rows: survival, envelope fractions (min / median)."""
    t = table.assign(gain_set=0)
    s = sweep_table.summarize_table(t, cfg, robot)
    frac = np.array([e["fraction_of_bound"] for e in s["envelope"].values()])
    mono = np.array([e["fraction_of_bound_monotone"] for e in s["envelope"].values()])
    return {
        "survival_rate": s["survival_rate"],
        "upright_rate": s["upright_rate"],
        "n_envs": s["n_envs"],
        "nan_envs": s["nan_envs"],
        "envelope_fraction_median": float(np.median(frac)),
        "envelope_fraction_min": float(np.min(frac)),
        "envelope_fraction_monotone_median": float(np.median(mono)),
        "envelope_fraction_monotone_min": float(np.min(mono)),
        "peak_torque_nm_median": float(np.median(table["max_abs_torque_nm"])),
        "envelope": {
            str(a): {
                "impulse_ns": e["largest_survived_impulse_ns"],
                "fraction": e["fraction_of_bound"],
                "bound_impulse_ns": e["bound_impulse_ns"],
            }
            for a, e in s["envelope"].items()
        },
    }


def heldout(sets: dict, hc: HeldoutConfig, out, *, progress: bool = True) -> dict:
    """Evaluate gain sets {name: (Gains or GainSchedule, regularisation (2,))} on the held-out grid,
    variations, one-foot task and sinusoid (module docstring), into ``out`` (resumable). Returns
    {name: {"grid": {...}, "variations": {name: {...}}, "one_foot": {...}, "sinusoid_com_rmse_m"}},
    plus "_timing"."""
    out = pathlib.Path(out)
    dtype = scenario.float_dtype()
    impulses = hc.grid_impulses
    result: dict = {name: {"variations": {}} for name in sets}
    timing: dict = {}
    for gi, ((kind, *reg), names) in enumerate(_groups(sets).items()):
        controls = [sets[n][0] for n in names]
        stacked = _stack(controls, dtype)
        tag = hashlib.sha256(
            json.dumps(
                [flat_dict(hc), [store.controls_dict(c) for c in controls], reg], sort_keys=True, default=io.jsonable
            ).encode()
        ).hexdigest()[:10]
        # Stand: the grid and the variations, one program (per-env plant: friction varies).
        cfg = sweep_config.SweepConfig(
            robot=hc.robot,
            controller=hc.controller,
            magnitudes=tuple(hc.grid_magnitudes),
            directions=tuple(hc.grid_directions),
            push_duration=hc.grid_duration,
            push_onset=hc.grid_onset,
            horizon=hc.grid_horizon,
            friction=(0.5, 1.0),
            backend=hc.heldout_backend,
            out=None,
        )
        nominal = _nominal(controls[0], dtype)
        st = _with_kind(sweep.make_setup(cfg, nominal, controller=_controller(reg, hc)), kind)
        robot = st.robot
        vdirs = grids.azimuths(hc.variation_directions)
        blocks = [("grid", "trunk", hc.grid_duration, 1.0, impulses, np.asarray(hc.grid_directions))]
        vimp = np.linspace(impulses[0], impulses[-1], hc.variation_magnitudes)
        for v in hc.variations:
            body, dur, fr = VARIATIONS[v]
            blocks.append((v, body, dur, fr, vimp, vdirs))
        cols = _block_columns(robot, blocks, len(controls), hc.grid_onset)
        table, timing[f"stand_{gi}"] = _run_table(
            st,
            _scenarios(robot, cols, stacked, dtype),
            cols,
            out / f"stand_{gi}",
            hc.chunk_size,
            tag,
            progress,
            hc.grid_onset + hc.grid_duration,
        )
        for s, name in enumerate(names):
            mine = table[table["gain_set"] == s]
            result[name]["grid"] = _envelope(mine[mine["block"] == "grid"], cfg, robot)
            for v in hc.variations:
                result[name]["variations"][v] = _envelope(mine[mine["block"] == v], cfg, robot)
        if hc.one_foot:
            of = dataclasses.replace(
                cfg, task="one-foot", push_onset=hc.one_foot_onset, horizon=hc.one_foot_horizon, friction=(1.0, 1.0)
            )
            st1 = _with_kind(sweep.make_setup(of, nominal, controller=_controller(reg, hc)), kind)
            blocks = [("one_foot", "trunk", hc.grid_duration, 1.0, vimp, vdirs)]
            cols = _block_columns(robot, blocks, len(controls), hc.one_foot_onset)
            table1, timing[f"one_foot_{gi}"] = _run_table(
                st1,
                _scenarios(robot, cols, stacked, dtype),
                cols,
                out / f"one_foot_{gi}",
                hc.chunk_size,
                tag,
                progress,
                hc.one_foot_onset + hc.grid_duration,
            )
            for s, name in enumerate(names):
                result[name]["one_foot"] = _envelope(table1[table1["gain_set"] == s], of, robot)
        if hc.sinusoid_s > 0:
            rmse, timing[f"sinusoid_{gi}"] = sinusoid(controls, reg, hc)
            for s, name in enumerate(names):
                result[name]["sinusoid_com_rmse_m"] = rmse[s]
    result["_timing"] = timing
    return result


def _block_columns(robot, blocks, n_sets: int, onset: float) -> dict:
    """Columns of every (block, gain set, impulse, azimuth) row."""
    cols: dict = {
        k: []
        for k in (
            "block",
            "gain_set",
            "impulse_ns",
            "magnitude_n",
            "azimuth_deg",
            "duration_s",
            "body",
            "friction",
            "mass_scale",
        )
    }
    for name, body, dur, fr, imps, azs in blocks:
        s, imp, az = (a.ravel() for a in np.meshgrid(np.arange(n_sets), imps, azs, indexing="ij"))
        cols["block"] += [name] * s.size
        cols["gain_set"] += s.tolist()
        cols["impulse_ns"] += imp.tolist()
        cols["magnitude_n"] += (imp / dur).tolist()
        cols["azimuth_deg"] += az.tolist()
        cols["duration_s"] += [dur] * s.size
        cols["body"] += [robot.index.pushable_body_id(body)] * s.size
        cols["friction"] += [fr] * s.size
        cols["mass_scale"] += [1.0] * s.size
    out = {k: np.asarray(v) for k, v in cols.items()}
    out["onset"] = onset
    return out


def sinusoid(controls: list, reg, hc: HeldoutConfig) -> tuple[list, dict]:
    """CoM RMSE (m) of each gain set (all Gains or all GainSchedules) on the seed's CoM sinusoid
    (``hc.sinusoid_s`` s, no push), the closed loop of ``wbc-jax balance --task sinusoid`` (metrics
    only), all sets as one batch."""
    sim = SimConfig(record=False, physics=physics.PhysicsConfig(backend=hc.sinusoid_backend))
    dtype = scenario.float_dtype()
    st = scenario.setup(
        "sinusoid",
        duration=hc.sinusoid_s,
        controller=_controller(reg, hc),
        sim=sim,
        gains=_nominal(controls[0], dtype),
        scene=scenario.load_scene(hc.robot, hc.controller.tasks),
    )
    st = _with_kind(st, _kind(controls[0]))
    one = scenario.single(st)
    scen = jax.tree_util.tree_map(lambda x: np.repeat(np.asarray(x), len(controls), 0), one)
    scen = scen.replace(gains=_stack(controls, st.dtype))
    res = runner.run(st, scen)
    cols = metrics_lib.summarize(res.metrics)
    return [float(x) for x in cols["com_rmse_m"]], {
        "compile_s": round(res.compile_s, 2),
        "run_s": round(res.run_s, 2),
        "backend": st.backend,
    }


def run(hc: HeldoutConfig | None = None, *, progress: bool = True) -> dict:
    """The ``wbc-jax heldout`` job: the gain sets of ``hc.sets`` held out into ``hc.out`` (resumable):
    heldout.json, envelope_polar.png. Returns {name: the summary row}."""
    hc = heldout_default_config() if hc is None else hc
    out = pathlib.Path(hc.out)
    if not hc.sets:  # (wbc-jax tune adds its own sets; the heldout job has only these)
        raise ValueError("--sets: give at least one gain set ('default', 'critical' or NAME=FILE)")
    runs.check_output_dir(out, "heldout")
    robot = describe(hc.robot)
    files = set_files(hc.sets, robot)
    sets = load_sets(hc.sets, robot, scenario.float_dtype())
    fp = runs.fingerprint(
        {"heldout": flat_dict(hc), "dtype": str(scenario.float_dtype())},
        [*files.values(), hc.controller.tasks],
        hc.robot,
    )
    runs.claim_output_dir(out, "heldout", fp, resume=True)
    if runs.output_changed(out / "heldout.json") is None:
        # A re-run of a finished run: heldout.json (the timings measured when it ran) stays as it is.
        rep = loader.read_json(out / "heldout.json", "held-out summary")
        return {n: {k: rep[n][k] for k in SUMMARY_KEYS} for n in sets}
    results = heldout(sets, hc, out / "parts", progress=progress)
    rep = write_heldout(
        out / "heldout.json",
        results,
        {},
        extra={"config": flat_dict(hc)},
        inputs={**files, "tasks": hc.controller.tasks},
    )
    runs.record_output(out / "heldout.json")
    tuning_plots.envelope_polar(rep, out / "envelope_polar.png")
    return {n: {k: rep[n][k] for k in SUMMARY_KEYS} for n in sets}
