"""The balancing controller of the seed paper: momentum task first, postural task in
its null space, any motion tasks in between.

One control tick (seed paper; robotology whole-body-controllers) reads like the pipeline::

    dynamics terms -> contact terms -> L_dot* (momentum task) -> contact wrenches f (QP or analytic)
                   -> tau = Sigma f + tau_model (torques, postural task in the null space)
                   -> motion tasks in recursive null spaces (hierarchy), saturation

Built from one :class:`ControllerConfig` by :func:`make_controller`, in the optax / MuJoCo
Playground manner: ``controller.init(t_ref) -> state`` and
``controller.step(gains, state, t, ref, time) -> (output, state)``, both pure (jit, vmap, grad).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax.control import constraints, forces, hierarchy, momentum, qp, task_rows, torques
from wbc_jax.control import tasks as tasks_lib
from wbc_jax.control.gains import Gains
from wbc_jax.control.references import Reference
from wbc_jax.core.constants import min_jerk
from wbc_jax.core.types import Array, pytree_dataclass
from wbc_jax.robot import contacts as contacts_lib
from wbc_jax.robot.dynamics import DynamicsTerms, Frames
from wbc_jax.robot.model import Robot

FORCE_MODES = forces.FORCE_MODES


@dataclasses.dataclass(frozen=True)
class ControllerConfig:
    """Every setting of the controller (hashable; closed over by jit).

    Attributes:
      forces: ``"qp"`` (friction cone, torsion, unilateral, CoP constraints) or ``"analytic"``
        (the seed paper's C++: minimum torque norm, no inequality constraints).
      postural: ``"stable"`` (Nava 2016, default) or ``"seed"``.
      pinv_damping: damping of Lambda^+ (WBC Reg.pinvDamp = 1 in simulation).
      pinv_tol: absolute tolerance of the pseudo-inverses (Reg.pinvTol).
      kp_postural_reg: Reg.KP_postural. hessian_reg: Reg.HessianQP.
      base_vel_damping: Reg.pinvDamp_baseVel (angular-momentum integral).
      torque_limit: saturation (N m); None: each joint's motor limit in the robot's model (the
        actuators' ctrlrange, ``torque_limit`` of :class:`~wbc_jax.robot.model.RobotIndex`). qp_iterations: at most this many interior-point steps.
      qp_warm_start: start the force QP's interior point from the last tick's multipliers and
        slacks (4 Newton steps a tick instead of 6 in the sinusoid; after a push the batch's
        slowest QP 10 instead of 14), stopping at the warm start's own float32 tolerance
        (:data:`wbc_jax.control.qp.WARM_START_TOL_FLOAT32`): at the cold start's 2e-6 the one-foot
        acceptance scenario (which falls) amplified the different stopping points to 8.9 % in its
        end CoM speed, at 5e-7 0.03 % (BENCHMARKS.md, qpmax46). Off by default.
      qp_tol: the force QPs' relative KKT tolerance (None: :func:`wbc_jax.control.qp.default_tolerances`
        of the precision, 2e-6 in float32).
      qp_unrolled_steps: the force QPs' first Newton steps written out before their while loop (0 to
        qp_iterations; the same solutions): on a GPU each pass of the loop waits for its predicate on the
        host (BENCHMARKS.md, issue 46). 0 by default.
      qp_engine: the force QPs' solver, :data:`wbc_jax.control.qp.QP_ENGINES`, or ``"auto"`` (default: the dual
        active-set method, as one Warp kernel on a GPU with warp-lang or by eiquadprog in a CPU program where it
        builds, else the interior point; :func:`wbc_jax.control.qp.resolve_engine`, resolved when the config is made):
        ``"jax"`` (the interior point), ``"warp"`` (it as one Warp kernel, :mod:`wbc_jax.control.qp_warp`) or
        ``"warp_active_set"`` (the dual active-set method as one Warp kernel: the exact solution, no warm start) or
        ``"eiquadprog"`` (the same method by eiquadprog in C++, CPU programs, :mod:`wbc_jax.control.qp_eiquadprog`).
        The Warp engines need warp-lang; every engine but ``"jax"`` takes qp_unrolled_steps 0.
      mass_solve_engine: who factorises the mass matrix and solves with it in the torque law,
        :data:`wbc_jax.control.torques.MASS_SOLVE_ENGINES`: ``"jax"`` or ``"warp"`` (one Warp tile kernel, a block
        per environment, :mod:`wbc_jax.control.cholesky_warp`; needs warp-lang; derivatives by JAX's solve), or
        ``"auto"`` (default: ``"warp"`` on a GPU with warp-lang, else ``"jax"``; resolved when the config is made).
      ritz_engine: who computes the ``stable`` postural projector's Ritz decomposition,
        :data:`wbc_jax.control.torques.RITZ_ENGINES`: ``"jax"`` (default: QR and ``eigh``) or ``"warp"`` (one Warp
        kernel, a thread per environment, :mod:`wbc_jax.control.ritz_warp`; needs warp-lang; certified alike).
      torque_weight_soft: |tau|^2 against |A f - w|^2 in the soft momentum QP.
      angular_weight_soft: the angular rows of |A f - w|^2 against the linear ones in the soft
        momentum QP (1: WBC; < 1: the CoM first where a push asks more than the feet can give).
      normal_force_weight: desired normal forces against the torques in the force QP.
      freeze_postural_projector: hold the postural projector constant in derivatives (the earlier,
        inexact gradient; kept for comparison: results/tuning/grad_check_sources.json).
      solution_damping, projector_reg: of the motion-task hierarchy (None: by precision,
        :data:`wbc_jax.control.hierarchy.SOLUTION_DAMPING` / :data:`wbc_jax.control.hierarchy.PROJECTOR_REG`).
      effort_damping: mu >= 0 of the hierarchy's effort-bounded pseudo-inverses
        (:mod:`wbc_jax.control.hierarchy`): a task direction that the levels above block to a fraction rho
        of its gain gets rho^4 / (rho^4 + mu (1 - rho^2)^2) of its acceleration, the postural task
        keeps the rest; 0: plain hierarchical least squares.
      compensate_passive: include the model's joint damping in the bias h.
      violation_tol: the largest violation of a contact's own constraints, relative to its normal
        force, that the force QP's wrenches may have before the soft QP is used instead (None: by
        precision, :data:`wbc_jax.control.constraints.VIOLATION_TOL`).
      contact_detection: contact detection on every contact but the soles (``Contact.detect``: on
        one contact; :func:`make_controller` sets this when a contact of the set detects, so that
        the rollout measures the contact forces): the measured normal force gates the contact's
        activation. A contact the simulator does not see (normal force below
        ``detection_threshold`` x its fz_min) ramps out in ``detection_ramp_out`` s; once seen again
        it ramps back in over ``detection_ramp_in`` s (a minimum-jerk gate, rate-limited per tick).
    """

    forces: str = "qp"
    postural: str = "stable"
    pinv_damping: float = 1.0
    pinv_tol: float = 1e-5
    kp_postural_reg: float = 0.1
    hessian_reg: float = 1e-7
    base_vel_damping: float = 1e-7
    torque_limit: float | None = None
    qp_iterations: int = qp.DEFAULT_ITERATIONS
    qp_warm_start: bool = False
    qp_tol: float | None = None
    qp_unrolled_steps: int = 0
    qp_engine: str = "auto"
    mass_solve_engine: str = "auto"
    ritz_engine: str = "jax"
    torque_weight_soft: float = 1e-4
    angular_weight_soft: float = 1.0
    normal_force_weight: float = 1e3
    freeze_postural_projector: bool = False
    solution_damping: float | None = None
    projector_reg: float | None = None
    effort_damping: float = 1.0
    compensate_passive: bool = True
    violation_tol: float | None = None
    contact_detection: bool = False
    detection_threshold: float = 0.1
    detection_ramp_out: float = 0.02
    detection_ramp_in: float = 0.3

    def saturation(self, index) -> np.ndarray | float:
        """The torque saturation (N m): ``torque_limit``, else per joint (n,) the motors' limits of
        the robot ``index`` (:class:`~wbc_jax.robot.model.RobotIndex`)."""
        return np.asarray(index.torque_limit, float) if self.torque_limit is None else self.torque_limit

    def __post_init__(self):
        if self.qp_engine == "auto":  # the engine it names on this machine, recorded as such (qp.resolve_engine)
            object.__setattr__(
                self, "qp_engine", qp.resolve_engine("auto", self.qp_warm_start is True, self.qp_unrolled_steps)
            )
        if self.mass_solve_engine == "auto":  # likewise (torques.resolve_mass_solve_engine)
            object.__setattr__(self, "mass_solve_engine", torques.resolve_mass_solve_engine("auto"))
        if self.forces not in FORCE_MODES:
            raise ValueError(f"unknown forces mode {self.forces!r}; valid: {list(FORCE_MODES)}")
        if self.postural not in torques.POSTURAL_VARIANTS:
            raise ValueError(f"unknown postural variant {self.postural!r}; valid: {list(torques.POSTURAL_VARIANTS)}")
        positive = (
            "pinv_damping",
            "pinv_tol",
            "hessian_reg",
            "base_vel_damping",
            "torque_limit",
            "torque_weight_soft",
            "angular_weight_soft",
            "normal_force_weight",
            "detection_threshold",
            "detection_ramp_out",
            "detection_ramp_in",
        )
        for name in positive:
            value = getattr(self, name)
            if name == "torque_limit" and value is None:  # the robot's motor limits
                continue
            if (
                isinstance(value, bool)
                or not isinstance(value, (int, float))
                or not (math.isfinite(value) and value > 0)
            ):
                raise ValueError(f"controller setting {name} must be positive and finite, got {value!r}")
        if not (
            isinstance(self.kp_postural_reg, (int, float))
            and math.isfinite(self.kp_postural_reg)
            and self.kp_postural_reg >= 0
        ):
            raise ValueError(f"controller setting kp_postural_reg must be >= 0, got {self.kp_postural_reg!r}")
        if not isinstance(self.qp_warm_start, bool):
            raise ValueError(f"controller setting qp_warm_start must be True or False, got {self.qp_warm_start!r}")
        if isinstance(self.qp_iterations, bool) or not isinstance(self.qp_iterations, int) or self.qp_iterations < 1:
            raise ValueError(f"controller setting qp_iterations must be an integer >= 1, got {self.qp_iterations!r}")
        steps = self.qp_unrolled_steps
        if isinstance(steps, bool) or not isinstance(steps, int) or not 0 <= steps <= self.qp_iterations:
            raise ValueError(
                f"controller setting qp_unrolled_steps must be an integer from 0 to qp_iterations "
                f"({self.qp_iterations}), got {steps!r}"
            )
        if self.qp_engine not in qp.QP_ENGINES:
            raise ValueError(f"unknown controller setting qp_engine {self.qp_engine!r}; valid: {list(qp.QP_ENGINES)}")
        if self.qp_engine != "jax" and steps:
            raise ValueError(
                f"controller setting qp_engine {self.qp_engine!r} takes qp_unrolled_steps 0 ("
                f"{'the Warp kernel' if self.qp_engine in qp.WARP_ENGINES else 'eiquadprog'} has no while loop to "
                f"unroll), got {steps!r}"
            )
        if self.mass_solve_engine not in torques.MASS_SOLVE_ENGINES:
            raise ValueError(
                f"unknown controller setting mass_solve_engine {self.mass_solve_engine!r}; "
                f"valid: {list(torques.MASS_SOLVE_CHOICES)}"
            )
        if self.ritz_engine not in torques.RITZ_ENGINES:
            raise ValueError(
                f"unknown controller setting ritz_engine {self.ritz_engine!r}; valid: {list(torques.RITZ_ENGINES)}"
            )
        if self.qp_engine in qp.ACTIVE_SET_ENGINES and self.qp_warm_start:
            raise ValueError(
                f"controller setting qp_engine {self.qp_engine!r} takes qp_warm_start False (the active-set method "
                "starts from the unconstrained minimiser); warm starts: qp_engine 'jax' or 'warp'"
            )
        if isinstance(self.effort_damping, bool) or not (
            isinstance(self.effort_damping, (int, float)) and 0.0 <= self.effort_damping < math.inf
        ):
            raise ValueError(f"controller setting effort_damping must be >= 0 and finite, got {self.effort_damping!r}")
        for name in ("solution_damping", "projector_reg", "violation_tol", "qp_tol"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value > 0):
                raise ValueError(f"controller setting {name} must be positive or None, got {value!r}")

    @property
    def force_settings(self) -> forces.ForceSettings:
        return forces.ForceSettings(
            mode=self.forces,
            hessian_reg=self.hessian_reg,
            qp_iterations=self.qp_iterations,
            warm_start=self.qp_warm_start,
            qp_tol=self.qp_tol,
            qp_unrolled_steps=self.qp_unrolled_steps,
            qp_engine=self.qp_engine,
            torque_weight_soft=self.torque_weight_soft,
            angular_weight_soft=self.angular_weight_soft,
            normal_force_weight=self.normal_force_weight,
            violation_tol=self.violation_tol,
        )


@pytree_dataclass
class ControllerState:
    """Controller memory and the arrays fixed for a run.

    Attributes:
      com_err_integral: (3,) integral of the CoM error (used only when ki_com > 0).
      centroidal_jacobian_ref: (2, 3, n) J_G,ang at the postural reference, left/right stance.
      pinv_damping, kp_postural_reg: () Reg.pinvDamp and Reg.KP_postural as arrays, so that
        gradients reach them (gain tuning's gradient check).
      contact_gate: (K,) contact detection's gate of each contact in [0, 1] (1: seen; its
        activation is multiplied by mj(gate), mj the minimum-jerk ramp); 1 for contacts without
        detection.
      qp_start: (2, M) multipliers and slacks of the last tick's force QP (the engaged contacts'
        equality QP), its warm start in this tick (NaN: a cold start; :func:`forces.distribute`).
    """

    com_err_integral: Array
    centroidal_jacobian_ref: Array
    pinv_damping: Array
    kp_postural_reg: Array
    contact_gate: Array
    qp_start: Array


@pytree_dataclass
class ControlOutput:
    """Per-tick outputs and diagnostics (K contacts, D contact wrench rows, m motion-task rows).

    Attributes:
      tau: (n,) saturated joint torques;  tau_unsat: (n,) before saturation
      f: (D,) commanded contact wrenches, world axes at the contact points
      Ldot_star: (6,) desired momentum rate;  Ldot_cmd: (6,) A f + f_grav
      qp_infeasible: () bool (a formulation in use had no feasible solution)
      qp_violation: () max constraint violation of the commanded f, relative to each contact's
        normal force (>= 0)
      activation: (K,) contact activations;  contact_pos: (K, 3);  contact_R: (K, 3, 3)
      task_err: (m,) the motion tasks' errors in stack order
    """

    tau: Array
    tau_unsat: Array
    f: Array
    Ldot_star: Array
    Ldot_cmd: Array
    qp_infeasible: Array
    qp_violation: Array
    activation: Array
    contact_pos: Array
    contact_R: Array
    task_err: Array


class Controller(NamedTuple):
    """A controller built by :func:`make_controller`.

    Attributes:
      frames: the points whose kinematics ``step`` reads from the dynamics terms (contacts first,
        then the motion tasks'): pass them to :func:`wbc_jax.robot.dynamics.terms`.
      init: ``init(t_ref) -> ControllerState``, at the postural reference (the initial state).
      step: ``step(gains, state, t, ref, time, measured=None) -> (ControlOutput, ControllerState)``;
        ``measured``: (K,) the normal force the simulator applied at each contact in the last physics
        step (contact detection), None: not measured.
      config, contact_set, stack: what it was built from.
    """

    frames: Frames
    init: Callable[[DynamicsTerms], ControllerState]
    step: Callable[..., tuple[ControlOutput, ControllerState]]
    config: ControllerConfig
    contact_set: contacts_lib.ContactSet
    stack: tasks_lib.TaskStack | None


def make_controller(
    robot: Robot,
    config: ControllerConfig | None = None,
    *,
    contact_set: contacts_lib.ContactSet | None = None,
    stack: tasks_lib.TaskStack | None = None,
    control_dt: float = 0.01,
) -> Controller:
    """Build the controller of one robot.

    Args:
      robot: the robot (mass, joints).
      config: settings (default :class:`ControllerConfig`).
      contact_set: the contacts (default: the two soles, :func:`wbc_jax.robot.contacts.feet_contact_set`).
      stack: motion tasks between the force task and the postural task, resolved
        (:func:`wbc_jax.control.tasks.resolve`); None: the two-level law of the seed.
      control_dt: the control period (s), for the CoM error integral.
    """
    config = ControllerConfig() if config is None else config
    cset = contacts_lib.feet_contact_set(robot) if contact_set is None else contact_set
    # Contacts whose activation the measured contact state gates (never the soles).
    detect = np.array([c.foot < 0 and (c.detect or config.contact_detection) for c in cset.contacts])
    if detect.any() and not config.contact_detection:
        config = dataclasses.replace(config, contact_detection=True)  # the rollout measures the forces
    seen_force = config.detection_threshold * np.array([c.params.fz_min for c in cset.contacts])
    stack = stack if stack is not None and stack.tasks else None
    frames = cset.frames if stack is None else cset.frames + stack.frames
    frame0 = len(cset.contacts)
    mass = robot.index.mass
    saturation = config.saturation(robot.index)
    settings = config.force_settings
    feet = cset.feet

    def init(t_ref: DynamicsTerms) -> ControllerState:
        dtype = t_ref.M.dtype
        J = jnp.stack([momentum.centroidal_jacobian_at_posture(t_ref, k, config.base_vel_damping) for k in feet])
        return ControllerState(
            com_err_integral=jnp.zeros(3, dtype),
            centroidal_jacobian_ref=J,
            pinv_damping=jnp.asarray(config.pinv_damping, dtype),
            kp_postural_reg=jnp.asarray(config.kp_postural_reg, dtype),
            contact_gate=jnp.ones(len(cset.contacts), dtype),
            qp_start=forces.cold_start(cset, dtype),
        )

    def detection(gate: Array, measured) -> Array:
        """The gates (K,) after one tick: up by dt / ramp_in where the measured normal force
        (K,) shows the contact, down by dt / ramp_out where it does not."""
        if measured is None or not detect.any():
            return gate
        seen = jnp.asarray(measured, gate.dtype) > jnp.asarray(seen_force, gate.dtype)
        rate = jnp.where(seen, control_dt / config.detection_ramp_in, -control_dt / config.detection_ramp_out)
        return jnp.where(detect, jnp.clip(gate + rate, 0.0, 1.0), 1.0)

    def step(gains: Gains, state: ControllerState, t: DynamicsTerms, ref: Reference, time: Array, measured=None):
        dtype = t.M.dtype
        f_grav = constraints.gravity_wrench(mass, dtype)
        cterms = contacts_lib.contact_terms(cset, t, time, jnp.clip(ref.activation, 0.0, 1.0))
        gate = detection(state.contact_gate, measured)
        act = cterms.activation * jnp.where(detect, min_jerk(gate)[0], 1.0) if detect.any() else cterms.activation

        # Momentum task. The angular-momentum integral is linearised about the postural
        # reference, with the foot that carries more of the weight as the fixed one.
        stance = jnp.argmax(jnp.stack([act[feet[0]], act[feet[1]]]))
        ang_integral = state.centroidal_jacobian_ref[stance] @ (t.s - ref.s_des)
        com_err_integral = state.com_err_integral + control_dt * (t.W_p_CoM - ref.com_pos)
        Ldot_star = momentum.momentum_rate_reference(
            mass=mass,
            W_p_CoM=t.W_p_CoM,
            W_v_CoM=t.W_v_CoM,
            L_ang=t.L_G[3:],
            com_pos_des=ref.com_pos,
            com_vel_des=ref.com_vel,
            com_acc_des=ref.com_acc,
            com_err_integral=com_err_integral,
            ang_integral=ang_integral,
            kp_com=gains.kp_com,
            kd_com=gains.kd_com,
            ki_com=gains.ki_com,
            kp_ang=gains.kp_ang,
            ki_ang=gains.ki_ang,
        )
        wrench_des = Ldot_star - f_grav

        # Torque law, affine in f, with each contact's rows scaled by its activation.
        rows = contacts_lib.row_activation(cset, act)
        with jax.named_scope("torque_law"):
            tt = torques.torque_terms(
                t,
                cterms.J * rows[:, None],
                cterms.Jdot_nu * rows,
                postural=config.postural,
                kp_postural=gains.kp_postural,
                kd_postural=gains.kd_postural,
                s_des=ref.s_des,
                pinv_damping=state.pinv_damping,
                pinv_tol=config.pinv_tol,
                kp_postural_reg=state.kp_postural_reg,
                compensate_passive=config.compensate_passive,
                freeze_projector=config.freeze_postural_projector,
                mass_solve_engine=config.mass_solve_engine,
                ritz_engine=config.ritz_engine,
            )

        # Force task: the contact wrenches.
        A = constraints.wrench_map(cset, cterms.W_p, t.W_p_CoM).astype(dtype)
        with jax.named_scope("force_distribution"):
            f, infeasible, qp_start = forces.distribute(
                cset, act, A, wrench_des, tt, cterms.W_R, settings, state.qp_start
            )

        # Motion tasks in the null space of the force task, the postural task last.
        task_err = jnp.zeros(0, dtype)
        if stack is not None:
            levels = task_rows.levels(stack, t, time, frame0)
            task_err = jnp.concatenate(list(task_rows.task_errors(stack, t, time, frame0).values()))
            tau_unsat = hierarchy.solve(
                t,
                tt,
                f,
                levels,
                solution_damping=config.solution_damping,
                projector_reg=config.projector_reg,
                compensate_passive=config.compensate_passive,
                effort_damping=config.effort_damping,
            ).tau
        else:
            tau_unsat = tt.tau_model + tt.Sigma @ f
        out = ControlOutput(
            tau=jnp.clip(tau_unsat, -jnp.asarray(saturation, dtype), jnp.asarray(saturation, dtype)),
            tau_unsat=tau_unsat,
            f=f,
            Ldot_star=Ldot_star,
            Ldot_cmd=A @ f + f_grav,
            qp_infeasible=infeasible,
            qp_violation=constraints.violation(cset, f, cterms.W_R, act),
            activation=act,
            contact_pos=cterms.W_p,
            contact_R=cterms.W_R,
            task_err=task_err,
        )
        return out, state.replace(com_err_integral=com_err_integral, contact_gate=gate, qp_start=qp_start)

    return Controller(frames=frames, init=init, step=step, config=config, contact_set=cset, stack=stack)
