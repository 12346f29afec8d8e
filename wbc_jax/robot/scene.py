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
from wbc_jax.robot import placement
from wbc_jax.robot.contacts import Contact, ContactParams, ContactSet, ResolvedContact, check_spec
from wbc_jax.robot.description import RobotDescription
from wbc_jax.robot.robots import describe

SPHERE_RADIUS = 0.005  # m, as the feet's corner spheres (the model builders of assets/)
CONTACT_SOLREF = (0.004, 1.0)  # as the feet


def _frame_point(m: mujoco.MjModel, idx: model_lib.RobotIndex, c: Contact):
    """(body id, point in the body frame, site id or -1) of a contact's frame."""
    offset = np.asarray(c.offset, float)
    named_points = idx.description.named_points
    if c.frame in named_points:
        body, point = named_points[c.frame]
        return idx.body_id(body), np.asarray(point) + offset, -1
    if c.frame and c.frame in idx.site_names:
        sid = idx.site_id(c.frame)
        return int(m.site_bodyid[sid]), m.site_pos[sid] + offset, sid
    if c.frame and c.frame in idx.body_names:
        return idx.body_id(c.frame), offset, -1
    valid = sorted((set(idx.body_names) | set(idx.site_names) | set(named_points)) - {""})
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


def _check_placement(
    m: mujoco.MjModel, d: mujoco.MjData, c: Contact, frame: tuple, placed: dict, desc: RobotDescription
) -> None:
    """Does contact ``c`` touch what it names at the initial posture (``d``, after mj_forward)?
    Contacts through the robot's own geoms (the soles) touch the floor: a sole must stand flat on it
    with its CoP rectangle inside the foot; others must reach their object, normal along its
    surface's, CoP rectangle on it (:mod:`wbc_jax.robot.placement`)."""
    body, _, _, W_p, W_R_c = frame
    surface, cop = c.touches or "floor", c.cop or desc.sole_cop
    if c.touches is None:
        geoms = _own_geoms(m, c, body, sorted(placed))
        if c.frame in desc.feet and not np.any(c.offset):
            placement.check_normal(c.name, W_R_c[:, 2], W_p, placed[surface], surface)
            placement.check_sole(m, d, c.name, m.site(c.frame).id, geoms, cop)
            return
    placement.check_reach(c.name, W_p, placed[surface], surface)  # first: the normal is the nearest face's
    placement.check_normal(c.name, W_R_c[:, 2], W_p, placed[surface], surface)
    if c.type == "surface":
        placement.check_cop_on_surface(c.name, W_p, W_R_c, cop, placed[surface], surface)


def check_feet(robot: model_lib.Robot, qpos: np.ndarray) -> None:
    """The default contact set (both soles, the WBC CoP rectangle) at the initial posture ``qpos``
    (nq,): each sole flat on the floor (:func:`wbc_jax.robot.placement.check_sole`)."""
    m = robot.mj_model
    d = mujoco.MjData(m)
    d.qpos[:] = qpos
    mujoco.mj_forward(m, d)
    for frame in robot.description.feet:
        site = m.site(frame).id
        placement.check_sole(m, d, frame, site, _pair_geoms(m, int(m.site_bodyid[site])), robot.description.sole_cop)


def _own_geoms(m: mujoco.MjModel, c: Contact, body: int, surfaces: list[str]) -> list[int]:
    """The collision geoms through which a contact without ``touches`` acts (its body's)."""
    geoms = _pair_geoms(m, body)
    if not geoms:
        raise ValueError(
            f"contact {echo(c.name)}: body {echo(m.body(body).name)} has no collision geoms; "
            f"give 'touches: <object>' (valid: {surfaces})"
        )
    return geoms


def _pair_geoms(m: mujoco.MjModel, body: int) -> list[int]:
    geoms = set(m.pair_geom1.tolist()) | set(m.pair_geom2.tolist())
    return sorted(g for g in geoms if m.geom_bodyid[g] == body)


