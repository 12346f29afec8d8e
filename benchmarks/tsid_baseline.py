"""[TSID peer] The iCub balanced by TSID (Pinocchio + eiquadprog, C++) on C MuJoCo physics.

A real peer of wbc_jax on the CPU: the controller a user of this robot would otherwise write with
TSID (stack-of-tasks/tsid), on the same plant, tasks, pushes and metrics as the rest of the project,
so that the figures compare like for like. JAX-free: it imports numpy, mujoco, pinocchio, tsid,
``benchmarks/baseline_cpu.py`` (the closed-loop metrics, the reference table, pushes) and
``wbc_jax/core/constants.py`` / ``assets/build_icub_mjcf.py`` by file path.

Plant (as :func:`wbc_jax.robot.model.load_mj_model`): ``assets/icub/icub_23dof.xml`` without its visual
meshes, C MuJoCo at 1 kHz (the model's Newton solver, pyramidal cones, four 5 mm corner spheres per
sole), 23 torque motors saturated at their ctrlrange (+-60 N m; MuJoCo clamps ``ctrl`` to it, the
torques are clipped here first so that the metrics see the applied torque), pushes as a world-axes
force on the CoM of a body (default ``chest``) through ``xfrc_applied``, from an onset for a duration.
No auto-reset: a diverged state is restored to the tick's start and flagged (a NaN run), as in
:func:`baseline_cpu.simulate`.

Controller model: the icub-models ``iCubGazeboV2_5`` URDF in Pinocchio with a free flyer, reduced to
the 23 joints of ``DRIVEN_JOINTS`` (neck and wrists locked at 0, as in the MJCF). Its CoM, joint-space
mass matrix and sole frames equal C MuJoCo's to ~1e-12 at any state (``tests/test_tsid_baseline.py``):
the MJCF carries the URDF's masses and inertias at 12 digits, no armature, and the static links
fused into their moving parents as Pinocchio's reduction fuses them.

State map (:class:`StateMap`): MuJoCo's free joint is qpos = [p (world), quaternion (w, x, y, z)],
qvel = [dp/dt (world axes), omega (base axes)]; Pinocchio's free flyer is q = [p, quaternion (x, y, z,
w)], v = [R' dp/dt, omega] (both in base axes, R = the base orientation). The joints are reordered by
name (Pinocchio orders them depth-first through the URDF tree: legs, torso, arms). So v = T qvel with
T = blkdiag(R', I3, P) (P the joint permutation), and M_mujoco = T' M_pinocchio T.

Formulation (TSID ``InverseDynamicsFormulationAccForce``, variables the accelerations dv (29,) and the
3-D forces at the four corners of each sole's CoP rectangle (24,); ``SolverHQuadProgFast``, TSID's
eiquadprog HQP solver, once per 10 ms control tick, torques held for 10 physics steps):

* level 0 (constraints): the floating-base rows of the dynamics; per sole a ``Contact6d``: its motion
  constraint J dv + dJ v = -Kp e - Kd de with Kp = Kd = 0 (= the WBC's rigid contact, J nu_dot +
  dJ nu = 0), and its force constraints: a friction pyramid |f_t| <= mu f_n per corner and axis with
  mu the model's floor friction (the contact pairs' sliding friction, 1.0), the sum of the corners'
  normal forces >= ``FZ_MIN`` (the WBC's minimum normal force per foot) and <= ``FZ_MAX``;
  the corners are those of ``FOOT_SIZE`` (the WBC CoP rectangle, ``ContactParams.foot_size``, the
  rectangle of the metrics' support margin), so the CoP stays inside it;
* level 1 (one weighted least-squares cost): CoM (``TaskComEquality``), centroidal angular momentum
  (``TaskAMEquality``), joint posture (``TaskJointPosture``) and the contacts' force regularisation,
  weighted as :class:`TsidConfig`.

eiquadprog's HQP solves two levels (constraints, then one weighted cost), so the WBC's strict
hierarchy (the momentum task first, the postural task in its null space) becomes weights: the CoM
task at 1, the angular momentum at ``w_am`` = 1e-3 (about 1 / m^2: an angular-momentum-rate error of
1 N m weighs as a CoM-acceleration error of 1 / m m/s^2, i.e. as 1 N of linear-momentum rate, the
equal weighting of the WBC's momentum rows), the posture at 1e-3 (small: it yields to the momentum;
TSID's own biped examples use 1e-4 to 1e-1), the forces' regularisation at 1e-5 (TSID's examples).
The weights have no WBC counterpart and move the push envelope (``tsid_peer.py --sensitivity``).
The torque limits are not in the QP: with TSID's ``TaskActuationBounds`` as hard constraints (level
0), eiquadprog looped without returning on a 158.6 N, 0.1 s forward push.

Gains: the WBC defaults (``wbc_jax/core/constants.py``) where the formulations correspond:

* K_P,CoM = (50, 50, 10), K_D,CoM = 2 sqrt(K_P,CoM) / 20 -> ``TaskComEquality`` Kp, Kd: the same
  law (the WBC asks the momentum rate m (c_ddot_ref - K_P e - K_D e_dot), TSID the CoM acceleration
  c_ddot_ref - K_P e - K_D e_dot). K_I,CoM = 0 by default, and TSID's CoM task has no integral.
* K_P,w = 1 -> ``TaskAMEquality`` Kp: TSID asks L_dot = -Kp (L - L_ref) + L_dot_ref with L_ref = 0,
  the WBC's -K_P,w L.
* K_I,w = 0.25: no counterpart. The WBC adds -K_I,w J_G,ang (s - s_des), the integral of the angular
  momentum; TSID's angular-momentum task has none (its Kd is unused). The posture task holds the
  posture instead.
* the postural k_p (per joint) and k_d = 2 sqrt(k_p) / 20: cannot correspond. The WBC postural task
  is a torque, -k_p (s - s_des) - k_d s_dot projected into the null space of the momentum task; TSID's
  is a joint-acceleration PD, s_ddot = -Kp (s - s_des) - Kd s_dot. The same numbers are taken as
  acceleration gains (1/s^2) with TSID's critical damping Kd = 2 sqrt(Kp): with the WBC's damping
  ratio 0.05 on accelerations the posture rings (the stand task's CoM error grows ~100x).

The model's joint damping (1 N m s/rad per joint, from the URDF) is compensated, tau += D s_dot, as
the WBC controller's ``compensate_passive`` does by default. A tick whose QP fails (eiquadprog status
!= 0) keeps the previous torques and counts in ``qp_infeasible_ticks``.

Metrics: ``baseline_cpu.LoopMetrics`` (one implementation with the NumPy baseline, the quantities of
``wbc_jax.sim.loop.ClosedLoop``: CoM from MuJoCo's ``subtree_com``, the sole sites, the anchors at the start),
named by ``baseline_cpu.summary_columns`` as ``constants.METRIC_NAMES``; ``survived`` is the strict
criterion of ``constants.SURVIVAL_CRITERION``. ``max_constraint_violation``: the largest violation of
TSID's own contact-force inequalities by the commanded corner forces, divided by the foot's normal
force (at least ``FZ_MIN``), as ``wbc_jax.control.constraints.violation`` normalises.

References (:func:`make_schedule`): the ``stand`` and ``sinusoid`` tasks of
:func:`wbc_jax.control.references.make_schedule` (CoM at its initial value; plus 2 cm along world y at
0.2 Hz from t = 0; posture at the home keyframe; both feet active), evaluated with
``baseline_cpu.schedule_table``.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import math
import pathlib
import sys
import time
import warnings
from collections.abc import Sequence
from typing import Any

import mujoco
import numpy as np

from wbc_jax.robot import icub

ROOT = pathlib.Path(__file__).resolve().parent.parent
MODEL_XML = ROOT / "assets" / "icub" / "icub_23dof.xml"


def _load_by_path(name: str, path: pathlib.Path):
    """A module of this repository loaded from its file (``benchmarks/`` and ``assets/`` are not
    packages, and ``wbc_jax`` imports JAX on import), registered in ``sys.modules`` once."""
    module = sys.modules.get(name)
    if module is None:
        spec = importlib.util.spec_from_file_location(name, path)
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module  # dataclasses look their module up by name
        spec.loader.exec_module(module)
    return module


bc = _load_by_path("baseline_cpu", ROOT / "benchmarks" / "baseline_cpu.py")
mjcf = _load_by_path("_wbc_build_icub_mjcf", ROOT / "assets" / "build_icub_mjcf.py")
constants = bc.constants

DRIVEN_JOINTS: tuple[str, ...] = tuple(mjcf.DRIVEN_JOINTS)
FEET = ("l_sole", "r_sole")
ROBOTS = ("icub",)  # the robots whose Pinocchio model this peer builds (wbc_jax.jobs.limit_ddp checks)
TASKS = ("stand", "sinusoid")
# Copies of wbc_jax names (modules that import JAX), checked in tests/test_tsid_baseline.py:
FOOT_SIZE = ((-0.07, 0.12), (-0.045, 0.045))  # robot.contacts.ContactParams().foot_size (m, sole frame)
FZ_MIN = 10.0  # robot.contacts.ContactParams().fz_min (N, per foot)
TASK_DURATION = {"stand": 10.0, "sinusoid": 20.0}  # control.references.make_schedule's defaults (s)
SINE_AMPLITUDE, SINE_FREQUENCY, SINE_AXIS = 0.02, 0.2, (0.0, 1.0, 0.0)  # its sinusoid (m, Hz)
FZ_MAX = 1e4  # N per foot: no WBC counterpart (TSID needs one); ~30 x the robot's weight
# TSID wheels are built against one Pinocchio: another version's Model crashes TSID's RobotWrapper
# (tsid 1.10.0 with pin 4.1.0: MemoryError or "free(): invalid pointer"). tsid -> pin version.
TSID_PINOCCHIO = {"1.10.0": "4.0.0"}


# --------------------------------------------------------------------------------------
# Packages and models
# --------------------------------------------------------------------------------------


def tsid_problem() -> str | None:
    """Why TSID cannot run here (a sentence), or None. Reads package metadata only: importing a
    TSID built against another Pinocchio works, constructing its RobotWrapper crashes the process."""
    from importlib import metadata

    try:
        tsid_version = metadata.version("tsid")
    except metadata.PackageNotFoundError:
        return "tsid is not installed (python3 .ci/install_libtsid.py && pip install -e '.[dev]')"
    try:
        pin_version = metadata.version("pin")
    except metadata.PackageNotFoundError:
        return "pinocchio (pip package 'pin') is not installed"
    wanted = TSID_PINOCCHIO.get(tsid_version)
    if wanted is not None and pin_version != wanted:
        return (
            f"tsid {tsid_version} is built against Pinocchio {wanted}, found pin {pin_version} "
            f"(its RobotWrapper would crash): pip install pin=={wanted}"
        )
    return None


def _import_tsid():
    """The ``tsid`` module, after :func:`tsid_problem` (raises ImportError with its sentence)."""
    problem = tsid_problem()
    if problem is not None:
        raise ImportError(problem)
    with warnings.catch_warnings():
        # Its bindings register one shared_ptr converter twice (a RuntimeWarning, harmless).
        warnings.simplefilter("ignore", RuntimeWarning)
        import tsid
    return tsid


def load_mj_model(path: pathlib.Path | str = MODEL_XML) -> mujoco.MjModel:
    """The C MuJoCo model as :func:`wbc_jax.robot.model.load_mj_model` (``visual=False``) compiles it: the
    MJCF without its visual mesh geoms and meshes (they never collide), no auto-reset either way.

    Raises FileNotFoundError (missing model file)."""
    path = pathlib.Path(path)
    if not path.exists():
        raise FileNotFoundError(f"model file {path} is missing; regenerate it with 'python assets/build_icub_mjcf.py'")
    spec = mujoco.MjSpec.from_file(str(path))
    for geom in list(spec.geoms):
        if geom.type == mujoco.mjtGeom.mjGEOM_MESH:
            spec.delete(geom)
    for mesh in list(spec.meshes):
        spec.delete(mesh)
    return spec.compile()


def pinocchio_model(urdf: pathlib.Path | str | None = None):
    """The URDF in Pinocchio with a free flyer, reduced to ``DRIVEN_JOINTS`` (every other joint
    locked at 0). Returns a ``pinocchio.Model`` (nq = 30, nv = 29).

    urdf: None: icub-models' iCubGazeboV2_5 (``assets/build_icub_mjcf.icub_paths``).
    Raises ValueError if the URDF lacks a driven joint."""
    import pinocchio as pin

    path = str(mjcf.icub_paths()[0] if urdf is None else urdf)
    full = pin.buildModelFromUrdf(path, pin.JointModelFreeFlyer())
    names = list(full.names)
    missing = [j for j in DRIVEN_JOINTS if j not in names]
    if missing:
        raise ValueError(f"{path}: joints {missing} not found")
    locked = [full.getJointId(n) for n in names[2:] if n not in DRIVEN_JOINTS]  # 0: universe, 1: root
    return pin.buildReducedModel(full, locked, pin.neutral(full))


def _body_id(m: mujoco.MjModel, name: str) -> int:
    """Body id by name; ValueError listing the valid names."""
    i = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, name)
    if i < 0:
        valid = sorted(mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b) for b in range(1, m.nbody))
        raise ValueError(f"unknown body {name!r}; valid bodies: {valid}")
    return i


def floor_friction(m: mujoco.MjModel) -> float:
    """The sliding friction of the model's foot-floor contact pairs (one value; ValueError if they
    differ or the model has none)."""
    mu = np.unique(np.asarray(m.pair_friction)[:, 0])
    if mu.size != 1:
        raise ValueError(f"expected one floor friction over the contact pairs, got {mu.tolist()}")
    return float(mu[0])


def sole_contact_rectangle(m: mujoco.MjModel, qpos: np.ndarray | None = None) -> tuple:
    """The largest rectangle ((x_min, x_max), (y_min, y_max)) m, in sole-frame coordinates, inside
    the contact spheres' centres of both soles (the model's feet: 4 spheres per sole, geoms
    ``{l,r}_foot_contact_*``), at qpos (nq,) (None: the home keyframe)."""
    d = mujoco.MjData(m)
    d.qpos[:] = m.key("home").qpos if qpos is None else qpos
    mujoco.mj_kinematics(m, d)
    lo, hi = np.full(2, -np.inf), np.full(2, np.inf)
    for site in FEET:
        s = m.site(site).id
        R, p = d.site_xmat[s].reshape(3, 3), d.site_xpos[s]
        geoms = [g for g in range(m.ngeom) if m.geom(g).name.startswith(f"{site[0]}_foot_contact_")]
        if not geoms:
            raise ValueError(f"the model has no contact geoms {site[0]}_foot_contact_*")
        local = (d.geom_xpos[geoms] - p) @ R
        lo, hi = np.maximum(lo, local[:, :2].min(0)), np.minimum(hi, local[:, :2].max(0))
    return ((float(lo[0]), float(hi[0])), (float(lo[1]), float(hi[1])))


def non_foot_bodies(m: mujoco.MjModel) -> np.ndarray:
    """Bodies that must stay off the floor (wbc_jax.sim.loop.ClosedLoop): all but the world, the soles'
    bodies and their parents (the ankles). (k,) int."""
    feet = np.array([m.site_bodyid[m.site(s).id] for s in FEET])
    excluded = set(feet.tolist()) | set(m.body_parentid[feet].tolist())
    return np.array([b for b in range(1, m.nbody) if b not in excluded])


# --------------------------------------------------------------------------------------
# State map
# --------------------------------------------------------------------------------------


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
    """Index maps between C MuJoCo's coordinates and Pinocchio's for the 23-joint iCub.

    Attributes (n = 23, joints in ``joints`` order): mj_qpos, mj_dof, actuators (n,): MuJoCo qpos
    and dof addresses and actuator ids; pin_q, pin_v (n,): Pinocchio q and v indices; to_pin_order
    (n,): ``x_pin = x[to_pin_order]`` puts a joint vector in Pinocchio's actuated order (v[6:]);
    from_pin_order (n,): its inverse; base_body: MuJoCo's free-floating body.

    Raises ValueError (a joint missing from either model, no free joint at MuJoCo's root, models
    of different sizes).
    """

    def __init__(self, mj_model: mujoco.MjModel, pin_model, joints: Sequence[str] = DRIVEN_JOINTS):
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


# --------------------------------------------------------------------------------------
# References
# --------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class TaskSchedule:
    """The fields of :class:`wbc_jax.control.references.Schedule` that ``baseline_cpu.schedule_table``
    reads, for the stand and sinusoid tasks: com0 (3,), s0 (n,) (joints order), no minimum-jerk
    segments, an optional CoM sinusoid (m, Hz, world axis)."""

    name: str
    duration: float
    com0: np.ndarray
    s0: np.ndarray
    com_segments: tuple = ((), (), np.zeros((0, 3)))
    posture_segments: tuple = ((), (), None)
    activation_segments: tuple = ((), (), np.zeros((0, 2)))
    sine_amplitude: float = 0.0
    sine_frequency: float = 0.0
    sine_axis: tuple = SINE_AXIS


def make_schedule(task: str, com0: np.ndarray, s0: np.ndarray, duration: float | None = None) -> TaskSchedule:
    """The references of ``task`` as :func:`wbc_jax.control.references.make_schedule` builds them:
    ``stand`` (CoM held at com0 (3,), default 10 s) or ``sinusoid`` (com0 + 2 cm sin(2 pi 0.2 t)
    along world y, default 20 s); posture s0 (n,). Raises ValueError (other tasks, bad sizes)."""
    if task not in TASKS:
        raise ValueError(f"unknown task {task!r}; the TSID peer runs {list(TASKS)}")
    com0, s0 = np.asarray(com0, float), np.asarray(s0, float)
    if com0.shape != (3,) or s0.ndim != 1:
        raise ValueError(f"com0 must be (3,) and s0 (n,), got {com0.shape} and {s0.shape}")
    if duration is not None and not (math.isfinite(duration) and duration > 0):
        raise ValueError(f"duration must be a positive number of seconds, got {duration}")
    duration = float(duration or TASK_DURATION[task])
    if task == "stand":
        return TaskSchedule("stand", duration, com0, s0)
    return TaskSchedule("sinusoid", duration, com0, s0, sine_amplitude=SINE_AMPLITUDE, sine_frequency=SINE_FREQUENCY)


# --------------------------------------------------------------------------------------
# The TSID controller
# --------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class TsidConfig:
    """Weights and gains of the TSID controller (module docstring: what corresponds to the WBC).

    Attributes:
      w_com, w_am, w_posture, w_force_reg: level-1 weights of the CoM, angular-momentum, posture
        tasks and the contacts' force regularisation.
      kp_com, kd_com (3,): CoM task PD (1/s^2, 1/s); None: the WBC's K_P,CoM, K_D,CoM.
      kp_am (3,): angular-momentum task gain (1/s); None: the WBC's K_P,w.
      kp_posture (n,): posture PD stiffness (1/s^2, ``DRIVEN_JOINTS`` order); None: the WBC's
        postural k_p values. kd_posture (n,): None: 2 sqrt(kp_posture) (critical damping).
      contact_kp: PD gain of the soles' motion constraints (Kd = 2 sqrt(Kp)); 0: rigid contact.
      mu: friction coefficient of the corners' pyramids; None: the model's floor friction.
      fz_min, fz_max: bounds of each sole's normal force (N). foot_size: the CoP rectangle
        ((x_min, x_max), (y_min, y_max)) m in the sole frame, its corners the contact points.
      compensate_damping: add the model's joint damping D s_dot to the torques.
    """

    w_com: float = 1.0
    w_am: float = 1e-3
    w_posture: float = 1e-3
    w_force_reg: float = 1e-5
    kp_com: tuple | None = None
    kd_com: tuple | None = None
    kp_am: tuple | None = None
    kp_posture: tuple | None = None
    kd_posture: tuple | None = None
    contact_kp: float = 0.0
    mu: float | None = None
    fz_min: float = FZ_MIN
    fz_max: float = FZ_MAX
    foot_size: tuple = FOOT_SIZE
    compensate_damping: bool = True

    def __post_init__(self):
        for name in ("w_com", "w_am", "w_posture", "w_force_reg", "contact_kp", "fz_min", "fz_max"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise ValueError(f"TsidConfig.{name} must be a finite number >= 0, got {value!r}")
        if not 0 < self.fz_min <= self.fz_max:
            raise ValueError(f"TsidConfig needs 0 < fz_min <= fz_max, got {self.fz_min}, {self.fz_max}")
        if self.mu is not None and not (math.isfinite(self.mu) and self.mu > 0):
            raise ValueError(f"TsidConfig.mu must be positive, got {self.mu!r}")
        (x0, x1), (y0, y1) = self.foot_size
        if not (x0 < x1 and y0 < y1):
            raise ValueError(f"TsidConfig.foot_size needs x_min < x_max and y_min < y_max, got {self.foot_size}")

    def gains(self, n: int) -> dict[str, np.ndarray]:
        """The resolved gains (float64): kp_com, kd_com, kp_am (3,), kp_posture, kd_posture (n,),
        in ``DRIVEN_JOINTS`` order. Raises ValueError on a wrong shape or a negative gain."""
        wbc = icub.DESCRIPTION.default_gain_values(n)
        out = {
            "kp_com": wbc["kp_com"] if self.kp_com is None else self.kp_com,
            "kd_com": wbc["kd_com"] if self.kd_com is None else self.kd_com,
            "kp_am": wbc["kp_ang"] if self.kp_am is None else self.kp_am,
            "kp_posture": wbc["kp_postural"] if self.kp_posture is None else self.kp_posture,
        }
        out = {k: np.asarray(v, float) for k, v in out.items()}
        kd = 2.0 * np.sqrt(np.maximum(out["kp_posture"], 0.0)) if self.kd_posture is None else self.kd_posture
        out["kd_posture"] = np.asarray(kd, float)
        for name, value in out.items():
            size = n if name.endswith("posture") else 3
            if value.shape != (size,) or not np.all(np.isfinite(value)) or np.any(value < 0):
                raise ValueError(f"TsidConfig {name} must be {size} finite numbers >= 0, got {value.tolist()}")
        return out

    def corners(self) -> np.ndarray:
        """The contact points (3, 4): the CoP rectangle's corners on the sole plane (sole frame)."""
        (x0, x1), (y0, y1) = self.foot_size
        return np.array([[x, y, 0.0] for x in (x0, x1) for y in (y0, y1)]).T


