"""The TSID balancing controller (:class:`TsidController`) and its settings (:class:`TsidConfig`)."""

from __future__ import annotations

import dataclasses
import math

import mujoco
import numpy as np

from wbc_jax.robot.description import RobotDescription
from wbc_jax.robot.pinocchio import StateMap
from wbc_jax.robot.robots import DEFAULT_ROBOT, describe

from .model import FZ_MAX, FZ_MIN, floor_friction, import_tsid


@dataclasses.dataclass(frozen=True)
class TsidConfig:
    """Weights and gains of the TSID controller (module docstring: what corresponds to the WBC).

    Attributes:
      w_com, w_am, w_posture, w_force_reg: level-1 weights of the CoM, angular-momentum, posture
        tasks and the contacts' force regularisation.
      kp_com, kd_com (3,): CoM task PD (1/s^2, 1/s); None: the WBC's K_P,CoM, K_D,CoM.
      kp_am (3,): angular-momentum task gain (1/s); None: the WBC's K_P,w.
      kp_posture (n,): posture PD stiffness (1/s^2, the controlled joints' order); None: the WBC's
        postural k_p values. kd_posture (n,): None: 2 sqrt(kp_posture) (critical damping).
      contact_kp: PD gain of the soles' motion constraints (Kd = 2 sqrt(Kp)); 0: rigid contact.
      mu: friction coefficient of the corners' pyramids; None: the model's floor friction.
      fz_min, fz_max: bounds of each sole's normal force (N). foot_size: the CoP rectangle
        ((x_min, x_max), (y_min, y_max)) m in the sole frame, its corners the contact points;
        None: the robot's (its description's ``sole_cop``, the WBC's).
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
    foot_size: tuple | None = None
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
        if self.foot_size is not None:
            (x0, x1), (y0, y1) = self.foot_size
            if not (x0 < x1 and y0 < y1):
                raise ValueError(f"TsidConfig.foot_size needs x_min < x_max and y_min < y_max, got {self.foot_size}")

    def gains(self, robot: RobotDescription, n: int | None = None) -> dict[str, np.ndarray]:
        """The resolved gains (float64) on ``robot`` (None fields: its WBC defaults): kp_com, kd_com,
        kp_am (3,), kp_posture, kd_posture (n,), in its joints' order. Raises ValueError on a wrong
        shape or a negative gain (``n``: the joint count the caller expects)."""
        n = len(robot.joints) if n is None else n
        wbc = robot.default_gain_values(n)
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

    def sole_rectangle(self, robot: RobotDescription) -> tuple:
        """The CoP rectangle ((x_min, x_max), (y_min, y_max)) m on ``robot``: ``foot_size`` or its own."""
        return robot.sole_cop if self.foot_size is None else self.foot_size

    def corners(self, robot: RobotDescription) -> np.ndarray:
        """The contact points (3, 4): the CoP rectangle's corners on the sole plane (sole frame)."""
        (x0, x1), (y0, y1) = self.sole_rectangle(robot)
        return np.array([[x, y, 0.0] for x in (x0, x1) for y in (y0, y1)]).T


class TsidController:
    """TSID's balancing controller for a robot's controlled joints (module docstring), built at a state.

    Usage: ``tau, info = ctrl(t, qpos, qvel, ref)`` once per control tick with MuJoCo's state.

    Args:
      pin_model: :func:`pinocchio_model`. state_map: :class:`StateMap` of it and the MuJoCo model.
      mj_model: the MuJoCo model (floor friction, joint damping).
      qpos0 (nq,): MuJoCo state at which the soles' contact references are taken (zero velocity).
      s_des (n,): the posture reference (the joints' order). config: :class:`TsidConfig`.
      robot: the robot's name (its description: default gains, CoP rectangle, sole frames).
    """

    def __init__(
        self,
        pin_model,
        state_map: StateMap,
        mj_model: mujoco.MjModel,
        qpos0: np.ndarray,
        s_des: np.ndarray,
        config: TsidConfig | None = None,
        robot: str = DEFAULT_ROBOT,
    ):
        tsid = import_tsid()
        self.tsid = tsid
        self.config = cfg = TsidConfig() if config is None else config
        self.description = desc = describe(robot)
        self.map = state_map
        n = len(state_map.joints)
        g = cfg.gains(desc, n)
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
        points, normal = cfg.corners(desc), np.array([0.0, 0.0, 1.0])
        self.contacts = []
        for frame in desc.pinocchio_feet:
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
        """Posture reference s_des (n,) (the controlled joints' order), zero velocity and acceleration."""
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
        Returns (tau (n,) unsaturated, the controlled joints' order; info dict: ``status`` (eiquadprog's,
        0 = solved), ``infeasible`` (bool: the previous torques are kept), ``solution``)."""
        q, v = self.map.q_v(qpos, qvel, R)
        tau_pin, sol = self.solve(t, q, v, ref["com_pos"], ref["com_vel"], ref["com_acc"])
        tau = self.torques(tau_pin, np.asarray(qvel, float)[self.map.mj_dof])
        return tau, {"status": int(sol.status), "infeasible": tau_pin is None, "solution": sol}

    def torques(self, tau_pin: np.ndarray | None, s_dot: np.ndarray) -> np.ndarray:
        """The motor torques (n,), unsaturated, the controlled joints' order, from TSID's tau_pin (n,)
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
