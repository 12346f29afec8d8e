"""The MuJoCo scene of a contact set: objects, collision spheres, contact pairs.

:func:`build_scene` turns a checked contact specification (:mod:`wbc_jax.robot.contacts`: contacts and
scene objects) into a robot model with the objects of the scene (boxes: a table, a wall), small
collision spheres on the robot where a contact touches one (one for a point contact, the four
corners of the CoP rectangle for a surface one, like the feet), and the contact pairs between
them; and into the resolved :class:`~wbc_jax.robot.contacts.ContactSet` the controller uses. It runs on
the host, before anything is compiled, and checks what only the model can tell: that each contact
reaches the surface it touches at the initial posture, with its normal leaving that surface.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np

from wbc_jax.core.loader import echo
from wbc_jax.robot import model as model_lib
from wbc_jax.robot.contacts import FEET_FRAMES, Contact, ContactParams, ContactSet, ResolvedContact, check_spec

SPHERE_RADIUS = 0.005  # m, as the feet's corner spheres (assets/build_icub_mjcf.py)
CONTACT_SOLREF = (0.004, 1.0)  # as the feet
REACH_TOL = 0.005  # m: a contact's point must be this close to the surface it touches (initial posture)


def _frame_point(m: mujoco.MjModel, idx: model_lib.RobotIndex, c: Contact):
    """(body id, point in the body frame, site id or -1) of a contact's frame."""
    offset = np.asarray(c.offset, float)
    if c.frame in model_lib.NAMED_POINTS:
        body, point = model_lib.NAMED_POINTS[c.frame]
        return idx.body_id(body), np.asarray(point) + offset, -1
    if c.frame and c.frame in idx.site_names:
        sid = idx.site_id(c.frame)
        return int(m.site_bodyid[sid]), m.site_pos[sid] + offset, sid
    if c.frame and c.frame in idx.body_names:
        return idx.body_id(c.frame), offset, -1
    valid = sorted((set(idx.body_names) | set(idx.site_names) | set(model_lib.NAMED_POINTS)) - {""})
    raise ValueError(f"contact {echo(c.name)}: unknown frame {echo(c.frame)}; valid frames: {valid}")


def _contact_rotation(normal: np.ndarray, site_R: np.ndarray | None) -> np.ndarray:
    """World rotation of a contact frame with z = normal: the site's axes if its z is the normal
    (the soles), else x = world x (or y) projected on the tangent plane."""
    z = normal / np.linalg.norm(normal)
    if site_R is not None and site_R[:, 2] @ z > 1 - 1e-6:
        return site_R
    ref = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = ref - (ref @ z) * z
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], axis=1)


def _box_distance(p: np.ndarray, centre: np.ndarray, half: np.ndarray) -> float:
    """Signed distance of p (3,) to an axis-aligned box (negative inside)."""
    q = np.abs(p - centre) - half
    return float(np.linalg.norm(np.maximum(q, 0.0)) + min(q.max(), 0.0))


def _check_touch(c: Contact, W_p: np.ndarray, normal: np.ndarray, centre: np.ndarray, half: np.ndarray,
                 reach: bool = True) -> None:  # fmt: skip
    """A contact's point must lie on the surface of what it touches (within REACH_TOL) at the
    initial posture (unless not ``reach``), and its normal must leave that surface (not point into
    the object)."""
    surface = c.touches or "floor"
    dist = _box_distance(W_p, centre, half)
    if reach and abs(dist) > REACH_TOL:
        raise ValueError(f"contact {echo(c.name)}: its point {W_p.round(3).tolist()} is {abs(dist) * 100:.1f} cm "
                         f"{'inside' if dist < 0 else 'away from'} the surface of {echo(surface)} at the initial posture "
                         f"(at most {REACH_TOL * 1e3:.0f} mm: it must touch it); move the object (pos, shift) or "
                         "change the initial posture")  # fmt: skip
    rise = lambda e: (_box_distance(W_p + 0.01 * e, centre, half) - _box_distance(W_p - 0.01 * e, centre, half)) / 0.02  # noqa: E731
    n = normal / np.linalg.norm(normal)
    if rise(n) < 0.5:  # more than 60 deg from the surface's outward normal
        raise ValueError(f"contact {echo(c.name)}: normal {np.round(n, 3).tolist()} points into {echo(surface)} or along its "
                         f"surface (the surface faces {np.round([rise(e) for e in np.eye(3)], 3).tolist()}); the "
                         "normal points out of the touched surface, towards the robot")  # fmt: skip


def _pair_geoms(m: mujoco.MjModel, body: int) -> list[int]:
    geoms = set(m.pair_geom1.tolist()) | set(m.pair_geom2.tolist())
    return sorted(g for g in geoms if m.geom_bodyid[g] == body)


