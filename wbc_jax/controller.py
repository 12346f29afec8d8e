"""The balancing controller of the seed paper: momentum task first, postural task in its null space.

One control tick (controller-spec 1.10) reads like the pipeline::

    dynamics terms -> L_dot* (momentum task) -> feet wrenches f (QP or analytic)
                   -> tau = Sigma f + tau_model (torques, postural task in the null space)

Contact switching follows the codyco ``torqueBalancing`` module of the seed paper: each foot has
an activation c in [0, 1] (minimum-jerk ramps); the rows of J_c are scaled by c, and the wrench
is the blend f = w f_two_feet + (1 - w) f_one_foot with w = min(c_L, c_R), so the torques stay
continuous while a foot is loaded or unloaded.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax import contact_qp, hierarchy, momentum, torques
from wbc_jax.dynamics import DynamicsTerms
from wbc_jax.types import Array, pytree_dataclass

FORCE_MODES = ("qp", "analytic")

# WBC iCubGazeboV2_5, state 1 "two feet balancing" (gainsAndReferences.m; controller-spec 3.1).
WBC_KP_POSTURAL = (
    [10, 30, 20] + [10, 10, 10, 8] * 2 + [30, 30, 20, 20, 100, 100] + [30, 50, 30, 60, 100, 100]
)


@pytree_dataclass
class Gains:
    """Controller gains: a pytree, so batches of gain sets vmap and gradients flow.

    Attributes (n = 23 joints):
      kp_com, kd_com, ki_com: (3,) CoM PID (ki_com = 0: the WBC law; > 0: the seed's PID)
      kp_ang: (3,) on the angular momentum;  ki_ang: (3,) on its (linearised) integral
      kp_postural, kd_postural: (n,) postural task
    """

    kp_com: Array
    kd_com: Array
    ki_com: Array
    kp_ang: Array
    ki_ang: Array
    kp_postural: Array
    kd_postural: Array


def default_gains(n: int = 23, dtype=jnp.float32) -> Gains:
    """WBC iCubGazeboV2_5 gains: K_P,CoM = [50, 50, 10], K_D,CoM = 2 sqrt(K_P)/20,
    K_I,w = 0.25, K_P,w = 2 sqrt(0.25) = 1, postural k_p per joint, k_d = 2 sqrt(k_p)/20."""
    if n != len(WBC_KP_POSTURAL):
        raise ValueError(f"default gains are for the 23-joint iCub, got n={n}")
    kp_com = np.array([50.0, 50.0, 10.0])
    kp_post = np.array(WBC_KP_POSTURAL, dtype=float)
    as_array = lambda x: jnp.asarray(x, dtype)  # noqa: E731
    return Gains(
        kp_com=as_array(kp_com),
        kd_com=as_array(2 * np.sqrt(kp_com) / 20),
        ki_com=as_array(np.zeros(3)),
        kp_ang=as_array(np.ones(3)),
        ki_ang=as_array(np.full(3, 0.25)),
        kp_postural=as_array(kp_post),
        kd_postural=as_array(2 * np.sqrt(kp_post) / 20),
    )


def validate_gains(gains: Gains, n: int) -> None:
    """Raise ValueError (before any compilation) for wrong shapes, NaN/inf or negative gains."""
    shapes = {"kp_com": 3, "kd_com": 3, "ki_com": 3, "kp_ang": 3, "ki_ang": 3,
              "kp_postural": n, "kd_postural": n}  # fmt: skip
    for name, size in shapes.items():
        value = np.asarray(getattr(gains, name))
        if value.shape[-1:] != (size,):
            raise ValueError(f"gain {name} must have {size} entries (last axis), got {value.shape}")
        if not np.all(np.isfinite(value)):
            raise ValueError(f"gain {name} has NaN or infinite entries: {value}")
        if np.any(value < 0):
            raise ValueError(f"gain {name} has negative entries: {value}")


@dataclasses.dataclass(frozen=True)
class ControllerConfig:
    """Static settings (hashable; closed over by jit).

    Attributes:
      forces: ``"qp"`` (friction cone, torsion, unilateral, CoP constraints) or ``"analytic"``
        (the seed paper's C++: minimum torque norm, no inequality constraints).
      postural: ``"stable"`` (Nava 2016, default) or ``"seed"``.
      pinv_damping: damping of Lambda^+ (WBC Reg.pinvDamp = 1 in simulation).
      pinv_tol: absolute tolerance of the pseudo-inverses (Reg.pinvTol).
      kp_postural_reg: Reg.KP_postural. hessian_reg: Reg.HessianQP.
      base_vel_damping: Reg.pinvDamp_baseVel (angular-momentum integral).
      torque_limit: saturation (N m). contact: QP contact parameters. qp_iterations: Newton steps.
    """

    forces: str = "qp"
    postural: str = "stable"
    pinv_damping: float = 1.0
    pinv_tol: float = 1e-5
    kp_postural_reg: float = 0.1
    hessian_reg: float = 1e-7
    base_vel_damping: float = 1e-7
    torque_limit: float = 60.0
    contact: contact_qp.ContactParams = contact_qp.ContactParams()
    qp_iterations: int = contact_qp.DEFAULT_ITERATIONS

    def __post_init__(self):
        if self.forces not in FORCE_MODES:
            raise ValueError(f"unknown forces mode {self.forces!r}; valid: {list(FORCE_MODES)}")
        if self.postural not in torques.POSTURAL_VARIANTS:
            raise ValueError(
                f"unknown postural variant {self.postural!r}; valid: {list(torques.POSTURAL_VARIANTS)}"
            )
        for name in ("pinv_damping", "pinv_tol", "hessian_reg", "base_vel_damping", "torque_limit"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be positive and finite, got {value}")


@pytree_dataclass
class Reference:
    """References at one tick: com_pos/com_vel/com_acc (3,), s_des (n,), activation (2,)."""

    com_pos: Array
    com_vel: Array
    com_acc: Array
    s_des: Array
    activation: Array


@pytree_dataclass
class ControllerConstants:
    """Arrays fixed for a run.

    Attributes:
      centroidal_jacobian_ref: (2, 3, n) J_G,ang at the postural reference, left/right stance.
      pinv_damping, kp_postural_reg: () the regularisation Reg.pinvDamp and Reg.KP_postural as
        arrays, so that gradients reach them (gain tuning's gradient check); None: the values of
        :class:`ControllerConfig`.
    """

    centroidal_jacobian_ref: Array
    pinv_damping: Array | None = None
    kp_postural_reg: Array | None = None


@pytree_dataclass
class ControllerState:
    """Controller memory: the integral of the CoM error (3,), used only when ki_com > 0."""

    com_err_integral: Array


@pytree_dataclass
class ControlOutput:
    """Per-tick outputs and diagnostics.

    Attributes:
      tau: (n,) saturated joint torques;  tau_unsat: (n,) before saturation
      f: (12,) commanded feet wrenches [f_L; f_R], world axes at the sole origins
      Ldot_star: (6,) desired momentum rate;  Ldot_cmd: (6,) A f + f_grav
      qp_infeasible: () bool (a QP in use fell back to its unconstrained solution)
      qp_violation: () max constraint violation of the commanded f, relative to f_z (>= 0)
    """

    tau: Array
    tau_unsat: Array
    f: Array
    Ldot_star: Array
    Ldot_cmd: Array
    qp_infeasible: Array
    qp_violation: Array


def constants_at_reference(t_ref: DynamicsTerms, config: ControllerConfig) -> ControllerConstants:
    """Precompute J_G,ang (Nava 2016) at the postural reference, for each stance foot."""
    J = jnp.stack(
        [momentum.centroidal_jacobian_at_posture(t_ref, k, config.base_vel_damping) for k in range(2)]
    )
    dtype = t_ref.M.dtype
    return ControllerConstants(
        centroidal_jacobian_ref=J,
        pinv_damping=jnp.asarray(config.pinv_damping, dtype),
        kp_postural_reg=jnp.asarray(config.kp_postural_reg, dtype),
    )


def init_state(dtype=jnp.float32) -> ControllerState:
    return ControllerState(com_err_integral=jnp.zeros(3, dtype))


def constraint_violation(f: Array, W_R_feet: Array, activation: Array, params) -> Array:
    """Max over both feet of max(C f_k - b, 0) / max(f_z, fz_min), for feet with activation > 0.
    The unilateral row is scaled by the activation (a foot being unloaded may go below fz_min)."""
    C_foot, b_foot = contact_qp.foot_constraints(params)
    viol = []
    for k in range(2):
        C, b = contact_qp.world_constraints(C_foot, b_foot, W_R_feet[k])
        b = b.at[_FZ_MIN_ROW].multiply(activation[k])
        f_k = f[6 * k : 6 * k + 6]
        fz = jnp.maximum((W_R_feet[k].T @ f_k[:3])[2], params.fz_min)
        v = jnp.max(jnp.maximum(C @ f_k - b, 0.0)) / fz
        viol.append(jnp.where(activation[k] > 0, v, 0.0))
    return jnp.maximum(viol[0], viol[1])


_FZ_MIN_ROW = 14  # index of the unilateral row -f_z <= -fz_min in foot_constraints


TORQUE_WEIGHT_SOFT = 1e-4  # weight of |tau|^2 against |A f - w|^2 (N^2 vs (N m)^2) in the soft QP


def _two_feet_momentum_qp(A, wrench_des, tt, W_R_feet, config):
    """min 1/2 |A f - w|^2 + (c/2) |tau_model + Sigma f|^2 + (eps/2) |f|^2  s.t. C_2 f <= b_2.

    f (12,) both feet, world axes; C_2 = blkdiag(world constraints of each foot) (38, 12)."""
    C_foot, b_foot = contact_qp.foot_constraints(config.contact)
    Cs, bs = zip(*[contact_qp.world_constraints(C_foot, b_foot, W_R_feet[k]) for k in range(2)])
    zeros = jnp.zeros_like(Cs[0])
    C2 = jnp.block([[Cs[0], zeros], [zeros, Cs[1]]])
    b2 = jnp.concatenate(bs)
    c = TORQUE_WEIGHT_SOFT
    H = A.T @ A + c * tt.Sigma.T @ tt.Sigma + config.hessian_reg * jnp.eye(12, dtype=A.dtype)
    g = -A.T @ wrench_des + c * tt.Sigma.T @ tt.tau_model
    return contact_qp.solve_qp(H, g, C2, b2, iterations=config.qp_iterations)


def _torque_terms(gains, consts, t, ref, config, *, activation=None, contact=None):
    """The affine torque law of this tick: the two feet (``activation``) or a general contact set
    (``contact`` = scaled J_c, Jdot_nu_c); the regularisation from ``consts`` where it is an array."""
    return torques.torque_terms(
        t,
        activation,
        postural=config.postural,
        kp_postural=gains.kp_postural,
        kd_postural=gains.kd_postural,
        s_des=ref.s_des,
        pinv_damping=config.pinv_damping if consts.pinv_damping is None else consts.pinv_damping,
        pinv_tol=config.pinv_tol,
        kp_postural_reg=(
            config.kp_postural_reg if consts.kp_postural_reg is None else consts.kp_postural_reg
        ),
        contact=contact,
    )


def step(
    gains: Gains,
    consts: ControllerConstants,
    state: ControllerState,
    t: DynamicsTerms,
    ref: Reference,
    *,
    config: ControllerConfig,
    mass: float,
    dt: float,
    levels: tuple = (),
    contact_set=None,
    contacts=None,
) -> tuple[ControlOutput, ControllerState]:
    """One control tick: torques (n,) from the dynamics terms and the references.

    Args:
      gains: controller gains (pytree). consts: arrays precomputed at the reference.
      state: controller memory. t: dynamics terms at the current state. ref: references.
      config: static settings. mass: total mass (kg). dt: control period (s).
      levels: motion tasks between the force task and the postural task, highest priority first
        (:class:`wbc_jax.hierarchy.TaskLevel`, from :func:`wbc_jax.tasks.levels`). The force task
        does not see them (strict priority): f is chosen with the two-level torque law.
      contact_set, contacts: a general contact set (:class:`wbc_jax.contacts.ContactSet`, static)
        and its terms at this state (:class:`wbc_jax.contacts.ContactTerms`); None: the two feet
        of the WBC controller. See :func:`contact_set_wrenches`.

    Returns:
      ``(output, new_state)``.
    """
    act = jnp.clip(ref.activation, 0.0, 1.0)
    dtype = t.M.dtype
    f_grav = momentum.gravity_wrench(mass, dtype)

    # Momentum task. The angular-momentum integral is linearised about the postural reference,
    # using the foot that carries more of the weight as the fixed one.
    stance = jnp.argmax(act)
    J_G = consts.centroidal_jacobian_ref[stance]
    ang_integral = J_G @ (t.s - ref.s_des)
    com_err = t.W_p_CoM - ref.com_pos
    new_state = ControllerState(com_err_integral=state.com_err_integral + dt * com_err)
    Ldot_star = momentum.momentum_rate_reference(
        mass=mass,
        W_p_CoM=t.W_p_CoM,
        W_v_CoM=t.W_v_CoM,
        L_ang=t.L_G[3:],
        com_pos_des=ref.com_pos,
        com_vel_des=ref.com_vel,
        com_acc_des=ref.com_acc,
        com_err_integral=new_state.com_err_integral,
        ang_integral=ang_integral,
        kp_com=gains.kp_com,
        kd_com=gains.kd_com,
        ki_com=gains.ki_com,
        kp_ang=gains.kp_ang,
        ki_ang=gains.ki_ang,
    )
    wrench_des = Ldot_star - f_grav
    if contact_set is not None:
        return _step_contact_set(
            gains, consts, t, ref, contact_set, contacts, wrench_des, Ldot_star, f_grav, config, levels
        ), new_state

    tt = _torque_terms(gains, consts, t, ref, config, activation=act)

    # Force distribution. A = [A_L, A_R] has full row rank 6, so A^+ = A^T (A A^T)^-1 exactly.
    A = momentum.wrench_map(t.W_p_feet, t.W_p_CoM).astype(dtype)
    A_pinv = jnp.linalg.solve(A @ A.T, A).T
    f1 = A_pinv @ wrench_des
    N_A = jnp.eye(12, dtype=dtype) - A_pinv @ A
    A_stance = jnp.where(stance == 0, A[:, :6], A[:, 6:])
    R_stance = t.W_R_feet[stance]
    if config.forces == "qp":
        f_two, info_two = contact_qp.two_feet_wrenches(
            tt.Sigma, tt.tau_model, f1, N_A, t.W_R_feet[0], t.W_R_feet[1], config.contact,
            iterations=config.qp_iterations, hessian_reg=config.hessian_reg,
        )  # fmt: skip
        f_one, info_one = contact_qp.one_foot_wrench(
            A_stance, wrench_des, R_stance, config.contact,
            iterations=config.qp_iterations, hessian_reg=config.hessian_reg,
        )  # fmt: skip
        # WBC's two-feet QP keeps A f = L_dot* - f_grav as an equality; after a strong push that
        # rate is not realisable by feasible wrenches and the QP is infeasible. Instead of the
        # unconstrained (infeasible) wrenches, track the momentum rate as well as the contact
        # constraints allow (always feasible): the one-foot formulation over both feet.
        f_soft, info_soft = _two_feet_momentum_qp(A, wrench_des, tt, t.W_R_feet, config)
        infeasible_two, infeasible_one = info_two.infeasible, info_one.infeasible
        f_two = jnp.where(infeasible_two, f_soft, f_two)
        infeasible_two = infeasible_two & info_soft.infeasible
    else:
        # Seed paper C++: f0 minimises |tau| without inequality constraints (least squares over
        # range(N_A), regularised like the QP); one foot: f_k = A_k^-1 wrench_des.
        Z = contact_qp.range_basis(N_A)
        SZ = tt.Sigma @ Z
        y = -jnp.linalg.solve(
            SZ.T @ SZ + config.hessian_reg * jnp.eye(6, dtype=dtype),
            SZ.T @ (tt.tau_model + tt.Sigma @ f1),
        )
        f_two = f1 + Z @ y
        f_one = jnp.linalg.solve(A_stance, wrench_des)
        infeasible_two = infeasible_one = jnp.zeros((), bool)
    w_two = jnp.min(act)
    f_one_padded = jnp.where(
        stance == 0,
        jnp.concatenate([f_one, jnp.zeros(6, dtype)]),
        jnp.concatenate([jnp.zeros(6, dtype), f_one]),
    )
    f = w_two * f_two + (1.0 - w_two) * f_one_padded
    infeasible = (w_two > 0) & infeasible_two | (w_two < 1) & infeasible_one

    if levels:
        tau_unsat = hierarchy.solve(t, tt, f, levels).tau
    else:
        tau_unsat = tt.tau_model + tt.Sigma @ f
    tau = jnp.clip(tau_unsat, -config.torque_limit, config.torque_limit)
    out = ControlOutput(
        tau=tau,
        tau_unsat=tau_unsat,
        f=f,
        Ldot_star=Ldot_star,
        Ldot_cmd=A @ f + f_grav,
        qp_infeasible=infeasible,
        qp_violation=constraint_violation(f, t.W_R_feet, act, config.contact),
    )
    return out, new_state


# General contact set: weights of the force distribution (per N^2, against the torques' (N m)^2).
NORMAL_FORCE_WEIGHT = 1e3  # desired normal forces (a hand on a table)
INACTIVE_WEIGHT = 1e3  # x (1 - activation): the wrench of a contact being released goes to zero


def contact_set_wrenches(A, wrench_des, tt, cset, cterms, config):
    """Wrenches f (D,) of a general contact set (:mod:`wbc_jax.contacts`), the WBC two-feet QP
    extended to any contacts:

        minimise_f  |tau_model + Sigma f|^2 + w_n |S_n f - F_n|^2 + w_off sum_k (1 - a_k) |f_k|^2
        subject to  A f = L_dot* - f_grav   (f = f1 + Z y, Z a basis of null(A), as in WBC)
                    C f <= b                (each contact's friction cone, torsion, CoP, f_n >= a_k f_min)

    S_n f are the normal forces of the contacts with a desired one F_n (a hand pressing a table
    with 5 N, Nori et al. 2015). When the momentum rate is not realisable within the constraints
    (a strong push), the equality becomes the leading cost term (as the two-feet path):
    min |A f - w|^2 + c (the cost above), always feasible.

    Returns (f (D,), infeasible ()).
    """
    from wbc_jax import contacts as contacts_lib

    dtype = A.dtype
    D = cset.dim
    act = cterms.activation
    C, b = contacts_lib.constraints(cset, cterms.W_R, act)
    S_n, F_n = contacts_lib.normal_force_rows(cset, cterms.W_R, act)
    off = INACTIVE_WEIGHT * (1.0 - contacts_lib.row_activation(cset, act))
    A_pinv = jnp.linalg.solve(A @ A.T, A).T
    f1 = A_pinv @ wrench_des
    Z = contact_qp.range_basis(jnp.eye(D, dtype=dtype) - A_pinv @ A, D - 6)
    SZ, NZ = tt.Sigma @ Z, S_n @ Z
    H = SZ.T @ SZ + NORMAL_FORCE_WEIGHT * NZ.T @ NZ + Z.T @ (off[:, None] * Z)
    H = H + config.hessian_reg * jnp.eye(D - 6, dtype=dtype)
    g = SZ.T @ (tt.tau_model + tt.Sigma @ f1) + NORMAL_FORCE_WEIGHT * NZ.T @ (S_n @ f1 - F_n) + Z.T @ (off * f1)
    y, info = contact_qp.solve_qp(H, g, C @ Z, b - C @ f1, iterations=config.qp_iterations)
    c = TORQUE_WEIGHT_SOFT
    H_soft = (A.T @ A + c * (tt.Sigma.T @ tt.Sigma + NORMAL_FORCE_WEIGHT * S_n.T @ S_n + jnp.diag(off))
              + config.hessian_reg * jnp.eye(D, dtype=dtype))  # fmt: skip
    g_soft = -A.T @ wrench_des + c * (tt.Sigma.T @ tt.tau_model - NORMAL_FORCE_WEIGHT * S_n.T @ F_n)
    f_soft, info_soft = contact_qp.solve_qp(H_soft, g_soft, C, b, iterations=config.qp_iterations)
    f = jnp.where(info.infeasible, f_soft, f1 + Z @ y)
    return f, info.infeasible & info_soft.infeasible


def _step_contact_set(gains, consts, t, ref, cset, cterms, wrench_des, Ldot_star, f_grav, config, levels):
    from wbc_jax import contacts as contacts_lib

    dtype = t.M.dtype
    rows = contacts_lib.row_activation(cset, cterms.activation)
    tt = _torque_terms(gains, consts, t, ref, config, contact=(cterms.J * rows[:, None], cterms.Jdot_nu * rows))
    A = contacts_lib.wrench_map(cset, cterms.W_p, t.W_p_CoM).astype(dtype)
    if config.forces != "qp":
        raise ValueError("a general contact set needs forces='qp' (friction cones at every contact)")
    f, infeasible = contact_set_wrenches(A, wrench_des, tt, cset, cterms, config)
    tau_unsat = hierarchy.solve(t, tt, f, levels).tau if levels else tt.tau_model + tt.Sigma @ f
    return ControlOutput(
        tau=jnp.clip(tau_unsat, -config.torque_limit, config.torque_limit),
        tau_unsat=tau_unsat,
        f=f,
        Ldot_star=Ldot_star,
        Ldot_cmd=A @ f + f_grav,
        qp_infeasible=infeasible,
        qp_violation=contacts_lib.violation(cset, f, cterms.W_R, cterms.activation),
    )


GAIN_FIELDS = tuple(f.name for f in dataclasses.fields(Gains))
NON_NEGATIVE_GAINS = ("ki_com",)  # may be 0 in a gains file; all the others must be > 0


def gains_to_dict(gains: Gains) -> dict:
    """JSON-ready dict of lists."""
    return {k: np.asarray(getattr(gains, k)).tolist() for k in GAIN_FIELDS}


def gains_from_dict(values: dict, n: int = 23, dtype=jnp.float32) -> Gains:
    """Gains from a dict (e.g. a JSON gains file); names unknown/missing keys, checks values."""
    if not isinstance(values, dict):
        raise ValueError(f"gains must be a JSON object with keys {list(GAIN_FIELDS)}")
    unknown = sorted(set(values) - set(GAIN_FIELDS))
    missing = sorted(set(GAIN_FIELDS) - set(values))
    if unknown or missing:
        raise ValueError(
            f"gains: unknown keys {unknown}, missing keys {missing}; expected {list(GAIN_FIELDS)}"
        )
    arrays = {}
    for k in GAIN_FIELDS:
        try:
            arrays[k] = np.asarray(values[k], dtype=float)
        except (TypeError, ValueError) as err:
            raise ValueError(f"gain {k} must be a list of numbers, got {values[k]!r}") from err
    gains = Gains(**arrays)
    validate_gains(gains, n)
    # A gains file must have strictly positive gains (a zero gain disables a task); only the
    # CoM integral ki_com may be 0 (the WBC law has none).
    zero = {k: np.flatnonzero(arrays[k] <= 0).tolist() for k in GAIN_FIELDS
            if k not in NON_NEGATIVE_GAINS and np.any(arrays[k] <= 0)}  # fmt: skip
    if zero:
        raise ValueError(f"gains must be positive: non-positive entries (indices) {zero}")
    return jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype), gains)


def load_gains(path, n: int = 23, dtype=jnp.float32) -> Gains:
    """Read a gains JSON file (as written by ``wbc-jax tune`` or :func:`gains_to_dict`)."""
    import json
    import pathlib

    path = pathlib.Path(path)
    if not path.exists():
        raise FileNotFoundError(f"gains file {path} does not exist")
    try:
        values = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"gains file {path} is not valid JSON: {err}") from err
    return gains_from_dict(values, n, dtype)
