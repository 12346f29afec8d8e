"""The robot in Pinocchio: its model reduced to the controller's joints (:func:`pinocchio_model`) and
the maps between C MuJoCo's coordinates and Pinocchio's (:class:`StateMap`).

MuJoCo's free joint is qpos = [p, quaternion (w, x, y, z)], qvel = [dp/dt (world axes), omega (base
axes)]; Pinocchio's free flyer is q = [p, quaternion (x, y, z, w)], v = [R' dp/dt, omega] (both in
base axes); the joints keep their angles in each model's own order. Hence v_pinocchio = T qvel with
T = blkdiag(R', I3, P) (P the joint permutation), and M_mujoco = T' M_pinocchio T.

Used by the crocoddyl cross-check of ``wbc-jax limit`` (:mod:`wbc_jax.jobs.limit_ddp`) and the TSID
peer (``benchmarks/tsid_baseline/``). JAX-free (mujoco and numpy; Pinocchio when a model is
built), so that the peer imports it without JAX."""

from __future__ import annotations

import pathlib
from collections.abc import Sequence

import mujoco
import numpy as np

# The robots whose crocoddyl check wbc_jax.jobs.limit_ddp runs (every robot with a URDF has a
# Pinocchio model here: the TSID peer runs on Talos too; the crocoddyl check was never run on it).
ROBOTS = ("icub",)


def pinocchio_model(joints: Sequence[str], urdf: pathlib.Path | str | None = None, robot: str = "icub"):
    """The URDF in Pinocchio with a free flyer, reduced to ``joints`` (the controller's, every other
    joint locked at 0). Returns a ``pinocchio.Model`` (iCub: nq = 30, nv = 29; Talos: 29, 28).

    urdf: a URDF file; None: the URDF the robot's MJCF is built from (its description's
    ``urdf_text``). Raises ValueError if the URDF lacks one of ``joints`` or the robot has no URDF."""
    import pinocchio as pin

    from wbc_jax.robot.robots import describe

    if urdf is not None:
        path = str(urdf)
        full = pin.buildModelFromUrdf(path, pin.JointModelFreeFlyer())
    else:
        desc = describe(robot)
        if desc.urdf_text is None:
            raise ValueError(f"robot {robot!r} has no URDF for Pinocchio (its description's urdf_text)")
        path = f"the URDF of {robot}"
        full = pin.buildModelFromXML(desc.urdf_text(), pin.JointModelFreeFlyer())
    names = list(full.names)
    missing = [j for j in joints if j not in names]
    if missing:
        raise ValueError(f"{path}: joints {missing} not found")
    locked = [full.getJointId(n) for n in names[2:] if n not in joints]  # 0: universe, 1: root
    return pin.buildReducedModel(full, locked, pin.neutral(full))


def quat_wxyz_to_xyzw(quat: np.ndarray) -> np.ndarray:
    """MuJoCo's quaternion (w, x, y, z) (4,) -> Pinocchio's (x, y, z, w) (4,)."""
    quat = np.asarray(quat, float)
    return np.concatenate([quat[1:4], quat[:1]])


def base_velocity_to_pinocchio(R: np.ndarray, qvel_base: np.ndarray) -> np.ndarray:
    """MuJoCo's free-joint velocity [dp/dt (world axes), omega (base axes)] (6,) -> Pinocchio's
    free-flyer velocity [R' dp/dt, omega] (6,), both in base axes; R (3, 3): base orientation."""
    qvel_base = np.asarray(qvel_base, float)
    return np.concatenate([np.asarray(R, float).T @ qvel_base[:3], qvel_base[3:6]])


