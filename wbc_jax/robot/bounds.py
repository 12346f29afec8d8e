"""Theoretical bounds on push recovery with the feet in place, per push direction.

* The LIP bound (``wbc_jax.jobs.sweep_table.lip_bound``): a linear inverted pendulum (mass m,
  CoM height z0, omega = sqrt(g / z0)) with its CoP anywhere in the support polygon recovers from
  a horizontal CoM velocity v along u iff its capture point v / omega lies in the polygon:
  v <= omega d(u), d the distance from the CoM to the polygon's edge along u.
* The flywheel bound (:func:`flywheel_bound`): the same LIP plus a flywheel (the body rotating
  about the CoM), Pratt, Carff, Drakunov, Goswami, "Capture Point: A Step toward Humanoid Push
  Recovery", Humanoids 2006: the linear inverted pendulum plus flywheel and its capture region.

Derivation of the flywheel bound (one horizontal axis). A flywheel torque tau (the rate of the
centroidal angular momentum) moves the effective CoP: m x'' = m omega^2 (x - p - tau / (m g)).
The capture point xi = x + x' / omega obeys xi' = omega (xi - p - tau / (m g)); xi stays bounded
iff xi(0) = int_0^inf omega exp(-omega s) (p(s) + tau(s) / (m g)) ds. The weights integrate to 1,
so the p part is a point of the polygon and the flywheel adds the shift
D = int omega exp(-omega s) tau(s) / (m g) ds. With |tau| <= tau_max, the flywheel at rest at the
start and the end (a standing robot keeps no spin) and its angle within theta_max, the largest D
is reached by bang-bang, +tau_max for t1 then -tau_max for t1 (Pratt 2006's profile): the wheel
stops at theta = tau_max t1^2 / I, so t1 = sqrt(I theta_max / tau_max), and
D = (tau_max / (m g)) (1 - exp(-omega t1))^2 (a coast phase between the two only lowers D for the
same angle: D = (tau/(m g))(1 - e^-a)(1 - e^-b) with a b fixed is largest at a = b). So
v_max = omega (d + D) along a principal axis, and the impulse bound is m v_max
(tests/test_bounds.py integrates the ODE and solves the discretised optimal control as a
linear programme to check both). In 2-D the pitch and roll flywheels give independent shifts, a
box of D (asymmetric in pitch: the trunk flexes further than it extends), and xi(0) must lie in
the polygon plus that box (a Minkowski sum): the bound is omega times the distance along u to its
edge, d(u) itself where the box is a point (no torque or no range).

The robot's flywheel (:func:`flywheel_model`), chosen so the bound stays an upper bound:
* inertia: the larger, per axis, of the whole robot's centroidal inertia about the CoM and the
  upper body's (every body above the hips) about the hip axis (t1 and D grow with I);
* torque: both hips in parallel, per hip the smaller of the actuator's ctrlrange (+-60 N m, the
  controller's saturation) and the joint's actuatorfrcrange in assets/icub/icub_23dof.xml (MuJoCo
  clamps the joint's actuator force to it: 55.5 N m hip pitch, 37 N m hip roll);
* angle: the hip joints' range from the home posture: pitch (both hips turn alike) flexion for a
  forward push (the trunk pitches toward the push), extension for a backward one; roll (the hips
  turn in opposite senses, mirrored axes) the smaller side, the adducting hip's limit.
* a push at height h above the CoM also gives an angular impulse h J about the axis the flywheel
  must spin about to help, so the flywheel starts spinning that way and has to be braked within
  the same angle: it lowers D (the linear programme of the tests shows it), and the bound ignores it
  (an upper bound). A push point below the CoM would raise D and is refused.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from wbc_jax.core import constants


@dataclasses.dataclass(frozen=True)
class Flywheel:
    """The LIP + flywheel of a standing robot (SI units).

    Attributes:
      mass: total mass m [kg]; com_height: standing CoM height z0 [m].
      inertia_pitch / inertia_roll: flywheel inertia about the y / x axis [kg m^2].
      torque_pitch / torque_roll: largest flywheel torque about y / x [N m].
      flexion / extension: pitch range toward a forward / backward push [rad]; roll: roll range [rad].
    """

    mass: float
    com_height: float
    inertia_pitch: float
    inertia_roll: float
    torque_pitch: float
    torque_roll: float
    flexion: float
    extension: float
    roll: float

    @property
    def omega(self) -> float:
        return math.sqrt(constants.GRAVITY / self.com_height)

    def shift_box(self) -> np.ndarray:
        """(4, 2) corners of the box of capture-point shifts D the flywheel can add [m]."""
        fwd, back, side = (
            flywheel_shift(tau, inertia, theta, self.mass, self.omega)
            for tau, inertia, theta in (
                (self.torque_pitch, self.inertia_pitch, self.flexion),
                (self.torque_pitch, self.inertia_pitch, self.extension),
                (self.torque_roll, self.inertia_roll, self.roll),
            )
        )
        return np.array([[fwd, side], [fwd, -side], [-back, side], [-back, -side]])


def flywheel_shift(torque: float, inertia: float, theta_max: float, mass: float, omega: float) -> float:
    """Largest capture-point shift D [m] of a flywheel (bang-bang, module docstring):
    (tau / (m g)) (1 - exp(-omega t1))^2 with t1 = sqrt(I theta_max / tau)."""
    if min(torque, inertia, theta_max) < 0.0 or mass <= 0.0 or omega <= 0.0:
        raise ValueError(
            f"flywheel needs torque, inertia, theta_max >= 0 and mass, omega > 0; got "
            f"{torque=}, {inertia=}, {theta_max=}, {mass=}, {omega=}"
        )
    if torque == 0.0:
        return 0.0
    t1 = math.sqrt(inertia * theta_max / torque)
    return torque / (mass * constants.GRAVITY) * (1.0 - math.exp(-omega * t1)) ** 2


def ray_distance(points: np.ndarray, origin: np.ndarray, azimuth_deg: float) -> float:
    """Distance [m] from ``origin`` (2,) inside the convex hull of ``points`` (k, 2) to its
    boundary along the direction ``azimuth_deg``."""
    from scipy.spatial import ConvexHull

    u = np.array([math.cos(math.radians(azimuth_deg)), math.sin(math.radians(azimuth_deg))])
    hull = ConvexHull(np.asarray(points, float))
    if np.any(hull.equations[:, :2] @ origin + hull.equations[:, 2] > 1e-12):
        raise ValueError(f"origin {origin} lies outside the support polygon")
    # Facets a.x + b <= 0: the ray origin + s u leaves through the first facet it meets.
    return min(-(eq[:2] @ origin + eq[2]) / (eq[:2] @ u) for eq in hull.equations if eq[:2] @ u > 1e-12)


def flywheel_distance(points: np.ndarray, origin: np.ndarray, wheel: Flywheel, azimuth_deg: float) -> float:
    """Distance [m] from ``origin`` (2,) along ``azimuth_deg`` to the edge of the support polygon
    (the hull of ``points`` (k, 2)) grown by the flywheel's box of capture-point shifts: the
    farthest capture point, divided by omega the largest CoM velocity, it recovers from."""
    grown = (np.asarray(points, float)[:, None, :] + wheel.shift_box()[None]).reshape(-1, 2)
    return ray_distance(grown, origin, azimuth_deg)


def standing_support(robot, feet: str = "two-feet") -> tuple[np.ndarray, np.ndarray, object]:
    """(contact points (k, 2) of the soles, CoM (3,), MjData) in the home posture; ``feet``
    "two-feet" or "left-foot"."""
    import mujoco

    m = robot.mj_model
    d = mujoco.MjData(m)
    d.qpos[:] = robot.home_qpos()
    mujoco.mj_forward(m, d)
    geoms = robot.index.foot_geoms.ravel() if feet == "two-feet" else robot.index.foot_geoms[0]
    return d.geom_xpos[geoms, :2].copy(), d.subtree_com[robot.index.base_body].copy(), d


def _composite_inertia(m, d, bodies, point: np.ndarray) -> np.ndarray:
    """(3, 3) inertia of ``bodies`` about ``point`` in world axes."""
    inertia = np.zeros((3, 3))
    for b in bodies:
        rot = d.ximat[b].reshape(3, 3)
        r = d.xipos[b] - point
        inertia += rot @ np.diag(m.body_inertia[b]) @ rot.T + m.body_mass[b] * (r @ r * np.eye(3) - np.outer(r, r))
    return inertia


def _joint_limits(m, names, keyframe: str) -> tuple[np.ndarray, np.ndarray, float]:
    """(ranges (k, 2), home angles (k,), the smallest per-joint torque limit) of joints ``names``."""
    import mujoco

    ids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, n) for n in names]
    if min(ids) < 0:
        raise ValueError(f"the model lacks a hip joint of {names}")
    home = m.key(keyframe).qpos[m.jnt_qposadr[ids]]
    return m.jnt_range[ids], home, float(min(joint_torque_limits(m, names)))


def joint_torque_limits(m, names) -> np.ndarray:
    """(k,) N m: per joint of ``names``, the largest torque the plant applies: its actuator's
    ctrlrange times gear (0 without one), capped by the joint's actuatorfrcrange where limited
    (MuJoCo clamps the joint's actuator force to it)."""
    import mujoco

    ids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, n) for n in names]
    if min(ids) < 0:
        raise ValueError(f"the model lacks a joint of {list(names)}")
    torque = []
    for j in ids:
        act = [a for a in range(m.nu) if m.actuator_trnid[a, 0] == j]
        limit = abs(m.actuator_ctrlrange[act[0], 1] * m.actuator_gear[act[0], 0]) if act else 0.0
        if m.jnt_actfrclimited[j]:
            limit = min(limit, m.jnt_actfrcrange[j, 1])
        torque.append(limit)
    return np.array(torque, float)


