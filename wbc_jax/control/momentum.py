"""Desired rate of change of the centroidal momentum.

    L_dot = A f + f_grav    (A: the contact set's wrench map, :func:`wbc_jax.control.constraints.wrench_map`)

    x_ddot* = x_ddot_d - K_P,CoM (x - x_d) - K_D,CoM (x_dot - x_dot_d) - K_I,CoM int(x - x_d)
    L_dot*  = [m x_ddot*;  -K_P,w L_ang - K_I,w int(L_ang)]

References: seed paper (force task of highest priority); whole-body-controllers
``momentumBasedController.m``; Nava et al., IROS 2016 (the angular-momentum integral,
linearised around the postural reference).
"""

from __future__ import annotations

import jax.numpy as jnp

from wbc_jax.core.types import Array
from wbc_jax.robot.dynamics import DynamicsTerms


def centroidal_jacobian_at_posture(t_ref: DynamicsTerms, foot: int, base_damping: float = 1e-7) -> Array:
    """J_G,ang (3, n): angular momentum per joint displacement with the frame ``foot`` (an index
    into the frames of ``t_ref``, a sole) fixed (Nava 2016).

    With a fixed foot the base velocity is a function of the joint velocities,
    v_b = -(J_b^T J_b + eps I)^-1 J_b^T J_s s_dot, so that
    ``int(L_ang) ~= J_G,ang (s - s_d)`` with J_G = A_G,s + A_G,b (d v_b / d s_dot) evaluated
    at the postural reference (``t_ref`` = terms at the reference configuration).
    """
    J = t_ref.J_frames[foot]
    J_b, J_s = J[:, :6], J[:, 6:]
    v_b = -jnp.linalg.solve(J_b.T @ J_b + base_damping * jnp.eye(6, dtype=J.dtype), J_b.T @ J_s)
    A = t_ref.A_G
    return (A[:, 6:] + A[:, :6] @ v_b)[3:]


def momentum_rate_reference(
    *,
    mass: float,
    W_p_CoM: Array,
    W_v_CoM: Array,
    L_ang: Array,
    com_pos_des: Array,
    com_vel_des: Array,
    com_acc_des: Array,
    com_err_integral: Array,
    ang_integral: Array,
    kp_com: Array,
    kd_com: Array,
    ki_com: Array,
    kp_ang: Array,
    ki_ang: Array,
) -> Array:
    """L_dot* (6,) = [m x_ddot*; -K_P,w L_ang - K_I,w int(L_ang)] (all gains diagonal, (3,))."""
    acc = com_acc_des - kp_com * (W_p_CoM - com_pos_des) - kd_com * (W_v_CoM - com_vel_des) - ki_com * com_err_integral
    return jnp.concatenate([mass * acc, -kp_ang * L_ang - ki_ang * ang_integral])
