"""Rollouts as rerun recordings: the robot, CoM, support polygon, wrenches, pushes.

Host-side only (numpy in, ``.rrd`` or a viewer out); never imported by traced code.

A recording holds, on the ``sim_time`` timeline (seconds, one row per controller tick)::

    world/robot/<body>              Transform3D per tick (C MuJoCo mj_kinematics of traj qpos)
    world/robot/<body>/geom_<g>     static Transform3D (geom in body) + static Mesh3D (the robot's STL)
    world/floor                     static Boxes3D
    world/com, world/com_ref        Points3D (now) ; world/com/trail, world/com_ref/trail LineStrips3D
    world/support_polygon           LineStrips3D: convex hull of the sole spheres touching the floor
    world/contacts/f_meas, f_cmd    Arrows3D: force part of each contact's wrench, at the contact
    world/contacts/normals          Arrows3D: each contact's normal (its frame's z axis)
    world/scene/<object>            static Boxes3D: the scene's objects (a table, a wall)
    world/push                      Arrows3D on the pushed body (its tip at the body's CoM)
    plots/com_error_mm, plots/Ldot_star, plots/Ldot_meas, plots/tau,
    plots/f_cmd, plots/f_meas, plots/activation       Scalars

Any contact set is shown: the feet, hands on a table, a hand on a wall. ``wbc-jax view``
(:mod:`wbc_jax.jobs.view`) draws runs on disk with it.
"""

from __future__ import annotations

import functools

import mujoco
import numpy as np

from wbc_jax.robot import model as model_lib
from wbc_jax.robot.robots import DEFAULT_ROBOT, describe

TIMELINE = "sim_time"
FORCE_SCALE = 1.0 / 500.0  # m per N for the arrows: the ~160 N per sole of standing -> 0.32 m
TRAIL_S = 1.0  # s of CoM history drawn behind the CoM
CONTACT_TOL = 2e-3  # m: a sole sphere whose bottom is this close to the floor counts as touching
AXES6 = ["fx", "fy", "fz", "tx", "ty", "tz"]
TRAJ_FIELDS = (
    "t",
    "qpos",
    "com",
    "com_ref",
    "tau",
    "f_cmd",
    "f_meas",
    "Ldot_star",
    "Ldot_meas",
    "contact_pos",
    "contact_normal",
    "activation",
    "push",
)


def wrench_names(names: list[str], dims: list[int]) -> list[str]:
    """Series names of the stacked contact wrenches (surface: 6 entries, point: 3)."""
    return [f"{name} {a}" for name, dim in zip(names, dims, strict=True) for a in AXES6[:dim]]


@functools.lru_cache(maxsize=2)
def visual_model(robot: str = DEFAULT_ROBOT) -> mujoco.MjModel:
    """The robot's C model with its visual meshes (its description's ``mesh_dir``), cached."""
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


def check_trajectory(traj: dict) -> int:
    missing = [f for f in TRAJ_FIELDS if f not in traj]
    if missing:
        raise ValueError(f"trajectory lacks fields {missing}; needs {list(TRAJ_FIELDS)}")
    T = len(traj["t"])
    bad = [f for f in TRAJ_FIELDS if len(traj[f]) != T]
    if T == 0 or bad:
        raise ValueError(f"trajectory fields {bad} do not have the length of t ({T})")
    K = np.shape(traj["contact_pos"])[1]
    if np.shape(traj["activation"])[1:] != (K,) or np.shape(traj["contact_normal"])[1:] != (K, 3):
        raise ValueError(f"trajectory contact fields disagree on the number of contacts ({K})")
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


