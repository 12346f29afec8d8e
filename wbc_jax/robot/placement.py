"""Is a contact set physical at the initial posture? Measured in C MuJoCo before anything compiles.

A contact must touch what it names: its point on the touched surface, its normal along that
surface's outward normal, a sole flat on the floor with its contact spheres on it, a CoP rectangle
inside the foot (or on the touched object), and no scene object inside the robot. Each refusal is
one line naming the contact or object and the measured distance or angle against its tolerance.

Tolerances come from the model: the feet's contact spheres have a 5 mm radius (a point within
that of the surface touches it); normals within NORMAL_TOL_DEG (the example files' normals are
exact; a sole tilted by a few degrees already stands on one edge).
"""

from __future__ import annotations

import math

import mujoco
import numpy as np

REACH_TOL = 0.005  # m: the radius of the feet's contact spheres (assets/build_icub_mjcf.py)
NORMAL_TOL_DEG = 3.0
_STEP = 1e-4  # m: finite-difference step of the surface normal


def box_distance(p: np.ndarray, centre: np.ndarray, half: np.ndarray) -> float:
    """Signed distance of p (3,) to an axis-aligned box (negative inside)."""
    q = np.abs(p - centre) - half
    return float(np.linalg.norm(np.maximum(q, 0.0)) + min(q.max(), 0.0))


def surface_normal(p: np.ndarray, centre: np.ndarray, half: np.ndarray) -> np.ndarray:
    """(3,) the outward unit normal of a box's surface nearest p (the signed distance's gradient)."""
    grad = np.array(
        [box_distance(p + _STEP * e, centre, half) - box_distance(p - _STEP * e, centre, half) for e in np.eye(3)]
    )
    return grad / max(np.linalg.norm(grad), 1e-12)


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """The angle between two vectors (3,), degrees."""
    return math.degrees(math.atan2(np.linalg.norm(np.cross(a, b)), float(np.dot(a, b))))


def check_normal(name: str, normal: np.ndarray, W_p: np.ndarray, box: tuple, surface: str) -> None:
    """The contact normal (3,) must be within NORMAL_TOL_DEG of the outward normal of ``box``
    (centre, half sizes) at the contact point W_p (3,)."""
    n = normal / np.linalg.norm(normal)
    face = surface_normal(W_p, *box)
    off = angle_deg(n, face)
    if face @ n < 0.5:  # more than 60 deg: pointing into the surface or along it
        raise ValueError(
            f"contact {name!r}: normal {np.round(n, 3).tolist()} points into {surface!r} or along its "
            f"surface (the surface faces {np.round(face, 3).tolist()}); the normal points out of the "
            "touched surface, towards the robot"
        )
    if off > NORMAL_TOL_DEG:
        raise ValueError(
            f"contact {name!r}: normal {np.round(n, 3).tolist()} is {off:.1f} deg from the normal "
            f"{np.round(face, 3).tolist()} of the surface of {surface!r} it touches (at most "
            f"{NORMAL_TOL_DEG:g} deg)"
        )


def check_reach(name: str, W_p: np.ndarray, box: tuple, surface: str) -> None:
    """The contact point W_p (3,) must lie on the surface of ``box`` (within REACH_TOL)."""
    dist = box_distance(W_p, *box)
    if abs(dist) > REACH_TOL:
        raise ValueError(
            f"contact {name!r}: its point {W_p.round(3).tolist()} is {abs(dist) * 100:.1f} cm "
            f"{'inside' if dist < 0 else 'away from'} the surface of {surface!r} at the initial posture "
            f"(at most {REACH_TOL * 1e3:.0f} mm: it must touch it); move the object (pos, shift) or "
            "change the initial posture"
        )


def check_cop_on_surface(name: str, W_p: np.ndarray, W_R_c: np.ndarray, cop, box: tuple, surface: str) -> None:
    """Each corner of a surface contact's CoP rectangle ((x0, x1), (y0, y1)) in its frame (W_p,
    W_R_c) must lie on the touched surface (within REACH_TOL): the rectangle may not overhang it."""
    (x0, x1), (y0, y1) = cop
    for x, y in ((x0, y0), (x0, y1), (x1, y0), (x1, y1)):
        corner = W_p + W_R_c @ np.array([x, y, 0.0])
        dist = box_distance(corner, *box)
        if abs(dist) > REACH_TOL:
            raise ValueError(
                f"contact {name!r}: CoP corner ({x:g}, {y:g}) m is {abs(dist) * 100:.1f} cm off the "
                f"surface of {surface!r} at the initial posture (at most {REACH_TOL * 1e3:.0f} mm): the "
                f"rectangle {[list(cop[0]), list(cop[1])]} is larger than what it touches"
            )


