"""What a worker of the CPU baseline needs, NumPy only: the package's constants (loaded by file path),
the task's spec (:class:`BaselineSpec`), its references at the ticks (:func:`schedule_table`) and the C
model with the solver overrides (:func:`solver_model`)."""

from __future__ import annotations

import copy
import dataclasses
import importlib.util
import pathlib
import sys
from typing import Any

import mujoco
import numpy as np


def _load_constants():
    """``wbc_jax/core/constants.py``, loaded by file path.

    The numbers and names shared with the package live there (gravity, gain names and
    defaults, the minimum-jerk ramp, thresholds, metric names). It is loaded from its file, not
    imported as ``wbc_jax.core.constants``: importing that name runs ``wbc_jax/__init__.py``, which
    imports ``mujoco.mjx`` and so JAX (~3 s and ~200 MB in every worker process, and the
    baseline is meant to be JAX-free). constants.py itself imports only numpy."""
    name = "_wbc_jax_constants_by_path"  # its own name: no clash with a normal import
    module = sys.modules.get(name)
    if module is None:
        path = pathlib.Path(__file__).resolve().parents[2] / "wbc_jax" / "core" / "constants.py"
        spec = importlib.util.spec_from_file_location(name, path)
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    return module


constants = _load_constants()
GRAVITY = constants.GRAVITY
GAIN_FIELDS = constants.GAIN_FIELDS
RECOVERY_THRESHOLD = constants.RECOVERY_THRESHOLD
METRIC_NAMES = constants.METRIC_NAMES
min_jerk = constants.min_jerk
# Copies of names of modules that import JAX (wbc_jax.control.forces / wbc_jax.control.torques); checked
# against them in tests/test_baseline_cpu.py.
FORCE_MODES = ("qp", "analytic")
POSTURAL_VARIANTS = ("stable", "seed")
QP_FALLBACK_TOL = 1e-6  # wbc_jax.control.qp.default_tolerances(float64)[1]