def build_scene(robot: str, contacts, objects, qpos: np.ndarray | None = None):
    """Add the scene objects, the contacts' collision spheres and their pairs to the robot model.

    Args:
      robot: robot name (``wbc_jax.robot.model.ROBOTS``). contacts, objects: sequences of
        :class:`Contact` / :class:`SceneObject` (or mappings). qpos: (nq,) the initial posture
        (normals and ``under`` placements refer to it); None: the home keyframe.

    Returns:
      ``(robot, contact_set)``: a :class:`wbc_jax.robot.model.Robot` of the scene and the
      :class:`ContactSet`.

    Raises:
      ValueError: unknown frames or objects, missing normals, bad values, a contact with nothing
        to touch (naming the valid choices).
    """
    contacts, objects = check_spec(contacts, objects)
    base = model_lib.load_mj_model(robot)
    idx = model_lib.build_index(base, robot)
    qpos = base.key("home").qpos.copy() if qpos is None else np.asarray(qpos, float)
    if qpos.shape != (base.nq,):
        raise ValueError(f"qpos must have shape ({base.nq},), got {qpos.shape}")
    d = mujoco.MjData(base)
    d.qpos[:] = qpos
    mujoco.mj_forward(base, d)

    frames = {}
    for c in contacts:
        body, point, sid = _frame_point(base, idx, c)
        R_body = d.xmat[body].reshape(3, 3)
        site_R = d.site_xmat[sid].reshape(3, 3) if sid >= 0 else None
        W_R_c = _contact_rotation(np.asarray(c.normal, float), site_R)
        W_p = d.xpos[body] + R_body @ point
        frames[c.name] = (body, point, R_body.T @ W_R_c, W_p, W_R_c)

    soles = {c.frame for c in contacts if c.frame in FEET_FRAMES and not np.any(np.asarray(c.offset, float))}
    missing = sorted(set(FEET_FRAMES) - soles)
    if missing:
        raise ValueError(
            f"the contact set must hold both soles (frames {sorted(FEET_FRAMES)}, no offset): missing "
            f"{missing}; contacts given: {[c.name for c in contacts]}"
        )
    spec = mujoco.MjSpec.from_file(str(model_lib.ROBOTS[robot]))
    for geom in list(spec.geoms):  # physics model: no meshes (as load_mj_model)
        if geom.type == mujoco.mjtGeom.mjGEOM_MESH:
            spec.delete(geom)
    for mesh in list(spec.meshes):
        spec.delete(mesh)
    placed = {}
    for o in objects:
        if o.under is not None:
            _, _, _, W_p, W_R_c = frames[o.under]
            axis = int(np.argmax(np.abs(W_R_c[:, 2])))
            if abs(W_R_c[axis, 2]) < 1 - 1e-6 or W_R_c[2, 2] < -1e-6:
                raise ValueError(f"scene object {echo(o.name)}: 'under' needs a contact with normal +z or horizontal "
                                 f"along a world axis; {echo(o.under)} has normal {W_R_c[:, 2].round(3).tolist()}")  # fmt: skip
            pos = W_p - W_R_c[:, 2].round() * o.size[axis] + np.asarray(o.shift, float)
        else:
            pos = np.asarray(o.pos, float)
        placed[o.name] = (pos, np.asarray(o.size, float))
        spec.worldbody.add_geom(
            name=o.name, type=mujoco.mjtGeom.mjGEOM_BOX, size=list(o.size), pos=pos.tolist(),
            contype=0, conaffinity=0, rgba=[0.6, 0.45, 0.3, 1],
        )  # fmt: skip
    friction = {o.name: o.friction for o in objects}
    friction["floor"] = 1.0
    placed["floor"] = (np.array([0.0, 0.0, d.geom_xpos[base.geom("floor").id][2] - 1e3]), np.full(3, 1e3))
    for c in contacts:
        # Contacts through the robot's own geoms (the soles) touch the floor: their normal is
        # checked against it too (a sole whose normal points down is refused).
        _check_touch(c, frames[c.name][3], frames[c.name][4][:, 2], *placed[c.touches or "floor"],
                     reach=c.touches is not None)  # fmt: skip
    added: dict[str, list[str]] = {}
    for c in contacts:
        if c.touches is None:
            continue
        body, point, R_bc, _, _ = frames[c.name]
        if c.type == "point":
            corners = [np.zeros(2)]
        else:
            (x0, x1), (y0, y1) = c.cop or ContactParams().foot_size
            corners = [np.array([x, y]) for x in (x0, x1) for y in (y0, y1)]
        body_spec = spec.body(base.body(body).name)
        names = []
        for k, xy in enumerate(corners):
            local = point + R_bc @ np.array([xy[0], xy[1], SPHERE_RADIUS])
            name = f"{c.name}_contact_{k}"
            body_spec.add_geom(
                name=name, type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[SPHERE_RADIUS, 0, 0],
                pos=local.tolist(), contype=0, conaffinity=0, group=3, mass=0.0, rgba=[0.2, 0.4, 0.9, 1],
            )  # fmt: skip
            mu = friction[c.touches]
            spec.add_pair(
                name=f"{name}_{c.touches}", geomname1=c.touches, geomname2=name, condim=3,
                friction=[mu, mu, 0.005, 1e-4, 1e-4], solref=list(CONTACT_SOLREF),
            )  # fmt: skip
            names.append(name)
        added[c.name] = names
    m = spec.compile()
    scene_robot = model_lib.Robot(mj_model=m, index=model_lib.build_index(m, robot))

    resolved = []
    for c in contacts:
        body, point, R_bc, _, _ = frames[c.name]
        if c.touches is not None:
            geoms = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, g) for g in added[c.name]]
        else:
            geoms = _pair_geoms(m, body)
            if not geoms:
                raise ValueError(
                    f"contact {echo(c.name)}: body {echo(base.body(body).name)} has no collision geoms; "
                    f"give 'touches: <object>' (valid: {sorted(friction)})"
                )
        cop = c.cop or ContactParams().foot_size
        params = ContactParams(mu=c.mu, mu_t=c.mu_t, fz_min=c.fz_min, foot_size=cop)
        resolved.append(
            ResolvedContact(
                name=c.name,
                type=c.type,
                body=int(body),
                point=tuple(float(x) for x in point),
                R_body_contact=tuple(float(x) for x in R_bc.ravel()),
                params=params,
                normal_force=math.nan if c.normal_force is None else float(c.normal_force),
                activation=c.activation,
                foot=FEET_FRAMES.get(c.frame, -1) if not np.any(c.offset) else -1,
                geoms=tuple(int(g) for g in geoms),
                detect=c.detect,
            )  # fmt: skip
        )
    return scene_robot, ContactSet(contacts=tuple(resolved))
