"""[visualisation] Rollouts as rerun recordings: the robot, CoM, support polygon, wrenches, pushes.

Host-side only (numpy in, ``.rrd`` or a viewer out); never imported by traced code.

A recording holds, on the ``sim_time`` timeline (seconds, one row per controller tick)::

    world/robot/<body>              Transform3D per tick (C MuJoCo mj_kinematics of traj qpos)
    world/robot/<body>/geom_<g>     static Transform3D (geom in body) + static Mesh3D (iCub STL)
    world/floor                     static Boxes3D
    world/com, world/com_ref        Points3D (now) ; world/com/trail, world/com_ref/trail LineStrips3D
    world/support_polygon           LineStrips3D: convex hull of the sole spheres touching the floor
    world/contacts/f_meas, f_cmd    Arrows3D: force part of each sole wrench, at the sole origins
    world/push                      Arrows3D on the pushed body (its tip at the body's CoM)
    plots/com_error_mm, plots/Ldot_star, plots/Ldot_meas, plots/tau,
    plots/f_cmd, plots/f_meas       Scalars

Runs on disk (``wbc-jax view``): a ``balance`` run (``trajectory.npz``) is logged as is; env I of
a push sweep (``results.parquet`` + ``summary.json``) is first re-simulated with trajectory
recording from its stored scenario (:func:`replay_sweep_env`).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import pathlib

import mujoco
import numpy as np

from wbc_jax import model as model_lib

TIMELINE = "sim_time"
FORCE_SCALE = 1.0 / 500.0  # m per N for the arrows: the ~160 N per sole of standing -> 0.32 m
TRAIL_S = 1.0  # s of CoM history drawn behind the CoM
CONTACT_TOL = 2e-3  # m: a sole sphere whose bottom is this close to the floor counts as touching
WRENCH_NAMES = [f"{foot} {c}" for foot in "LR" for c in ("fx", "fy", "fz", "tx", "ty", "tz")]
AXES6 = ["fx", "fy", "fz", "tx", "ty", "tz"]
TRAJ_FIELDS = ("t", "qpos", "com", "com_ref", "tau", "f_cmd", "f_meas", "Ldot_star", "Ldot_meas",
               "feet_pos", "push")  # fmt: skip


@functools.lru_cache(maxsize=2)
def visual_model(robot: str = "icub") -> mujoco.MjModel:
    """The robot's C model with its visual meshes (from the installed icub-models), cached."""
    return model_lib.load_mj_model(robot, visual=True)


def _xyzw(wxyz: np.ndarray) -> np.ndarray:
    """MuJoCo quaternions (..., 4) w-first -> rerun's x-first."""
    return np.concatenate([wxyz[..., 1:], wxyz[..., :1]], axis=-1)


def _names(m: mujoco.MjModel, obj, count: int) -> list[str]:
    return [mujoco.mj_id2name(m, obj, i) or f"{i}" for i in range(count)]