class TsidController:
    """TSID's balancing controller for the 23-joint iCub (module docstring), built at a state.

    Usage: ``tau, info = ctrl(t, qpos, qvel, ref)`` once per control tick with MuJoCo's state.

    Args:
      pin_model: :func:`pinocchio_model`. state_map: :class:`StateMap` of it and the MuJoCo model.
      mj_model: the MuJoCo model (floor friction, joint damping).
      qpos0 (nq,): MuJoCo state at which the soles' contact references are taken (zero velocity).
      s_des (n,): the posture reference (``DRIVEN_JOINTS`` order). config: :class:`TsidConfig`.
    """

    def __init__(self, pin_model, state_map: StateMap, mj_model: mujoco.MjModel, qpos0: np.ndarray,
                 s_des: np.ndarray, config: TsidConfig | None = None):  # fmt: skip
        tsid = _import_tsid()
        self.tsid = tsid
        self.config = cfg = TsidConfig() if config is None else config
        self.map = state_map
        n = len(state_map.joints)
        g = cfg.gains(n)
        self.gains = g
        mu = floor_friction(mj_model) if cfg.mu is None else float(cfg.mu)
        self.mu = mu
        self.damping = np.asarray(mj_model.dof_damping[state_map.mj_dof], float) if cfg.compensate_damping else None
        self.robot = tsid.RobotWrapper(pin_model, tsid.FLOATING_BASE_SYSTEM, False)
        self.formulation = form = tsid.InverseDynamicsFormulationAccForce("tsid", self.robot, False)
        q0, v0 = state_map.q_v(qpos0, np.zeros(state_map.nv))
        form.computeProblemData(0.0, q0, v0)
        data = form.data()
        model = self.robot.model()
        points, normal = cfg.corners(), np.array([0.0, 0.0, 1.0])
        self.contacts = []
        for frame in FEET:
            if not model.existFrame(frame):
                raise ValueError(f"the Pinocchio model has no frame {frame!r}")
            contact = tsid.Contact6d(f"contact_{frame}", self.robot, frame, points, normal, mu, cfg.fz_min, cfg.fz_max)
            contact.setKp(cfg.contact_kp * np.ones(6))
            contact.setKd(2.0 * math.sqrt(cfg.contact_kp) * np.ones(6))
            contact.setReference(self.robot.framePosition(data, model.getFrameId(frame)))
            form.addRigidContact(contact, cfg.w_force_reg)
            self.contacts.append(contact)
        # The force inequalities are constant (sole frame): for the violation metric.
        self._force_rows = []
        for contact in self.contacts:
            ineq = contact.computeForceTask(0.0, q0, v0, data)
            self._force_rows.append((np.array(ineq.matrix), np.array(ineq.lowerBound), np.array(ineq.upperBound)))
        self.com_task = tsid.TaskComEquality("task-com", self.robot)
        self.com_task.setKp(g["kp_com"])
        self.com_task.setKd(g["kd_com"])
        form.addMotionTask(self.com_task, cfg.w_com, 1, 0.0)
        self.am_task = tsid.TaskAMEquality("task-am", self.robot)
        self.am_task.setKp(g["kp_am"])
        self.am_task.setKd(np.zeros(3))  # unused by TaskAMEquality
        self.am_task.setReference(tsid.TrajectorySample(3))  # L_ref = 0, L_dot_ref = 0
        form.addMotionTask(self.am_task, cfg.w_am, 1, 0.0)
        self.posture_task = tsid.TaskJointPosture("task-posture", self.robot)
        self.posture_task.setKp(state_map.joints_to_pin(g["kp_posture"]))
        self.posture_task.setKd(state_map.joints_to_pin(g["kd_posture"]))
        form.addMotionTask(self.posture_task, cfg.w_posture, 1, 0.0)
        self._com_ref = tsid.TrajectorySample(3)
        self._posture_ref = tsid.TrajectorySample(n)
        self.set_posture(s_des)
        self.solver = tsid.SolverHQuadProgFast("eiquadprog-fast")
        self.solver.resize(form.nVar, form.nEq, form.nIn)
        self._tau_prev = np.zeros(n)

    def set_posture(self, s_des: np.ndarray) -> None:
        """Posture reference s_des (n,) (``DRIVEN_JOINTS`` order), zero velocity and acceleration."""
        s_des = np.asarray(s_des, float)
        n = len(self.map.joints)
        if s_des.shape != (n,):
            raise ValueError(f"s_des must have shape ({n},), got {s_des.shape}")
        self._posture_ref.value(self.map.joints_to_pin(s_des))
        self._posture_ref.derivative(np.zeros(n))
        self._posture_ref.second_derivative(np.zeros(n))
        self.posture_task.setReference(self._posture_ref)

    def solve(self, t: float, q: np.ndarray, v: np.ndarray, com_pos, com_vel, com_acc):
        """One TSID solve at Pinocchio's state q (nq,), v (nv,) for the CoM references (3,) each.
        Returns (tau (n,) in Pinocchio's actuated order or None if the QP failed, the HQP output)."""
        ref = self._com_ref
        ref.value(np.asarray(com_pos, float))
        ref.derivative(np.asarray(com_vel, float))
        ref.second_derivative(np.asarray(com_acc, float))
        self.com_task.setReference(ref)
        hqp = self.formulation.computeProblemData(t, q, v)
        sol = self.solver.solve(hqp)
        if sol.status != 0:
            return None, sol
        return self.formulation.getActuatorForces(sol), sol

    def __call__(self, t: float, qpos: np.ndarray, qvel: np.ndarray, ref: dict, R: np.ndarray | None = None):
        """One control tick from MuJoCo's state qpos (nq,), qvel (nv,) (R (3, 3): base orientation).

        ref: com_pos, com_vel, com_acc (3,) (``baseline_cpu.schedule_table`` rows).
        Returns (tau (n,) unsaturated, ``DRIVEN_JOINTS`` order; info dict: ``status`` (eiquadprog's,
        0 = solved), ``infeasible`` (bool: the previous torques are kept), ``solution``)."""
        q, v = self.map.q_v(qpos, qvel, R)
        tau_pin, sol = self.solve(t, q, v, ref["com_pos"], ref["com_vel"], ref["com_acc"])
        tau = self.torques(tau_pin, np.asarray(qvel, float)[self.map.mj_dof])
        return tau, {"status": int(sol.status), "infeasible": tau_pin is None, "solution": sol}

    def torques(self, tau_pin: np.ndarray | None, s_dot: np.ndarray) -> np.ndarray:
        """The motor torques (n,), unsaturated, ``DRIVEN_JOINTS`` order, from TSID's tau_pin (n,)
        (Pinocchio's order) plus the joint damping D s_dot (s_dot (n,)); tau_pin None (a failed
        solve): the previous tick's torques."""
        if tau_pin is None:
            return self._tau_prev.copy()
        tau = self.map.joints_from_pin(tau_pin)
        if self.damping is not None:
            tau += self.damping * s_dot
        self._tau_prev = tau.copy()
        return tau

    def violation(self, sol) -> float:
        """Largest violation of the contacts' force inequalities by a solution's corner forces,
        over each sole's normal force (at least fz_min); 0 for a failed solve."""
        if sol.status != 0:
            return 0.0
        worst = 0.0
        for contact, (B, lb, ub) in zip(self.contacts, self._force_rows):
            f = np.asarray(self.formulation.getContactForce(contact.name, sol), float)
            Bf = B @ f
            v = max(float(np.max(Bf - ub)), float(np.max(lb - Bf)), 0.0)
            fz = max(float(np.sum(f[2::3])), self.config.fz_min)
            worst = max(worst, v / fz)
        return worst