def build_scene(robot: str, contacts, objects, qpos: np.ndarray | None = None):
    """Add the scene objects, the contacts' collision spheres and their pairs to the robot model.

    Args:
      robot: robot name (``wbc_jax.robot.robots.DESCRIPTIONS``). contacts, objects: sequences of
        :class:`Contact` / :class:`SceneObject` (or mappings). qpos: (nq,) the initial posture
        (normals and ``under`` placements refer to it); None: the home keyframe.

    Returns:
      ``(robot, contact_set)``: a :class:`wbc_jax.robot.model.Robot` of the scene and the
      :class:`ContactSet`.

    Raises:
      ValueError: unknown frames or objects, missing normals, bad values, a contact with nothing
        to touch (naming the valid choices).
    """
    desc = describe(robot)
    feet = {name: k for k, name in enumerate(desc.feet)}
    contacts, objects = check_spec(contacts, objects, desc.feet)
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

    soles = {c.frame for c in contacts if c.frame in feet and not np.any(np.asarray(c.offset, float))}
    missing = sorted(set(feet) - soles)
    if missing:
        raise ValueError(
            f"the contact set must hold both soles (frames {sorted(feet)}, no offset): missing "
            f"{missing}; contacts given: {[c.name for c in contacts]}"
        )
    spec = model_lib.physics_spec(desc)
    placed = {}
    for o in objects:
        if o.under is not None:
            _, _, _, W_p, W_R_c = frames[o.under]
            axis = int(np.argmax(np.abs(W_R_c[:, 2])))
            if abs(W_R_c[axis, 2]) < 1 - 1e-6 or W_R_c[2, 2] < -1e-6:
                raise ValueError(
                    f"scene object {echo(o.name)}: 'under' needs a contact with normal +z or horizontal "
                    f"along a world axis; {echo(o.under)} has normal {W_R_c[:, 2].round(3).tolist()}"
                )
            pos = W_p - W_R_c[:, 2].round() * o.size[axis] + np.asarray(o.shift, float)
        else:
            pos = np.asarray(o.pos, float)
        placed[o.name] = (pos, np.asarray(o.size, float))
        spec.worldbody.add_geom(
            name=o.name,
            type=mujoco.mjtGeom.mjGEOM_BOX,
            size=list(o.size),
            pos=pos.tolist(),
            contype=0,
            conaffinity=0,
            rgba=[0.6, 0.45, 0.3, 1],
        )
    friction = {o.name: o.friction for o in objects}
    friction["floor"] = 1.0
    placed["floor"] = (np.array([0.0, 0.0, d.geom_xpos[base.geom("floor").id][2] - 1e3]), np.full(3, 1e3))
    for c in contacts:
        _check_placement(base, d, c, frames[c.name], placed, desc)
    placement.check_objects_clear(
        base, d, {o.name: placed[o.name] for o in objects}, [(frames[c.name][0], frames[c.name][3]) for c in contacts]
    )
    added: dict[str, list[str]] = {}
    for c in contacts:
        if c.touches is None:
            continue
        body, point, R_bc, _, _ = frames[c.name]
        if c.type == "point":
            corners = [np.zeros(2)]
        else:
            (x0, x1), (y0, y1) = c.cop or desc.sole_cop
            corners = [np.array([x, y]) for x in (x0, x1) for y in (y0, y1)]
        body_spec = spec.body(base.body(body).name)
        names = []
        for k, xy in enumerate(corners):
            local = point + R_bc @ np.array([xy[0], xy[1], SPHERE_RADIUS])
            name = f"{c.name}_contact_{k}"
            body_spec.add_geom(
                name=name,
                type=mujoco.mjtGeom.mjGEOM_SPHERE,
                size=[SPHERE_RADIUS, 0, 0],
                pos=local.tolist(),
                contype=0,
                conaffinity=0,
                group=3,
                mass=0.0,
                rgba=[0.2, 0.4, 0.9, 1],
            )
            mu = friction[c.touches]
            spec.add_pair(
                name=f"{name}_{c.touches}",
                geomname1=c.touches,
                geomname2=name,
                condim=3,
                friction=[mu, mu, 0.005, 1e-4, 1e-4],
                solref=list(CONTACT_SOLREF),
            )
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
            geoms = _own_geoms(m, c, body, sorted(friction))
        cop = c.cop or desc.sole_cop
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
                foot=feet.get(c.frame, -1) if not np.any(c.offset) else -1,
                geoms=tuple(int(g) for g in geoms),
                detect=c.detect,
            )
        )
    return scene_robot, ContactSet(contacts=tuple(resolved))
