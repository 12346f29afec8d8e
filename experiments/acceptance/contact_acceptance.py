"""Measured acceptance of multi-contact balancing under pushes (issue 17).

    python experiments/acceptance/contact_acceptance.py --quick                      # CPU (C MuJoCo), float32
    python experiments/acceptance/contact_acceptance.py --backend jax                # GPU (MJX), float32
    python experiments/acceptance/contact_acceptance.py --only ramp wall [--quick]   # some parts; the others kept

Parts (each writes its keys into OUT/acceptance.json, with the device, precision and provenance; re-running a
part replaces its keys):

- ``sweep``: the hand-on-table chest-push sweep (experiments/tasks/hand_on_table.yaml, contact
  detection on; 0.1 s pushes, 20-600 N x 8 directions, 3 s as results/contacts; ``--quick``: 100-400 N
  x 4 directions, 2 s). ``hand_sweep_max_violation_rel``: the largest violation of a contact's own
  constraints by the commanded wrenches, relative to that contact's normal force, at any tick of any
  environment that did not fall (also given for the strictly surviving ones).
  ``phantom_contact_max_s``: the longest time any environment counted a contact (activation > 0)
  that MuJoCo did not see (zero normal force in the last physics step of the tick).
- ``ramp``: the hand, touching the table (its point on the top, as in hand_on_table.yaml), ramped
  in by its schedule (0.5 s minimum-jerk from 0.5 s) and out again (from 1.5 s); contact detection
  off (with it, a hand that touches with no force would be gated out before its ramp).
  ``ramp_feet_ripple_rel``: the feet's measured normal forces from 0.5 s to 2.3 s less their 0.1 s
  moving average (the slow load transfer of the 5 N and the robot's sway), peak to peak, relative
  to their mean (the larger foot's).
- ``posture``: the hand circle below a posture task on the torso and the right arm
  (experiments/tasks/reach_below_upper_body.yaml; 20 s, ``--quick``: 6 s).
  ``posture_below_hand_fell``, ``posture_below_hand_rmse_rad``: RMSE over ticks of the norm of the
  7 joints' error (and the largest per-joint RMSE).
- ``wall``: the left hand leaning on a wall (experiments/tasks/hand_on_wall.yaml, 5 N desired; 10 s).
  ``wall_hand_force_max_err_n``: the largest |measured - desired| hand normal force after 1 s; and
  the push envelope toward the wall (forward chest pushes, 0.1 s) with the hand against the feet
  alone (experiments/tasks/feet_contacts.yaml): the largest impulse survived below the first
  failure, and their ratio (all 8 directions on the GPU).

Precision follows JAX (float32 unless JAX_ENABLE_X64=1); the device is JAX's first.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import math
import pathlib
import time

import jax
import numpy as np

from wbc_jax.control import task_files
from wbc_jax.core import io, options, provenance
from wbc_jax.jobs import balance, sweep, sweep_config, sweep_table
from wbc_jax.robot import scene as contact_scene
from wbc_jax.sim import metrics as metrics_lib
from wbc_jax.sim import physics, runner, scenario
from wbc_jax.sim.state import SimConfig

ROOT = pathlib.Path(__file__).resolve().parents[2]

EXPERIMENTS = pathlib.Path(__file__).resolve().parents[1]
HAND = EXPERIMENTS / "tasks" / "hand_on_table.yaml"
WALL = EXPERIMENTS / "tasks" / "hand_on_wall.yaml"
FEET = EXPERIMENTS / "tasks" / "feet_contacts.yaml"
POSTURE = EXPERIMENTS / "tasks" / "reach_below_upper_body.yaml"
PARTS = ("sweep", "ramp", "posture", "wall")
POSTURE_JOINTS = 7  # the joints task of reach_below_upper_body.yaml


def sizes(quick: bool) -> dict:
    if quick:
        return dict(
            magnitudes=(100.0, 200.0, 300.0, 400.0),
            directions=(0.0, 90.0, 180.0, 270.0),
            horizon=2.0,
            posture_s=6.0,
            wall_s=10.0,
            wall_magnitudes=tuple(np.arange(100.0, 401.0, 50.0)),
            wall_directions=(0.0,),
        )
    return dict(
        magnitudes=tuple(np.linspace(20.0, 600.0, 30)),
        directions=tuple(np.arange(8) * 45.0),
        horizon=3.0,
        posture_s=20.0,
        wall_s=10.0,
        wall_magnitudes=tuple(np.linspace(20.0, 600.0, 30)),
        wall_directions=tuple(np.arange(8) * 45.0),
    )


def entry(value, prov: dict, **details) -> dict:
    """One figure: its value, the device (provenance.device_label), the precision, its provenance."""
    return {
        "value": value,
        "device": prov["device"]["label"],
        "dtype": str(scenario.float_dtype()),
        "provenance": prov,
        **details,
    }


def as_dict(records) -> dict:
    """A Trajectory record as a dict of numpy arrays."""
    return {f.name: np.asarray(getattr(records, f.name)) for f in dataclasses.fields(records)}


def normal_force(traj: dict, cset, k: int, key: str = "f_meas") -> np.ndarray:
    """(..., T) normal force of contact k in a record (batch axes first)."""
    sl = cset.slices()[k]
    return np.einsum("...ti,...ti->...t", traj[key][..., sl.start : sl.start + 3], traj["contact_normal"][..., k, :])


def single_run(scene: scenario.Scene, duration: float, backend: str):
    """One recorded closed-loop run of a scene (stand task): (setup, trajectory dict, metrics)."""
    sim = SimConfig(record=True, physics=physics.PhysicsConfig(backend=backend))
    st = scenario.setup("stand", duration=duration, sim=sim, scene=scene)
    run = runner.run(st, scenario.single(st))
    traj = {k: v[0] for k, v in as_dict(run.records).items()}
    metrics = metrics_lib.summarize(jax.tree_util.tree_map(lambda x: x[0], run.metrics))
    print(
        f"  {pathlib.Path(scene.tasks_file or 'feet').stem}: {duration} s, {run.compile_s:.0f} s compiling, "
        f"{run.run_s:.0f} s running",
        flush=True,
    )
    return st, traj, metrics


def longest_run(mask: np.ndarray) -> np.ndarray:
    """(...,) the longest run of True along the last axis."""
    best = np.zeros(mask.shape[:-1], int)
    run = np.zeros(mask.shape[:-1], int)
    for t in range(mask.shape[-1]):
        run = np.where(mask[..., t], run + 1, 0)
        best = np.maximum(best, run)
    return best


def push_sweep(spec: pathlib.Path, backend: str, magnitudes, directions, horizon: float, record: bool):
    """A chest-push sweep of a contact file: (setup, metrics dict of columns, records or None)."""
    cfg = sweep_config.SweepConfig(
        magnitudes=tuple(magnitudes),
        directions=tuple(directions),
        horizon=horizon,
        push_onset=0.5,
        push_duration=0.1,
        backend=backend,
    )
    cfg = options.replace(cfg, tasks=str(spec))
    dtype = scenario.float_dtype()
    st = sweep.make_setup(cfg, sweep.base_gains(cfg, 23, dtype), record=record)
    scen, columns = sweep.build_scenarios(cfg, st.gains, st.robot.index.n, dtype)
    run = runner.run(st, scen)
    table = {**columns, **metrics_lib.summarize(run.metrics, cfg.push_onset + cfg.push_duration)}
    print(
        f"  {spec.stem}: {len(table['survived'])} envs, {run.compile_s:.0f} s compiling, {run.run_s:.0f} s running",
        flush=True,
    )
    return st, table, run.records


def part_sweep(args, sz, prov: dict) -> dict:
    st, table, rec = push_sweep(HAND, args.backend, sz["magnitudes"], sz["directions"], sz["horizon"], record=True)
    rec = as_dict(rec)
    cset = st.loop.contact_set
    dt = st.loop.cfg.control_dt
    viol = rec["qp_violation"]  # (B, T): max over the active contacts, relative
    upright, survived = np.asarray(table["upright"]), np.asarray(table["survived"])
    phantom = np.zeros(len(upright))
    per_contact = {}
    for k, c in enumerate(cset.contacts):
        if c.foot >= 0:
            continue
        seen = normal_force(rec, cset, k) > 0.0
        counted = rec["activation"][:, :, k] > 0.0
        ticks = longest_run(counted & ~seen)
        phantom = np.maximum(phantom, ticks * dt)
        per_contact[c.name] = {
            "phantom_max_s": float(ticks.max() * dt),
            "envs_leaving": int(np.any(~seen, axis=1).sum()),
        }
    grid = {
        "magnitudes_n": [float(sz["magnitudes"][0]), float(sz["magnitudes"][-1]), len(sz["magnitudes"])],
        "directions_deg": list(sz["directions"]),
        "horizon_s": sz["horizon"],
        "push_s": [0.5, 0.1],
    }
    return {
        "hand_sweep_max_violation_rel": entry(
            float(viol[upright].max()) if upright.any() else None,
            prov,
            definition="max over ticks and contacts of the commanded wrench's constraint violation relative to the "
            "contact's normal force, over the environments that did not fall",
            survived_only=float(viol[survived].max()) if survived.any() else None,
            all_envs=float(viol.max()),
            n_envs=int(len(upright)),
            n_upright=int(upright.sum()),
            n_survived=int(survived.sum()),
            qp_infeasible_envs=int((np.asarray(table["qp_infeasible_ticks"]) > 0).sum()),
            grid=grid,
        ),
        "phantom_contact_max_s": entry(
            float(phantom.max()),
            prov,
            definition="longest time an environment's controller counted a contact (activation > 0) while MuJoCo's "
            "normal force on it was zero, over every environment",
            per_contact=per_contact,
            upright_only=float(phantom[upright].max()) if upright.any() else None,
            grid=grid,
        ),
    }


RAMP = {"start": 0.5, "stop": 1.5, "ramp": 0.5}  # s, the hand's schedule in the ramp part


def ramp_scene() -> scenario.Scene:
    """hand_on_table.yaml with the hand ramped in and out by its schedule (RAMP), no detection."""
    spec = task_files.load_spec_file(HAND)
    robot = scenario.load_scene("icub").robot
    qpos = task_files.initial_qpos(robot, spec["initial_posture_deg"])
    cons = [dict(c, activation=RAMP, detect=False) if c["name"] == "left_hand" else c for c in spec["contacts"]]
    robot, cset = contact_scene.build_scene("icub", cons, copy.deepcopy(spec["scene"]), qpos)
    return scenario.Scene(robot, None, cset, qpos, str(HAND))


def part_ramp(args, sz, prov: dict) -> dict:
    end = RAMP["stop"] + RAMP["ramp"] + 0.3
    st, traj, _ = single_run(ramp_scene(), end, args.backend)
    cset = st.loop.contact_set
    t = traj["t"]
    window = t >= RAMP["start"]
    width = int(round(0.1 / st.loop.cfg.control_dt)) | 1  # odd: a centred average

    def ripple(x):  # peak to peak of x less its moving average, over the window's interior
        x = x[window]
        return float(np.ptp(x[width // 2 : -(width // 2)] - np.convolve(x, np.ones(width) / width, "valid")))

    out, worst = {}, 0.0
    for k, c in enumerate(cset.contacts):
        meas, cmd = normal_force(traj, cset, k), normal_force(traj, cset, k, "f_cmd")
        if c.foot < 0:
            on = (t >= RAMP["start"] + RAMP["ramp"]) & (t < RAMP["stop"])
            out[c.name] = {
                "meas_on_median_n": float(np.median(meas[on])),
                "meas_before_ramp_n": float(meas[~window].max()),
            }
            continue
        mean = float(meas[window].mean())
        out[c.name] = {
            "ripple_rel": ripple(meas) / mean,
            "cmd_ripple_rel": ripple(cmd) / mean,
            "mean_n": mean,
            "tick_jump_max_rel": float(np.abs(np.diff(meas[window])).max() / mean),
            "range_n": [float(meas[window].min()), float(meas[window].max())],
        }
        worst = max(worst, out[c.name]["ripple_rel"])
    return {
        "ramp_feet_ripple_rel": entry(
            worst,
            prov,
            backend=st.backend,
            contacts=out,
            hand_schedule_s=RAMP,
            definition="feet measured normal forces from the ramp-in's start to 0.3 s after the ramp-out, less their 0.1 s "
            "moving average, peak to peak, relative to their mean; the larger foot's",
        )
    }


def part_posture(args, sz, prov: dict) -> dict:
    st, traj, m = single_run(scenario.load_scene("icub", POSTURE), sz["posture_s"], args.backend)
    tracking = balance.task_tracking(st.loop.controller.stack, traj)
    err = traj["task_err"][:, :POSTURE_JOINTS]
    return {
        "posture_below_hand_fell": entry(
            bool(m["fell"] or m["nan"]),
            prov,
            duration_s=sz["posture_s"],
            com_rmse_m=m["com_rmse_m"],
            max_abs_torque_nm=m["max_abs_torque_nm"],
        ),
        "posture_below_hand_rmse_rad": entry(
            tracking["posture_joints"]["rmse"],
            prov,
            duration_s=sz["posture_s"],
            definition="RMSE over ticks of the norm of the 7 posture joints' error (torso, right arm)",
            max_rad=tracking["posture_joints"]["max"],
            per_joint_rmse_max_rad=float(np.sqrt((err**2).mean(0)).max()),
            hand_rmse_m=tracking["right_hand"]["rmse"],
        ),
    }


def part_wall(args, sz, prov: dict) -> dict:
    st, traj, m = single_run(scenario.load_scene("icub", WALL), sz["wall_s"], args.backend)
    hand = balance.contact_tracking(st.loop.contact_set, traj)["left_hand"]
    envelope = {}
    tables = {}
    for name, spec in (("hand", WALL), ("feet", FEET)):
        _, tables[name], _ = push_sweep(
            spec, args.backend, sz["wall_magnitudes"], sz["wall_directions"], sz["horizon"], record=False
        )
    import pandas as pd

    for az in sz["wall_directions"]:
        row = {}
        for name in ("hand", "feet"):
            table = pd.DataFrame({k: np.asarray(v) for k, v in tables[name].items()})
            group = table[np.isclose(table["azimuth_deg"], az)]
            row[f"{name}_impulse_ns"] = sweep_table.envelope_of(group)[1]
            row[f"{name}_survival_rate"] = float(group["survived"].mean())
        row["gain"] = row["hand_impulse_ns"] / row["feet_impulse_ns"] if row["feet_impulse_ns"] > 0 else None
        envelope[str(float(az))] = row
    return {
        "wall_hand_force_max_err_n": entry(
            hand["normal_force_err_max_n"],
            prov,
            duration_s=sz["wall_s"],
            fell=bool(m["fell"] or m["nan"]),
            definition="max over ticks after 1 s of |MuJoCo's hand normal force - 5 N|",
            normal_force_meas_median_n=hand["normal_force_meas_median_n"],
            max_drift_m=hand["max_drift_m"],
            com_rmse_m=m["com_rmse_m"],
            max_constraint_violation=m["max_constraint_violation"],
            push_envelope_toward_wall=envelope,
            envelope_definition="largest impulse (N s) survived below the first failure of chest pushes of 0.1 s at "
            "0.5 s (azimuth 0: forward, into the wall), with the hand vs the feet alone; gain = ratio",
            envelope_grid={
                "magnitudes_n": [
                    float(sz["wall_magnitudes"][0]),
                    float(sz["wall_magnitudes"][-1]),
                    len(sz["wall_magnitudes"]),
                ],
                "horizon_s": sz["horizon"],
            },
        )
    }


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument(
        "--backend",
        default="mujoco",
        choices=["mujoco", "jax"],
        help="physics: C MuJoCo (CPU) or MJX's JAX implementation (GPU; no Warp: records need contact forces)",
    )
    p.add_argument("--quick", action="store_true", help="CPU sizes (see the module docstring)")
    p.add_argument("--only", nargs="+", choices=PARTS, default=list(PARTS))
    p.add_argument("--out", default="results/contacts")
    args = p.parse_args(argv)
    runner.enable_compilation_cache()
    inputs = {"hand_on_table": HAND, "hand_on_wall": WALL, "feet": FEET, "posture": POSTURE}
    prov = provenance.record(inputs, argv=provenance.script_argv(__file__, argv))
    out = pathlib.Path(args.out) / "acceptance.json"
    result = json.loads(out.read_text()) if out.exists() else {}
    sz = sizes(args.quick)
    for part in args.only:
        t0 = time.time()
        print(f"{part} ...", flush=True)
        values = globals()[f"part_{part}"](args, sz, prov)
        for key, value in values.items():
            value["wall_time_s"] = round(time.time() - t0, 1)
            print(f"  {key}: {json.dumps(value['value'])}", flush=True)
        result.update(values)
        io.atomic_write_json(out, _jsonable(result))
    print(json.dumps({k: v["value"] for k, v in result.items()}, indent=1))
    return result


def _jsonable(value):
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (np.generic, np.ndarray)):
        return _jsonable(value.item() if np.ndim(value) == 0 else value.tolist())
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


if __name__ == "__main__":
    main()