def flywheel_model(robot) -> Flywheel:
    """The robot's LIP + flywheel from its MJCF in the home posture (choices: module docstring)."""
    m = robot.mj_model
    _, com, d = standing_support(robot)
    hip_pitch, hip_roll = robot.description.hip_pitch, robot.description.hip_roll
    legs = {int(m.jnt_bodyid[m.joint(n).id]) for n in hip_pitch}  # the bodies the hip pitch joints move
    in_leg = [any(a in legs for a in _ancestors(m, b)) for b in range(m.nbody)]
    upper = [b for b in range(1, m.nbody) if not in_leg[b]]
    hips = np.mean([d.xanchor[m.joint(n).id] for n in hip_pitch], axis=0)
    whole = _composite_inertia(m, d, range(1, m.nbody), com)
    trunk = _composite_inertia(m, d, upper, hips)
    pitch_range, pitch_home, pitch_torque = _joint_limits(m, hip_pitch, robot.description.nominal_keyframe)
    roll_range, roll_home, roll_torque = _joint_limits(m, hip_roll, robot.description.nominal_keyframe)
    return Flywheel(
        mass=float(m.body_subtreemass[robot.index.base_body]),
        com_height=float(com[2]),
        inertia_pitch=float(max(whole[1, 1], trunk[1, 1])),
        inertia_roll=float(max(whole[0, 0], trunk[0, 0])),
        torque_pitch=2.0 * pitch_torque,
        torque_roll=2.0 * roll_torque,
        flexion=float(np.min(pitch_range[:, 1] - pitch_home)),
        extension=float(np.min(pitch_home - pitch_range[:, 0])),
        roll=float(min(np.min(roll_range[:, 1] - roll_home), np.min(roll_home - roll_range[:, 0]))),
    )


