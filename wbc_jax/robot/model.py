"""Load the robot, put it on the accelerator, and resolve names to indices once.

Everything name-based is resolved here, at build time, so that traced code only sees
integer index arrays and bad names fail early with the list of valid choices.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import mujoco
import numpy as np

from wbc_jax.core import mjx as mjx_device
from wbc_jax.core.mjx import mjx
from wbc_jax.robot.description import RobotDescription
from wbc_jax.robot.robots import DEFAULT_ROBOT, describe


def check_name(kind: str, name: str, valid: list[str]) -> None:
    if name not in valid:
        plural = "bodies" if kind == "body" else f"{kind}s"
        raise ValueError(f"unknown {kind} {name!r}; valid {plural}: {sorted(valid)}")


def _names(m: mujoco.MjModel, obj: mujoco.mjtObj, count: int) -> list[str]:
    return [mujoco.mj_id2name(m, obj, i) or "" for i in range(count)]


def _quat_to_mat(quat: np.ndarray) -> np.ndarray:
    R = np.zeros(9)
    mujoco.mju_quat2Mat(R, np.asarray(quat, dtype=float))
    return R.reshape(3, 3)


def load_mj_model(robot: str = DEFAULT_ROBOT, *, visual: bool = False) -> mujoco.MjModel:
    """Compile the robot's MJCF into a C MuJoCo model.

    Args:
      robot: robot name (``wbc_jax.robot.robots.DESCRIPTIONS``).
      visual: keep the visual meshes (read from the description's ``mesh_dir``). The
        physics model drops them: they never collide, and MJX would otherwise preprocess
        tens of thousands of mesh vertices for nothing.

    Raises:
      ValueError: unknown robot name. FileNotFoundError: missing model file.
    """
    spec = physics_spec(describe(robot), visual=visual)
    return spec.compile()


def physics_spec(desc: RobotDescription, *, visual: bool = False) -> mujoco.MjSpec:
    """The robot's MJCF as an editable spec: without its visual meshes unless ``visual``."""
    path = desc.model_path
    if not path.exists():
        raise FileNotFoundError(
            f"model file {path} is missing; reinstall wbc_jax (it is package data), or in a "
            f"checkout regenerate it with 'python {desc.builder}'"
        )
    spec = mujoco.MjSpec.from_file(str(path))
    if visual:
        if desc.mesh_dir is None:
            raise ValueError(f"robot {desc.name} has no visual meshes")
        spec.meshdir = str(desc.mesh_dir())
    else:
        for geom in list(spec.geoms):
            if geom.type == mujoco.mjtGeom.mjGEOM_MESH:
                spec.delete(geom)
        for mesh in list(spec.meshes):
            spec.delete(mesh)
    return spec


@dataclasses.dataclass(frozen=True, eq=False)
class RobotIndex:
    """Static structure of the robot: ids resolved from names once (numpy, never traced).

    Attributes:
      joints: controller joint names, in controller order (n,).
      qpos_joints: qpos address of each controller joint (n,).
      dof_joints: dof address of each controller joint (n,).
      actuators: actuator id driving each controller joint (n,).
      dof_perm: MuJoCo dof index of each entry of the controller's ``nu`` (6+n,).
      base_body: body id of the floating base.
      foot_sites / foot_bodies: site ids of the soles and their bodies (2,).
      foot_points / foot_rotations: the sole sites' origins (2, 3) and axes (2, 3, 3) in their
        bodies' frames.
      foot_geoms: contact geom ids per foot (2, k).
      mass: total mass (kg).
      body_ancestor_dofs: bool (nbody, nv) in MuJoCo dof order, True where dof moves body.
      torque_limit: actuator ctrl limit per controller joint (n,).
    """

    robot: str
    joints: tuple[str, ...]
    qpos_joints: np.ndarray
    dof_joints: np.ndarray
    actuators: np.ndarray
    dof_perm: np.ndarray
    base_body: int
    foot_sites: np.ndarray
    foot_bodies: np.ndarray
    foot_points: np.ndarray
    foot_rotations: np.ndarray
    foot_geoms: np.ndarray
    site_names: tuple[str, ...]
    body_names: tuple[str, ...]
    mass: float
    body_ancestor_dofs: np.ndarray
    torque_limit: np.ndarray
    nq: int
    nv: int
    nu: int

    @property
    def n(self) -> int:
        """Number of controlled joints."""
        return len(self.joints)

    def site_id(self, name: str) -> int:
        """Site id by name; raises ValueError listing the valid names."""
        check_name("site", name, list(self.site_names))
        return self.site_names.index(name)

    def body_id(self, name: str) -> int:
        """Body id by name; raises ValueError listing the valid names."""
        check_name("body", name, list(self.body_names))
        return self.body_names.index(name)

    @property
    def pushable_bodies(self) -> tuple[str, ...]:
        """The bodies a push can act on: the robot's, not the world (body 0, which never moves)."""
        return self.body_names[1:]

    @property
    def description(self) -> RobotDescription:
        """The robot's description (:mod:`wbc_jax.robot.description`)."""
        return describe(self.robot)

    def pushable_body_id(self, name: str) -> int:
        """Body id of a body a push can act on (a body name or a role, ``trunk``); raises ValueError
        listing the valid names."""
        name = self.description.body(name)
        if name in self.body_names and name not in self.pushable_bodies:
            raise ValueError(
                f"cannot push body {name!r} (the world does not move); pushable bodies: {sorted(self.pushable_bodies)}"
            )
        check_name("body", name, list(self.pushable_bodies))
        return self.body_names.index(name)


def build_index(m: mujoco.MjModel, robot: str = DEFAULT_ROBOT, joints=None) -> RobotIndex:
    """Resolve joint, actuator, site and body names of ``m`` into a :class:`RobotIndex` (``joints``:
    the controlled joints, default the description's).

    Raises:
      ValueError: no free joint at the root, unknown joint/site names, a joint with no motor.
    """
    free = [j for j in range(m.njnt) if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE]
    if len(free) != 1 or m.jnt_qposadr[free[0]] != 0:
        raise ValueError(
            f"the model needs exactly one free joint at the root (a floating base); found {len(free)} free joints"
        )
    base_body = int(m.jnt_bodyid[free[0]])
    joint_names = _names(m, mujoco.mjtObj.mjOBJ_JOINT, m.njnt)
    hinge_names = [joint_names[j] for j in range(m.njnt) if j != free[0]]
    desc = describe(robot)
    joints = tuple(desc.joints if joints is None else joints)
    if len(set(joints)) != len(joints):
        raise ValueError(f"duplicate joint names in {joints}")
    for name in joints:
        check_name("joint", name, hinge_names)
    jid = np.array([joint_names.index(name) for name in joints])
    act_joint = {int(m.actuator_trnid[a, 0]): a for a in range(m.nu)}
    missing = [joints[k] for k, j in enumerate(jid) if j not in act_joint]
    if missing:
        raise ValueError(f"joints without a motor: {missing}")
    site_names = tuple(_names(m, mujoco.mjtObj.mjOBJ_SITE, m.nsite))
    for name in desc.feet:
        check_name("site", name, list(site_names))
    foot_sites = np.array([site_names.index(s) for s in desc.feet])
    foot_bodies = m.site_bodyid[foot_sites].copy()
    geom_names = _names(m, mujoco.mjtObj.mjOBJ_GEOM, m.ngeom)
    foot_geoms = np.array(
        [[g for g, nm in enumerate(geom_names) if nm.startswith(prefix)] for prefix in desc.foot_contact_prefixes]
    )
    dof_joints = m.jnt_dofadr[jid].copy()
    # Which dofs move each body: walk up the tree from the dof's body.
    ancestors = np.zeros((m.nbody, m.nv), dtype=bool)
    for b in range(m.nbody):
        c = b
        while c > 0:
            ancestors[b, m.dof_bodyid == c] = True
            c = m.body_parentid[c]
    actuators = np.array([act_joint[j] for j in jid])
    return RobotIndex(
        robot=robot,
        joints=joints,
        qpos_joints=m.jnt_qposadr[jid].copy(),
        dof_joints=dof_joints,
        actuators=actuators,
        dof_perm=np.concatenate([np.arange(6), dof_joints]),
        base_body=base_body,
        foot_sites=foot_sites,
        foot_bodies=foot_bodies,
        foot_points=m.site_pos[foot_sites].copy(),
        foot_rotations=np.stack([_quat_to_mat(m.site_quat[s]) for s in foot_sites]),
        foot_geoms=foot_geoms,
        site_names=site_names,
        body_names=tuple(_names(m, mujoco.mjtObj.mjOBJ_BODY, m.nbody)),
        mass=float(m.body_subtreemass[base_body]),
        body_ancestor_dofs=ancestors,
        torque_limit=m.actuator_ctrlrange[actuators, 1].copy(),
        nq=m.nq,
        nv=m.nv,
        nu=m.nu,
    )


@dataclasses.dataclass(frozen=True, eq=False)
class Robot:
    """C model, MJX model (built on first use) and static index of one robot."""

    mj_model: mujoco.MjModel
    index: RobotIndex

    @functools.cached_property
    def mjx_model(self) -> mjx.Model:
        """The MJX model (JAX implementation) on this process's device (concrete arrays, even when
        first asked for while tracing)."""
        with jax.ensure_compile_time_eval():
            return mjx_device.put_model(self.mj_model)

    @property
    def description(self) -> RobotDescription:
        """The robot's description (:mod:`wbc_jax.robot.description`)."""
        return self.index.description

    def home_qpos(self) -> np.ndarray:
        """qpos of the description's nominal keyframe (soles flat on the floor)."""
        return self.mj_model.key(self.description.nominal_keyframe).qpos.copy()


@functools.lru_cache(maxsize=8)
def load_robot(robot: str = DEFAULT_ROBOT) -> Robot:
    """Load a robot by name: C model, MJX model (JAX backend, on first use) and index (cached)."""
    m = load_mj_model(robot)
    return Robot(mj_model=m, index=build_index(m, robot))


def summary(robot: Robot) -> dict:
    """JSON-serialisable summary of the model (``wbc-jax info``)."""
    m, idx = robot.mj_model, robot.index
    return {
        "robot": idx.robot,
        "source": idx.description.source,
        "nq": int(m.nq),
        "nv": int(m.nv),
        "nu": int(m.nu),
        "nbody": int(m.nbody),
        "mass": float(idx.mass),
        "joints": list(idx.joints),
        "timestep": float(m.opt.timestep),
        "solver": {"iterations": int(m.opt.iterations), "ls_iterations": int(m.opt.ls_iterations)},
        "feet": list(idx.description.feet),
        "contact_geoms_per_foot": int(idx.foot_geoms.shape[1]),
        "torque_limit_nm": float(idx.torque_limit.max()),
        "home_qpos": [round(float(x), 6) for x in robot.home_qpos()],
    }


@functools.lru_cache(maxsize=8)
def pushable_bodies(robot: str) -> tuple[str, ...]:
    """The bodies of ``robot`` a push can act on (:attr:`RobotIndex.pushable_bodies`) and the body
    roles (``trunk``, ...): the valid values of the jobs' body flags. From the C model alone:
    checking a flag starts no JAX backend (``jax.distributed.initialize`` must come before one)."""
    return (*build_index(load_mj_model(robot), robot).pushable_bodies, *describe(robot).bodies)