def log_trajectory(
    rec,
    traj: dict,
    *,
    robot: str,
    push_body: str,
    joints: list[str] | None = None,
    contacts: list[str] | None = None,
    dims: list[int] | None = None,
    boxes: dict | None = None,
) -> None:
    """Log a recorded rollout to a rerun recording stream.

    Args:
      rec: ``rr.RecordingStream``.
      traj: numpy fields of :class:`rollout.Trajectory` (time-major, length T): t (T,),
        qpos (T, nq), com/com_ref (T, 3), tau (T, n), f_cmd/f_meas (T, D), Ldot_star/Ldot_meas
        (T, 6), contact_pos/contact_normal (T, K, 3), activation (T, K), push (T, 3).
      robot: robot name (visual model). push_body: body (or body role, ``trunk``) the push acts on
        (arrow tip at its CoM).
      joints: joint names (n,) for the torque series (default: indices).
      contacts, dims: contact names and wrench sizes (K,) (default: the two soles).
      boxes: scene objects {name: (center (3,), half sizes (3,), rotation (3, 3))}.
    """
    import rerun as rr

    T = check_trajectory(traj)
    m = visual_model(robot)
    bodies = _names(m, mujoco.mjtObj.mjOBJ_BODY, m.nbody)
    push_body = describe(robot).body(push_body)
    model_lib.check_name("body", push_body, bodies[1:])
    t = np.asarray(traj["t"], float)
    time = [rr.TimeColumn(TIMELINE, duration=t)]
    xpos, xquat, gpos = body_poses(m, traj["qpos"])

    # Static scene: meshes, floor, series styles.
    paths = log_robot_meshes(rec, m)
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    rec.log(
        "world/floor",
        rr.Boxes3D(
            centers=[[0, 0, -0.005]], half_sizes=[[1.0, 1.0, 0.005]], colors=[[90, 90, 90, 255]], fill_mode="solid"
        ),
        static=True,
    )
    K = np.shape(traj["contact_pos"])[1]
    contacts = (
        list(contacts) if contacts is not None else (["left", "right"] if K == 2 else [f"c{k}" for k in range(K)])
    )
    dims = list(dims) if dims is not None else [6] * K
    for name, (center, half, R) in (boxes or {}).items():
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, np.asarray(R, float).ravel())
        rec.log(
            f"world/scene/{name}",
            rr.Boxes3D(
                centers=[center],
                half_sizes=[half],
                quaternions=[_xyzw(quat)],
                colors=[[150, 115, 75, 255]],
                fill_mode="solid",
            ),
            static=True,
        )
    n = np.asarray(traj["tau"]).shape[1]
    series = {
        "plots/com_error_mm": ["|CoM - CoM_ref|"],
        "plots/Ldot_star": [f"L̇* {a}" for a in AXES6],
        "plots/Ldot_meas": [f"L̇ meas {a}" for a in AXES6],
        "plots/tau": list(joints) if joints is not None else [f"tau_{j}" for j in range(n)],
        "plots/f_cmd": [f"cmd {w}" for w in wrench_names(contacts, dims)],
        "plots/f_meas": [f"meas {w}" for w in wrench_names(contacts, dims)],
        "plots/activation": [f"activation {c}" for c in contacts],
    }
    for path, names in series.items():
        rec.log(path, rr.SeriesLines(names=names), static=True)

    # Columns (one call per entity for all ticks): body poses and time series.
    for b in range(1, m.nbody):
        rec.send_columns(
            paths[b],
            indexes=time,
            columns=rr.Transform3D.columns(translation=xpos[:, b], quaternion=_xyzw(xquat[:, b])),
        )
    com_err = 1e3 * np.linalg.norm(np.asarray(traj["com"]) - np.asarray(traj["com_ref"]), axis=1)
    values = {
        "plots/com_error_mm": com_err[:, None],
        "plots/Ldot_star": traj["Ldot_star"],
        "plots/Ldot_meas": traj["Ldot_meas"],
        "plots/tau": traj["tau"],
        "plots/f_cmd": traj["f_cmd"],
        "plots/f_meas": traj["f_meas"],
        "plots/activation": traj["activation"],
    }
    for path, v in values.items():
        v = np.asarray(v, float).reshape(T, -1)
        rec.send_columns(path, indexes=time, columns=rr.Scalars.columns(scalars=v.ravel()).partition([v.shape[1]] * T))

    # Per tick: CoM and trails, support polygon, wrench and push arrows.
    polys = support_polygons(m, gpos)
    trail = max(1, int(round(TRAIL_S / (t[1] - t[0])))) if T > 1 else 1
    push_id = bodies.index(push_body)
    com, com_ref = np.asarray(traj["com"]), np.asarray(traj["com_ref"])
    points = np.asarray(traj["contact_pos"]).reshape(T, K, 3)
    normals = np.asarray(traj["contact_normal"]).reshape(T, K, 3)
    starts = np.concatenate([[0], np.cumsum(dims)[:-1]])
    force_cols = np.concatenate([np.arange(s0, s0 + 3) for s0 in starts])
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
            f = np.asarray(traj[name][k])[force_cols].reshape(K, 3) * FORCE_SCALE
            rec.log(
                f"world/contacts/{name}",
                rr.Arrows3D(vectors=f, origins=points[k], colors=[color] * K, radii=0.006, labels=contacts),
            )
        act = np.asarray(traj["activation"][k])
        shade = (
            np.clip(act, 0, 1)[:, None] * np.array([40, 200, 80])
            + (1 - np.clip(act, 0, 1))[:, None] * np.array([200, 60, 40])
        ).astype(np.uint8)
        rec.log(
            "world/contacts/normals",
            rr.Arrows3D(
                vectors=0.08 * normals[k],
                origins=points[k],
                colors=shade,
                radii=0.003,
                labels=[f"{c} a={a:.2f}" for c, a in zip(contacts, act)],
            ),
        )
        p = np.asarray(traj["push"][k], float)
        if np.any(p != 0):
            v = p * FORCE_SCALE
            rec.log(
                "world/push",
                rr.Arrows3D(
                    vectors=[v],
                    origins=[xpos[k, push_id] - v],
                    colors=[[255, 0, 200]],
                    radii=0.01,
                    labels=[f"push {np.linalg.norm(p):.0f} N"],
                ),
            )
        else:
            rec.log("world/push", rr.Arrows3D(vectors=np.zeros((0, 3))))


def scene_boxes(robot: model_lib.Robot) -> dict:
    """The scene objects of a model (box geoms of the world body but the floor):
    {name: (center, half sizes, rotation)}."""
    m = robot.mj_model
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    out = {}
    for g in range(m.ngeom):
        if m.geom_bodyid[g] == 0 and m.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX:
            name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, g) or f"box_{g}"
            out[name] = (d.geom_xpos[g].copy(), m.geom_size[g].copy(), d.geom_xmat[g].reshape(3, 3).copy())
    return out