def _ancestors(m, body: int):
    while body > 0:
        yield body
        body = m.body_parentid[body]


def flywheel_bound(robot, directions_deg, push_body: str, flywheel: Flywheel | None = None) -> dict:
    """{azimuth: {"edge_distance_m", "flywheel_distance_m", "velocity_bound_mps",
    "impulse_bound_ns"}} of horizontal pushes on ``push_body`` (the feet in place, both soles);
    ``flywheel`` overrides the robot's (:func:`flywheel_model`)."""
    points, com, d = standing_support(robot)
    height = d.xipos[robot.index.pushable_body_id(push_body), 2] - com[2]  # xfrc_applied acts at the body's CoM
    if height < 0.0:
        raise ValueError(
            f"push body {push_body!r} is {-height:.3f} m below the CoM: the flywheel bound is "
            "derived for push points at or above it"
        )
    wheel = flywheel_model(robot) if flywheel is None else flywheel
    out = {}
    for az in directions_deg:
        edge = ray_distance(points, com[:2], az)
        reach = flywheel_distance(points, com[:2], wheel, az)
        out[float(az)] = {
            "edge_distance_m": edge,
            "flywheel_distance_m": reach,
            "velocity_bound_mps": wheel.omega * reach,
            "impulse_bound_ns": wheel.mass * wheel.omega * reach,
        }
    return out