@dataclasses.dataclass(frozen=True, eq=False)
class BaselineSpec:
    """Static description of one closed-loop task (same for every environment of a batch).

    Attributes:
      mj_model: C MuJoCo model (solver overrides of the setup's PhysicsConfig applied, no
        auto-reset, as :func:`wbc_jax.sim.physics.solver_mj_model`).
      nq, nv, n: sizes; qpos_joints, dof_joints, actuators (n,), dof_perm (nv,): as RobotIndex.
      base_body: floating-base body; foot_sites, foot_bodies (2,); mass (kg).
      push_body: body the pushes act on; non_foot_bodies: bodies that must stay off the floor.
      forces, postural, pinv_damping, pinv_tol, kp_postural_reg, hessian_reg, torque_limit,
        torque_weight_soft, angular_weight_soft, compensate_passive: as ControllerConfig.
      C_foot (m, 6), b_foot (m,): contact constraints of a sole in its frame
        (:func:`wbc_jax.control.constraints.contact_constraints`); fz_row: the row of ``-f_z <= -fz_min``;
        fz_min (N); foot_size ((x_min, x_max), (y_min, y_max)): the CoP rectangle (m).
      centroidal_jacobian_ref: (2, 3, n) J_G,ang at the reference (left, right stance).
      control_dt, physics_dt, n_sub, n_ticks: as the ClosedLoop / SimConfig.
      qpos0: (nq,) initial configuration (zero velocity).
      ref_*: references at the ticks t_k = k control_dt: com_pos/com_vel/com_acc (T, 3),
        s_des (T, n), activation (T, 2).
    """

    mj_model: Any
    nq: int
    nv: int
    n: int
    qpos_joints: np.ndarray
    dof_joints: np.ndarray
    actuators: np.ndarray
    dof_perm: np.ndarray
    base_body: int
    foot_sites: np.ndarray
    foot_bodies: np.ndarray
    mass: float
    push_body: int
    non_foot_bodies: np.ndarray
    forces: str
    postural: str
    pinv_damping: float
    pinv_tol: float
    kp_postural_reg: float
    hessian_reg: float
    torque_limit: np.ndarray  # (n,) N m, or () where one limit for all
    torque_weight_soft: float
    angular_weight_soft: float
    compensate_passive: bool
    C_foot: np.ndarray
    b_foot: np.ndarray
    fz_row: int
    fz_min: float
    foot_size: tuple
    centroidal_jacobian_ref: np.ndarray
    control_dt: float
    physics_dt: float
    n_sub: int
    n_ticks: int
    qpos0: np.ndarray
    ref_com_pos: np.ndarray
    ref_com_vel: np.ndarray
    ref_com_acc: np.ndarray
    ref_s_des: np.ndarray
    ref_activation: np.ndarray

    def __post_init__(self):
        if self.forces not in FORCE_MODES:
            raise ValueError(f"unknown forces mode {self.forces!r}; valid: {list(FORCE_MODES)}")
        if self.postural not in POSTURAL_VARIANTS:
            raise ValueError(f"unknown postural variant {self.postural!r}; valid: {list(POSTURAL_VARIANTS)}")
        act = np.clip(np.asarray(self.ref_activation, float), 0.0, 1.0)
        engaged, active = act > 0, act >= 1
        ramping = np.any(engaged & ~active, axis=1)
        bad = ~np.any(engaged, axis=1) | (ramping & ~np.any(active, axis=1))
        if np.any(bad):
            # forces.distribute has no formulation for these (its restricted momentum equality
            # has no contact to act on): the baseline does not simulate them.
            k = int(np.flatnonzero(bad)[0])
            raise ValueError(
                f"foot activations {act[k].tolist()} at tick {k}: the force distribution needs a "
                "foot in contact, and a fully active one while the other ramps"
            )

    def reference(self, k: int) -> dict:
        """References at tick k (shared by all environments)."""
        return {
            "com_pos": self.ref_com_pos[k],
            "com_vel": self.ref_com_vel[k],
            "com_acc": self.ref_com_acc[k],
            "s_des": self.ref_s_des[k],
            "activation": self.ref_activation[k],
        }

    def to_dict(self) -> dict:
        """Plain dict (picklable without importing this module)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}


def _segments(t: np.ndarray, x0: np.ndarray, starts, durations, deltas):
    """Sum of minimum-jerk segments at the times t (T,): pos, vel, acc, each (T, d)
    (references.segments for many times at once)."""
    starts, durations = np.asarray(starts, float), np.asarray(durations, float)
    x0 = np.asarray(x0, float)
    T = t.shape[0]
    if len(starts) == 0:
        zero = np.zeros((T,) + x0.shape)
        return np.broadcast_to(x0, (T,) + x0.shape).copy(), zero, zero.copy()
    deltas = np.asarray(deltas, float)
    p, v, a = min_jerk((t[:, None] - starts) / durations)
    return x0 + p @ deltas, (v / durations) @ deltas, (a / durations**2) @ deltas


def schedule_table(schedule, times: np.ndarray) -> dict:
    """Evaluate a :class:`wbc_jax.control.references.Schedule` at the times (T,) in NumPy (float64).

    Returns a dict of com_pos, com_vel, com_acc (T, 3), s_des (T, n), activation (T, 2)."""
    t = np.asarray(times, float)
    com, com_v, com_a = _segments(t, schedule.com0, *schedule.com_segments)
    if schedule.sine_amplitude:
        w = 2 * np.pi * schedule.sine_frequency
        axis = np.asarray(schedule.sine_axis, float)
        amp = schedule.sine_amplitude
        com = com + amp * np.sin(w * t)[:, None] * axis
        com_v = com_v + amp * w * np.cos(w * t)[:, None] * axis
        com_a = com_a - amp * w**2 * np.sin(w * t)[:, None] * axis
    s0 = np.asarray(schedule.s0, float)
    post = schedule.posture_segments
    if post[2] is None:
        s_des = np.broadcast_to(s0, (t.shape[0],) + s0.shape).copy()
    else:
        s_des = _segments(t, s0, *post)[0]
    act = _segments(t, np.ones(2), *schedule.activation_segments)[0]
    return {"com_pos": com, "com_vel": com_v, "com_acc": com_a, "s_des": s_des, "activation": act}


def solver_model(m: mujoco.MjModel, iterations: int | None = None, ls_iterations: int | None = None) -> mujoco.MjModel:
    """A copy of the C model with the solver overrides, never resetting a diverged state on its
    own (as :func:`wbc_jax.sim.physics.solver_mj_model`; the loop restores and flags it)."""
    m = copy.copy(m)
    if iterations is not None:
        m.opt.iterations = int(iterations)
    if ls_iterations is not None:
        m.opt.ls_iterations = int(ls_iterations)
    m.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_AUTORESET
    return m