def body_poses(m: mujoco.MjModel, qpos: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World poses of all bodies and geoms along a trajectory (C MuJoCo ``mj_kinematics``).

    Args:
      m: C model (the visual one: same bodies and qpos layout as the physics model).
      qpos: (T, nq) generalised positions.

    Returns:
      (xpos (T, nbody, 3), xquat (T, nbody, 4) w-first, geom_xpos (T, ngeom, 3)).
    """
    qpos = np.asarray(qpos, float)
    if qpos.ndim != 2 or qpos.shape[1] != m.nq:
        raise ValueError(f"qpos must have shape (T, {m.nq}), got {qpos.shape}")
    d = mujoco.MjData(m)
    T = qpos.shape[0]
    xpos, xquat = np.empty((T, m.nbody, 3)), np.empty((T, m.nbody, 4))
    gpos = np.empty((T, m.ngeom, 3))
    for k in range(T):
        d.qpos[:] = qpos[k]
        mujoco.mj_kinematics(m, d)
        xpos[k], xquat[k], gpos[k] = d.xpos, d.xquat, d.geom_xpos
    return xpos, xquat, gpos


def convex_hull_2d(points: np.ndarray) -> np.ndarray:
    """Convex hull of planar points (N, 2), counter-clockwise, closed (first point repeated).

    Andrew's monotone chain; fewer than 3 distinct points give them as they are (a point or a
    segment: the support "polygon" of a sole touching on one edge)."""
    pts = np.unique(np.asarray(points, float).reshape(-1, 2), axis=0)
    if len(pts) < 3:
        return pts

    def half(seq):
        chain: list = []
        for p in seq:
            while len(chain) >= 2 and np.cross(chain[-1] - chain[-2], p - chain[-2]) <= 0:
                chain.pop()
            chain.append(p)
        return chain[:-1]

    hull = half(pts) + half(pts[::-1])
    return np.array(hull + [hull[0]])


def support_polygons(m: mujoco.MjModel, geom_xpos: np.ndarray) -> list[np.ndarray]:
    """Per tick, the closed hull (K, 2) of the sole contact spheres within CONTACT_TOL of the floor.

    Args: m: C model; geom_xpos: (T, ngeom, 3) from :func:`body_poses`."""
    names = _names(m, mujoco.mjtObj.mjOBJ_GEOM, m.ngeom)
    soles = np.array([g for g, n in enumerate(names) if "_foot_contact" in n])
    if soles.size == 0:
        raise ValueError("the model has no sole contact geoms ('*_foot_contact*')")
    bottom = geom_xpos[:, soles, 2] - m.geom_size[soles, 0]
    return [convex_hull_2d(geom_xpos[k, soles[bottom[k] < CONTACT_TOL], :2]) for k in range(len(bottom))]


def _check_traj(traj: dict) -> int:
    missing = [f for f in TRAJ_FIELDS if f not in traj]
    if missing:
        raise ValueError(f"trajectory lacks fields {missing}; needs {list(TRAJ_FIELDS)}")
    T = len(traj["t"])
    bad = [f for f in TRAJ_FIELDS if len(traj[f]) != T]
    if T == 0 or bad:
        raise ValueError(f"trajectory fields {bad} do not have the length of t ({T})")
    if np.shape(traj["f_cmd"])[1:] != (12,):
        raise ValueError(
            f"this run has a general contact set ({np.shape(traj['f_cmd'])[1]} wrench entries, "
            f"{np.shape(traj['feet_pos'])[1]} contacts); the rerun view shows two-feet runs only (not done yet); "
            "its plots (contact_forces.png) and metrics.json show the contacts"
        )
    return T


def log_robot_meshes(rec, m: mujoco.MjModel) -> list[str]:
    """Log every mesh geom once (static), under its body's entity. Returns the body entity paths
    (nbody,), index = body id; world (body 0) is ``world/robot``.

    The compiled model's vertices are used (not the STL files directly): MuJoCo re-centres each
    mesh at its centroid and moves that offset into geom_pos/geom_quat, so these two agree."""
    import rerun as rr

    bodies = _names(m, mujoco.mjtObj.mjOBJ_BODY, m.nbody)
    paths = ["world/robot"] + [f"world/robot/{bodies[b]}" for b in range(1, m.nbody)]
    for g in np.flatnonzero(m.geom_type == mujoco.mjtGeom.mjGEOM_MESH):
        mesh = m.geom_dataid[g]
        v0, nv = m.mesh_vertadr[mesh], m.mesh_vertnum[mesh]
        f0, nf = m.mesh_faceadr[mesh], m.mesh_facenum[mesh]
        rgba = m.mat_rgba[m.geom_matid[g]] if m.geom_matid[g] >= 0 else m.geom_rgba[g]
        path = f"{paths[m.geom_bodyid[g]]}/geom_{g}"
        rec.log(path, rr.Transform3D(translation=m.geom_pos[g], quaternion=_xyzw(m.geom_quat[g])), static=True)
        rec.log(
            path,
            rr.Mesh3D(
                vertex_positions=m.mesh_vert[v0 : v0 + nv],
                triangle_indices=m.mesh_face[f0 : f0 + nf],
                albedo_factor=(np.clip(rgba, 0, 1) * 255).astype(np.uint8),
            ),
            static=True,
        )
    return paths


def log_trajectory(rec, traj: dict, *, robot: str = "icub", push_body: str = "chest",
                   joints: list[str] | None = None) -> None:  # fmt: skip
    """Log a recorded rollout to a rerun recording stream.

    Args:
      rec: ``rr.RecordingStream``.
      traj: numpy fields of :class:`rollout.Trajectory` (time-major, length T): t (T,),
        qpos (T, nq), com/com_ref (T, 3), tau (T, n), f_cmd/f_meas (T, 12), Ldot_star/Ldot_meas
        (T, 6), feet_pos (T, 2, 3), push (T, 3).
      robot: robot name (visual model). push_body: body the push acts on (arrow tip at its CoM).
      joints: joint names (n,) for the torque series (default: indices).
    """
    import rerun as rr

    T = _check_traj(traj)
    m = visual_model(robot)
    bodies = _names(m, mujoco.mjtObj.mjOBJ_BODY, m.nbody)
    model_lib._check_name("body", push_body, bodies[1:])
    t = np.asarray(traj["t"], float)
    time = [rr.TimeColumn(TIMELINE, duration=t)]
    xpos, xquat, gpos = body_poses(m, traj["qpos"])

    # Static scene: meshes, floor, series styles.
    paths = log_robot_meshes(rec, m)
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    rec.log("world/floor", rr.Boxes3D(centers=[[0, 0, -0.005]], half_sizes=[[1.0, 1.0, 0.005]],
                                      colors=[[90, 90, 90, 255]], fill_mode="solid"), static=True)  # fmt: skip
    n = np.asarray(traj["tau"]).shape[1]
    series = {
        "plots/com_error_mm": ["|CoM - CoM_ref|"],
        "plots/Ldot_star": [f"L̇* {a}" for a in AXES6],
        "plots/Ldot_meas": [f"L̇ meas {a}" for a in AXES6],
        "plots/tau": list(joints) if joints is not None else [f"tau_{j}" for j in range(n)],
        "plots/f_cmd": [f"cmd {w}" for w in WRENCH_NAMES],
        "plots/f_meas": [f"meas {w}" for w in WRENCH_NAMES],
    }
    for path, names in series.items():
        rec.log(path, rr.SeriesLines(names=names), static=True)

    # Columns (one call per entity for all ticks): body poses and time series.
    for b in range(1, m.nbody):
        rec.send_columns(paths[b], indexes=time,
                         columns=rr.Transform3D.columns(translation=xpos[:, b], quaternion=_xyzw(xquat[:, b])))  # fmt: skip
    com_err = 1e3 * np.linalg.norm(np.asarray(traj["com"]) - np.asarray(traj["com_ref"]), axis=1)
    values = {
        "plots/com_error_mm": com_err[:, None], "plots/Ldot_star": traj["Ldot_star"],
        "plots/Ldot_meas": traj["Ldot_meas"], "plots/tau": traj["tau"],
        "plots/f_cmd": traj["f_cmd"], "plots/f_meas": traj["f_meas"],
    }  # fmt: skip
    for path, v in values.items():
        v = np.asarray(v, float).reshape(T, -1)
        rec.send_columns(path, indexes=time,
                         columns=rr.Scalars.columns(scalars=v.ravel()).partition([v.shape[1]] * T))  # fmt: skip

    # Per tick: CoM and trails, support polygon, wrench and push arrows.
    polys = support_polygons(m, gpos)
    trail = max(1, int(round(TRAIL_S / (t[1] - t[0])))) if T > 1 else 1
    push_id = bodies.index(push_body)
    com, com_ref = np.asarray(traj["com"]), np.asarray(traj["com_ref"])
    feet = np.asarray(traj["feet_pos"]).reshape(T, 2, 3)
    for k in range(T):
        rec.set_time(TIMELINE, duration=float(t[k]))
        lo = max(0, k - trail)
        rec.log("world/com", rr.Points3D([com[k]], radii=0.012, colors=[[230, 60, 40]], labels=["CoM"]))
        rec.log("world/com_ref", rr.Points3D([com_ref[k]], radii=0.008, colors=[[40, 200, 80]]))
        rec.log("world/com/trail", rr.LineStrips3D([com[lo : k + 1]], radii=0.003, colors=[[230, 60, 40]]))
        rec.log("world/com_ref/trail", rr.LineStrips3D([com_ref[lo : k + 1]], radii=0.002, colors=[[40, 200, 80]]))
        poly = polys[k]
        strip = np.column_stack([poly, np.full(len(poly), 1e-3)]) if len(poly) else np.zeros((0, 3))
        rec.log("world/support_polygon", rr.LineStrips3D([strip], radii=0.003, colors=[[250, 200, 0]]))
        for name, color in (("f_meas", [60, 120, 250]), ("f_cmd", [250, 250, 250])):
            f = np.asarray(traj[name][k]).reshape(2, 6)[:, :3] * FORCE_SCALE
            rec.log(f"world/contacts/{name}", rr.Arrows3D(vectors=f, origins=feet[k], colors=[color] * 2,
                                                          radii=0.006, labels=["L", "R"]))  # fmt: skip
        p = np.asarray(traj["push"][k], float)
        if np.any(p != 0):
            v = p * FORCE_SCALE
            rec.log("world/push", rr.Arrows3D(vectors=[v], origins=[xpos[k, push_id] - v],
                                              colors=[[255, 0, 200]], radii=0.01,
                                              labels=[f"push {np.linalg.norm(p):.0f} N"]))  # fmt: skip
        else:
            rec.log("world/push", rr.Arrows3D(vectors=np.zeros((0, 3))))


def _load_json(path: pathlib.Path) -> dict:
    if not path.exists():
        raise FileNotFoundError(f"{path} is missing")
    return json.loads(path.read_text())


def run_kind(run_dir: str | pathlib.Path) -> str:
    """``"balance"`` (trajectory.npz) or ``"sweep"`` (results.parquet + summary.json)."""
    run_dir = pathlib.Path(run_dir)
    if not run_dir.is_dir():
        raise FileNotFoundError(f"run directory {run_dir} does not exist")
    if (run_dir / "trajectory.npz").exists():
        return "balance"
    if (run_dir / "results.parquet").exists() or (run_dir / "manifest.json").exists():
        return "sweep"
    raise FileNotFoundError(
        f"{run_dir} is neither a balance run (no trajectory.npz) nor a finished push sweep "
        f"(no results.parquet); found: {sorted(p.name for p in run_dir.iterdir())}"
    )


def sweep_config(summary: dict):
    """The :class:`sweep.SweepConfig` stored in a sweep's summary.json (lists back to tuples)."""
    from wbc_jax import sweep

    values = {k: tuple(v) if isinstance(v, list) else v for k, v in summary["config"].items()}
    known = {f.name for f in dataclasses.fields(sweep.SweepConfig)}
    return sweep.SweepConfig(**{k: v for k, v in values.items() if k in known})