def check_sole(m: mujoco.MjModel, d: mujoco.MjData, name: str, site: int, geoms, cop) -> None:
    """A sole (site id ``site``, its contact spheres ``geoms``) flat on the floor at the state of
    ``d`` (after mj_forward): its z axis within NORMAL_TOL_DEG of vertical, every sphere within
    REACH_TOL of the floor (mj_geomDistance), and the CoP rectangle ``cop`` inside the spheres'
    extent in the sole frame (to their radius)."""
    floor = m.geom("floor").id
    R = d.site_xmat[site].reshape(3, 3)
    tilt = angle_deg(R[:, 2], np.array([0.0, 0.0, 1.0]))
    if tilt > NORMAL_TOL_DEG:
        raise ValueError(
            f"contact {name!r}: sole {m.site(site).name} is tilted {tilt:.1f} deg against the floor at "
            f"the initial posture (at most {NORMAL_TOL_DEG:g} deg): it would stand on an edge; change "
            "the initial posture"
        )
    fromto = np.zeros(6)
    gaps = [mujoco.mj_geomDistance(m, d, floor, int(g), 1.0, fromto) for g in geoms]
    worst = max(gaps, key=abs)
    if abs(worst) > REACH_TOL:
        raise ValueError(
            f"contact {name!r}: sole {m.site(site).name} is {abs(worst) * 100:.1f} cm "
            f"{'below' if worst < 0 else 'above'} the floor at the initial posture (its contact spheres "
            f"at {min(gaps) * 100:.1f} to {max(gaps) * 100:.1f} cm; at most {REACH_TOL * 1e3:.0f} mm): "
            "it must stand on it; change the initial posture"
        )
    local = np.array([R.T @ (d.geom_xpos[g] - d.site_xpos[site]) for g in geoms])
    lo, hi = local[:, :2].min(0) - REACH_TOL, local[:, :2].max(0) + REACH_TOL
    (x0, x1), (y0, y1) = cop
    if x0 < lo[0] or y0 < lo[1] or x1 > hi[0] or y1 > hi[1]:
        raise ValueError(
            f"contact {name!r}: CoP rectangle {[[x0, x1], [y0, y1]]} m is larger than the foot: its "
            f"contact spheres span x [{lo[0]:.3f}, {hi[0]:.3f}], y [{lo[1]:.3f}, {hi[1]:.3f}] m in the "
            "sole frame (their radius included); give a cop inside it"
        )


def robot_points(m: mujoco.MjModel, d: mujoco.MjData, extra=(), spacing: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Points along the robot's skeleton at the state of ``d``: every segment from a body's origin to
    its parent's (not the world) and to each ``extra`` (body id, world point (3,)) (the contact
    points: the hands), every ``spacing`` m, and the collision geoms' centres. Returns (points
    (N, 3), body id of each (N,))."""
    points, bodies = (
        [d.geom_xpos[g] for g in range(m.ngeom) if m.geom_bodyid[g] > 0],
        [int(m.geom_bodyid[g]) for g in range(m.ngeom) if m.geom_bodyid[g] > 0],
    )
    segments = [(int(m.body_parentid[b]), b, d.xpos[b]) for b in range(1, m.nbody)]
    segments += [(int(b), int(b), np.asarray(p, float)) for b, p in extra]
    for parent, b, z in segments:
        a = d.xpos[parent] if parent > 0 else z
        n = max(int(np.linalg.norm(z - a) / spacing), 1)
        for s in np.linspace(0.0, 1.0, n + 1):
            points.append(a + s * (z - a))
            bodies.append(b)
    return np.array(points), np.array(bodies)


def check_objects_clear(m: mujoco.MjModel, d: mujoco.MjData, objects: dict, extra=()) -> None:
    """No scene object (name -> (centre (3,), half sizes (3,))) may hold a point of the robot's
    skeleton (:func:`robot_points`, with the ``extra`` segments) deeper than REACH_TOL at the
    initial posture."""
    points, bodies = robot_points(m, d, extra)
    for name, (centre, half) in objects.items():
        depth = -np.array([box_distance(p, centre, half) for p in points])
        k = int(np.argmax(depth))
        if depth[k] > REACH_TOL:
            raise ValueError(
                f"scene object {name!r} intersects the robot at the initial posture: body "
                f"{m.body(int(bodies[k])).name!r} is {depth[k] * 100:.1f} cm inside it (at most "
                f"{REACH_TOL * 1e3:.0f} mm); move it (pos, shift)"
            )