class StateMap:
    """Index maps between C MuJoCo's coordinates and Pinocchio's for a robot's controlled joints.

    Attributes (n joints, in ``joints`` order): mj_qpos, mj_dof, actuators (n,): MuJoCo qpos
    and dof addresses and actuator ids; pin_q, pin_v (n,): Pinocchio q and v indices; to_pin_order
    (n,): ``x_pin = x[to_pin_order]`` puts a joint vector in Pinocchio's actuated order (v[6:]);
    from_pin_order (n,): its inverse; base_body: MuJoCo's free-floating body.

    Raises ValueError (a joint missing from either model, no free joint at MuJoCo's root, models
    of different sizes).
    """

    def __init__(self, mj_model: mujoco.MjModel, pin_model, joints: Sequence[str]):
        m = mj_model
        free = [j for j in range(m.njnt) if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE]
        if len(free) != 1 or m.jnt_qposadr[free[0]] != 0:
            raise ValueError("the MuJoCo model needs exactly one free joint, at qpos[0:7]")
        if (m.nq, m.nv) != (pin_model.nq, pin_model.nv):
            raise ValueError(f"MuJoCo (nq, nv) = {(m.nq, m.nv)} but Pinocchio's = {(pin_model.nq, pin_model.nv)}")
        self.joints = tuple(joints)
        mj_names = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j) for j in range(m.njnt)]
        pin_names = list(pin_model.names)
        for j in self.joints:
            if j not in mj_names or j not in pin_names:
                where = "MuJoCo" if j not in mj_names else "Pinocchio"
                raise ValueError(f"joint {j!r} is not in the {where} model")
        jid = [mj_names.index(j) for j in self.joints]
        self.base_body = int(m.jnt_bodyid[free[0]])
        self.mj_qpos = m.jnt_qposadr[jid].copy()
        self.mj_dof = m.jnt_dofadr[jid].copy()
        act_of_joint = {int(m.actuator_trnid[a, 0]): a for a in range(m.nu)}
        missing = [self.joints[k] for k, j in enumerate(jid) if j not in act_of_joint]
        if missing:
            raise ValueError(f"joints without a motor: {missing}")
        self.actuators = np.array([act_of_joint[j] for j in jid])
        ids = [pin_model.getJointId(j) for j in self.joints]
        self.pin_q = np.array([pin_model.idx_qs[i] for i in ids])
        self.pin_v = np.array([pin_model.idx_vs[i] for i in ids])
        if sorted(self.pin_v.tolist()) != list(range(6, pin_model.nv)):
            raise ValueError("the joints must be all of Pinocchio's actuated joints")
        self.from_pin_order = self.pin_v - 6  # x = x_pin[from_pin_order]
        self.to_pin_order = np.argsort(self.from_pin_order)  # x_pin = x[to_pin_order]
        self.nq, self.nv = m.nq, m.nv

    def q_v(self, qpos: np.ndarray, qvel: np.ndarray, R: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """MuJoCo (qpos (nq,), qvel (nv,)) -> Pinocchio (q (nq,), v (nv,)). R (3, 3): the base
        orientation if known (MjData.xmat of the base), else from the quaternion."""
        qpos, qvel = np.asarray(qpos, float), np.asarray(qvel, float)
        if R is None:
            R = np.zeros(9)
            mujoco.mju_quat2Mat(R, qpos[3:7])
            R = R.reshape(3, 3)
        q = np.empty(self.nq)
        q[:3] = qpos[:3]
        q[3:7] = quat_wxyz_to_xyzw(qpos[3:7])
        q[self.pin_q] = qpos[self.mj_qpos]
        v = np.empty(self.nv)
        v[:6] = base_velocity_to_pinocchio(R, qvel[:6])
        v[self.pin_v] = qvel[self.mj_dof]
        return q, v

    def velocity_matrix(self, R: np.ndarray) -> np.ndarray:
        """T (nv, nv) with v_pinocchio = T qvel_mujoco at base orientation R (3, 3):
        blkdiag(R', I3, P). Kinetic energy gives M_mujoco = T' M_pinocchio T."""
        T = np.zeros((self.nv, self.nv))
        T[:3, :3] = np.asarray(R, float).T
        T[3:6, 3:6] = np.eye(3)
        T[self.pin_v, self.mj_dof] = 1.0
        return T

    def joints_to_pin(self, x: np.ndarray) -> np.ndarray:
        """A joint vector (n,) in ``joints`` order -> Pinocchio's actuated order (n,)."""
        return np.asarray(x, float)[self.to_pin_order]

    def joints_from_pin(self, x_pin: np.ndarray) -> np.ndarray:
        """A joint vector (n,) in Pinocchio's actuated order (v[6:], TSID's torques) -> ``joints`` order."""
        return np.asarray(x_pin, float)[self.from_pin_order]