_REPLAY: dict = {}  # (sweep key, robot, dtype) -> (jitted recording rollout, d0, consts)


def replay_sweep_env(run_dir: str | pathlib.Path, env: int, *, robot_name: str = "icub"):
    """Re-simulate env ``env`` of a finished push sweep, recording its trajectory.

    The scenario is rebuilt deterministically from the stored config, seed and base gains
    (:func:`sweep.build_scenarios`): same push, gain set, joint offset, friction and mass scale
    (plant = :func:`sweep.plant_model`, controller on the nominal model), as in
    :func:`sweep.make_batched_runner`. Run in the dtype the sweep ran in (float32 from the CLI,
    float64 with x64 on): the replay then equals the sweep's metrics.

    Returns:
      (traj dict of numpy (T, ...), replay metrics columns dict, the sweep's table row dict).

    Raises:
      FileNotFoundError: missing files. ValueError: env out of range, or the rebuilt scenario
        does not match the stored row (the sweep was written by other code).
    """
    import jax
    import jax.numpy as jnp
    import pandas as pd

    from wbc_jax import balance, sweep
    from wbc_jax import controller as ctrl_lib

    run_dir = pathlib.Path(run_dir)
    results = run_dir / "results.parquet"
    if not results.exists():
        raise FileNotFoundError(f"{results} is missing: the sweep has not finished; rerun it with the same --out")
    summary = _load_json(run_dir / "summary.json")
    table = pd.read_parquet(results)
    if not 0 <= env < len(table):
        raise ValueError(f"env {env} is out of range: this sweep has envs 0..{len(table) - 1}")
    cfg = sweep_config(summary)
    robot = model_lib.load_robot(robot_name)
    stack = contact_set = qpos = None
    if cfg.tasks_file is not None:  # the sweep's motion tasks, contacts and scene
        robot, stack, contact_set, qpos = balance.load_scenario(robot_name, cfg.tasks_file)
    n = robot.index.n
    dtype = np.dtype(jnp.zeros(()).dtype)
    base = ctrl_lib.gains_from_dict(summary["gains"], n, dtype)
    scen, columns = sweep.build_scenarios(cfg, base, n, dtype)
    row = table[table["env"] == env].iloc[0].to_dict()
    for name, col in columns.items():
        if not np.isclose(float(col[env]), float(row[name]), rtol=1e-6, atol=1e-9):
            raise ValueError(f"scenario column {name!r} of env {env}: rebuilt {col[env]}, stored {row[name]}")
    one = jax.tree_util.tree_map(lambda x: jnp.asarray(np.asarray(x)[env]), scen)

    key = (cfg.key(), robot_name, str(dtype))
    if key not in _REPLAY:  # one compilation per sweep definition (replays of other envs reuse it)
        rollout, d0, _, consts, _ = balance.setup(
            robot, cfg.task, duration=cfg.horizon, forces=cfg.forces, postural=cfg.postural,
            sim=dict(record=True, push_body=cfg.body, solver_iterations=cfg.solver_iterations),
            stack=stack, contact_set=contact_set, qpos=qpos,
        )  # fmt: skip
        _REPLAY[key] = (jax.jit(rollout), d0, consts)
    run, d0, consts = _REPLAY[key]
    mx = robot.mjx_model
    d = d0.replace(qpos=d0.qpos.at[robot.index.qpos_joints].add(one.joint_offset))
    plant = sweep.plant_model(mx, one.friction, one.mass_scale)
    metrics, traj = run(mx, d, one.gains, consts, one.push, plant)
    traj = {k: np.asarray(getattr(traj, k)) for k in traj.__dataclass_fields__}
    cols = sweep.metrics_columns(metrics, cfg.push_onset + cfg.push_duration)
    return traj, {k: np.asarray(v).item() for k, v in cols.items()}, row