# --------------------------------------------------------------------------------------
# Closed loop
# --------------------------------------------------------------------------------------


class TsidPeer:
    """The robot loaded once for many closed loops: the MuJoCo model (no auto-reset), the reduced
    Pinocchio model, their :class:`StateMap`, the home state and its references.

    Args: mj_model: None: :func:`load_mj_model`. pin_model: None: :func:`pinocchio_model`.
    """

    def __init__(self, mj_model: mujoco.MjModel | None = None, pin_model=None):
        self.mj_model = bc.solver_model(load_mj_model() if mj_model is None else mj_model)
        self.pin_model = pinocchio_model() if pin_model is None else pin_model
        self.map = StateMap(self.mj_model, self.pin_model)
        m = self.mj_model
        self.qpos0 = m.key("home").qpos.copy()
        self.foot_sites = np.array([m.site(s).id for s in FEET])
        self.non_foot_bodies = non_foot_bodies(m)
        self.control_dt = constants.CONTROL_DT
        self.physics_dt = float(m.opt.timestep)
        self.n_sub = int(round(self.control_dt / self.physics_dt))
        if abs(self.n_sub * self.physics_dt - self.control_dt) > 1e-9:
            raise ValueError(
                f"control period {self.control_dt} s is not a multiple of the timestep {self.physics_dt} s"
            )
        d = mujoco.MjData(m)
        d.qpos[:] = self.qpos0
        mujoco.mj_forward(m, d)
        self.com0 = d.subtree_com[self.map.base_body].copy()
        self.s0 = self.qpos0[self.map.mj_qpos].copy()
        self.mass = float(m.body_subtreemass[self.map.base_body])

    def schedule(self, task: str = "stand", duration: float | None = None) -> TaskSchedule:
        """The task's references from the home state (:func:`make_schedule`)."""
        return make_schedule(task, self.com0, self.s0, duration)

    def simulate(
        self,
        task: str = "stand",
        *,
        duration: float | None = None,
        push=None,
        push_body: str = "chest",
        config: TsidConfig | None = None,
        record: bool = True,
        timing: bool = False,
    ) -> dict:
        """One closed loop from the home state (as :func:`baseline_cpu.simulate` with one environment).

        Args:
          task: ``stand`` or ``sinusoid``; duration: seconds (None: the task's default).
          push: force (P, 3) N or (3,), onset, duration (P,) s (a dict; ``baseline_cpu.push_to_numpy``)
            on ``push_body``'s CoM, world axes; None: no push.
          config: :class:`TsidConfig` (None: the defaults). record: keep the CoM and torques per tick.
          timing: time the controller (state map; TSID problem data + solve + torques) and the physics
            (mj_step1 + mj_step2 + the tick's other mj_step): wall clock (perf_counter) and this
            thread's CPU time (thread_time: what a shared machine's other load does not add).

        Returns:
          dict: ``t`` (T,), ``com_ref`` (T, 3), ``metrics`` (``baseline_cpu.LoopMetrics.metrics``,
          (1,) arrays), ``summary`` (``baseline_cpu.summarize``: the ``constants.METRIC_NAMES``
          values; time to recover counted from the push's end), ``n_ticks``; with ``record``: ``com``
          (T, 3), ``tau`` (T, n), ``status`` (T,); with ``timing``: ``timing`` (seconds and
          microseconds per tick of each part).
        """
        m, smap = self.mj_model, self.map
        pb = _body_id(m, push_body)
        sched = self.schedule(task, duration)
        T = int(round(sched.duration / self.control_dt))
        ref = bc.schedule_table(sched, np.arange(T) * self.control_dt)
        pu = bc.push_to_numpy(push, 1)
        ctrl = TsidController(self.pin_model, smap, m, self.qpos0, sched.s0, config)
        d = mujoco.MjData(m)
        d.qpos[:] = self.qpos0
        d.qvel[:] = 0.0
        mujoco.mj_forward(m, d)
        sites, base, nfb = self.foot_sites, smap.base_body, self.non_foot_bodies
        # The metrics' support rectangle is the project's (FOOT_SIZE), whatever the contact points.
        W_R_feet0 = d.site_xmat[sites].reshape(1, 2, 3, 3).copy()
        tracker = bc.LoopMetrics(FOOT_SIZE, d.site_xpos[sites][None].copy(), W_R_feet0, d.subtree_com[base, 2:3].copy())
        rec = {"com": np.zeros((T, 3)), "tau": np.zeros((T, len(smap.joints))), "status": np.zeros(T, int)}
        wall, cpu = time.perf_counter, time.thread_time
        t_map, t_tsid, t_phys = [0.0, 0.0], [0.0, 0.0], [0.0, 0.0]  # (wall, this thread's CPU) seconds
        sub_times = np.arange(self.n_sub) * self.physics_dt
        F_cur = np.zeros(3)
        limit = m.actuator_ctrlrange[smap.actuators]
        n_sub, dt = self.n_sub, self.physics_dt
        for k in range(T):
            t_now = k * self.control_dt
            saved = (d.qpos.copy(), d.qvel.copy(), d.qacc_warmstart.copy(), d.time)
            F_all = bc._push_force(pu, (t_now + sub_times)[:, None, None], dt)[:, 0]  # (n_sub, 3)
            c0 = (wall(), cpu())
            mujoco.mj_step1(m, d)
            c1 = (wall(), cpu())
            q, v = smap.q_v(d.qpos, d.qvel, d.xmat[base].reshape(3, 3))
            c2 = (wall(), cpu())
            tau_pin, sol = ctrl.solve(t_now, q, v, ref["com_pos"][k], ref["com_vel"][k], ref["com_acc"][k])
            infeasible = tau_pin is None
            tau = np.clip(ctrl.torques(tau_pin, d.qvel[smap.mj_dof]), limit[:, 0], limit[:, 1])
            c4 = (wall(), cpu())
            # The tick's state for the metrics (after mj_step1: kinematics and CoM at it).
            mujoco.mj_subtreeVel(m, d)
            com, com_vel = d.subtree_com[base].copy(), d.subtree_linvel[base].copy()
            W_p_feet, W_R_feet = d.site_xpos[sites].copy(), d.site_xmat[sites].reshape(2, 3, 3).copy()
            body_low = bool(d.xpos[nfb, 2].min() < constants.BODY_FLOOR_HEIGHT)
            body_low |= not d.xmat[base, 8] >= np.cos(np.radians(constants.FALL_TRUNK_TILT_DEG))  # the trunk tipped
            violation = ctrl.violation(sol)
            c5 = (wall(), cpu())
            for j in range(n_sub):
                if np.any(F_all[j] != F_cur):
                    d.xfrc_applied[pb, :3] = F_cur = F_all[j]
                if j == 0:
                    d.ctrl[smap.actuators] = tau
                    mujoco.mj_step2(m, d)
                else:
                    mujoco.mj_step(m, d)
            c6 = (wall(), cpu())
            for j in (0, 1):
                t_phys[j] += (c1[j] - c0[j]) + (c6[j] - c5[j])
                t_map[j] += c2[j] - c1[j]
                t_tsid[j] += c4[j] - c2[j]
            qpos_, qvel_, warm, time_ = saved
            finite = (
                abs(d.time - (time_ + n_sub * dt)) < 0.5 * dt
                and np.isfinite(d.qpos).all()
                and np.isfinite(d.qvel).all()
            )
            if not finite:  # freeze at the tick's start, as baseline_cpu.simulate
                d.qpos[:], d.qvel[:], d.qacc_warmstart[:], d.time = qpos_, qvel_, warm, time_
            tracker.update(
                t_now, ref["com_pos"][k], ref["activation"][k], com[None], com_vel[None], W_p_feet[None],
                W_R_feet[None], tau[None], np.array([violation]), np.array([infeasible]), np.array([finite]),
                np.array([body_low]),
            )  # fmt: skip
            if record:
                rec["com"][k], rec["tau"][k], rec["status"][k] = com, tau, sol.status
        push_end = float(np.max(pu["onset"] + pu["duration"])) if push is not None else 0.0
        out = {
            "t": np.arange(T) * self.control_dt,
            "com_ref": ref["com_pos"],
            "metrics": tracker.metrics,
            "summary": bc.summarize(tracker.metrics, push_end)[0],
            "n_ticks": T,
        }
        if record:
            out.update(rec)
        if timing:
            out["timing"] = {"ticks": T}
            for j, kind in enumerate(("", "cpu_")):  # wall clock; CPU time of this thread
                out["timing"].update({
                    f"state_map_{kind}s": t_map[j], f"tsid_{kind}s": t_tsid[j], f"physics_{kind}s": t_phys[j],
                    f"state_map_{kind}us_per_tick": 1e6 * t_map[j] / T,
                    f"tsid_{kind}us_per_tick": 1e6 * t_tsid[j] / T,
                    f"controller_{kind}us_per_tick": 1e6 * (t_map[j] + t_tsid[j]) / T,
                    f"physics_{kind}us_per_tick": 1e6 * t_phys[j] / T,
                    f"physics_{kind}us_per_mj_step": 1e6 * t_phys[j] / (T * n_sub),
                })  # fmt: skip
        return out


def simulate(task: str = "stand", **kwargs: Any) -> dict:
    """:meth:`TsidPeer.simulate` on a freshly loaded robot (for one run; load a :class:`TsidPeer`
    once for many)."""
    return TsidPeer().simulate(task, **kwargs)