def load_run(run_dir: str | pathlib.Path, env: int | None = None) -> tuple[dict, dict]:
    """The trajectory of a run dir and how to draw it.

    Returns:
      (traj dict, info {"kind", "push_body", "joints", "name"}).

    Raises:
      FileNotFoundError / ValueError: unknown dir, missing files, env given for a balance run or
        missing / out of range for a sweep.
    """
    run_dir = pathlib.Path(run_dir)
    kind = run_kind(run_dir)
    joints = list(model_lib.ICUB_JOINTS)
    if kind == "balance":
        if env is not None:
            raise ValueError(f"{run_dir} is a balance run (one trajectory): --env applies to sweeps only")
        with np.load(run_dir / "trajectory.npz") as z:
            traj = {k: z[k] for k in z.files}
        joints = [str(j) for j in traj.pop("joints", joints)]
        return traj, {"kind": kind, "push_body": "chest", "joints": joints, "name": "rollout"}
    if env is None:
        import pandas as pd

        results = run_dir / "results.parquet"
        if not results.exists():
            raise FileNotFoundError(f"{results} is missing: the sweep has not finished")
        size = len(pd.read_parquet(results))
        raise ValueError(f"{run_dir} is a push sweep of {size} envs: choose one with --env I, I in 0..{size - 1}")
    traj, _, _ = replay_sweep_env(run_dir, env)
    body = sweep_config(_load_json(run_dir / "summary.json")).body
    return traj, {"kind": kind, "push_body": body, "joints": joints, "name": f"env_{env}"}


def view(run_dir: str | pathlib.Path, env: int | None = None, *, out: str | pathlib.Path | None = None,
         spawn: bool = False) -> pathlib.Path | None:  # fmt: skip
    """Log a run (or sweep env) to rerun: write ``out`` (default RUN_DIR/rollout.rrd or
    RUN_DIR/env_I.rrd) or, with ``spawn``, open a viewer. Returns the .rrd path (None if spawned)."""
    import rerun as rr

    run_dir = pathlib.Path(run_dir)
    traj, info = load_run(run_dir, env)
    _check_traj(traj)  # before a file or viewer is opened
    rec = rr.RecordingStream("wbc_jax", recording_id=f"{run_dir.resolve()}:{info['name']}")
    if spawn:
        rec.spawn()
        path = None
    else:
        path = pathlib.Path(out) if out is not None else run_dir / f"{info['name']}.rrd"
        path.parent.mkdir(parents=True, exist_ok=True)
        rec.save(str(path))
    log_trajectory(rec, traj, push_body=info["push_body"], joints=info["joints"])
    rec.flush()
    if path is not None:
        rec.disconnect()
    return path
