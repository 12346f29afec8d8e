"""[momentum task] Desired rate of change of the centroidal momentum and the wrench map.

    L_dot = A f + f_grav,   A_k = [I3 0; S(p_k - x_CoM) I3],   f_grav = [0, 0, -m g, 0, 0, 0]

    x_ddot* = x_ddot_d - K_P,CoM (x - x_d) - K_D,CoM (x_dot - x_dot_d) - K_I,CoM int(x - x_d)
    L_dot*  = [m x_ddot*;  -K_P,w L_ang - K_I,w int(L_ang)]

References: seed paper (force task of highest priority); whole-body-controllers
``momentumBasedController.m``; Nava et al., IROS 2016 (the angular-momentum integral,
linearised around the postural reference). See shared/reference/controller-spec.md 1.2-1.3.
"""

from __future__ import annotations

import jax.numpy as jnp

from wbc_jax.dynamics import DynamicsTerms
from wbc_jax.math import skew
from wbc_jax.types import Array

GRAVITY = 9.81  # m/s^2, as in the papers and MuJoCo's default


def wrench_map(W_p_feet: Array, W_p_CoM: Array) -> Array:
    """Map A (6, 12) from the feet wrenches [f_L; f_R] (world axes, at the sole origins) to the
    rate of the centroidal momentum. W_p_feet: (2, 3); W_p_CoM: (3,)."""
    blocks = []
    for k in range(2):
        top = jnp.concatenate([jnp.eye(3), jnp.zeros((3, 3))], axis=1)
        bottom = jnp.concatenate([skew(W_p_feet[k] - W_p_CoM), jnp.eye(3)], axis=1)
        blocks.append(jnp.concatenate([top, bottom], axis=0))
    return jnp.concatenate(blocks, axis=1)


def gravity_wrench(mass: float, dtype=jnp.float32) -> Array:
    """f_grav (6,): the weight as a centroidal wrench."""
    return jnp.array([0.0, 0.0, -mass * GRAVITY, 0.0, 0.0, 0.0], dtype=dtype)


def centroidal_jacobian_at_posture(
    t_ref: DynamicsTerms, foot: int, base_damping: float = 1e-7
) -> Array:
    """J_G,ang (3, n): angular momentum per joint displacement with ``foot`` fixed (Nava 2016).

    With a fixed foot the base velocity is a function of the joint velocities,
    v_b = -(J_b^T J_b + eps I)^-1 J_b^T J_s s_dot, so that
    ``int(L_ang) ~= J_G,ang (s - s_d)`` with J_G = A_G,s + A_G,b (d v_b / d s_dot) evaluated
    at the postural reference (``t_ref`` = terms at the reference configuration).
    """
    J = t_ref.J_feet[foot]
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
    acc = (
        com_acc_des
        - kp_com * (W_p_CoM - com_pos_des)
        - kd_com * (W_v_CoM - com_vel_des)
        - ki_com * com_err_integral
    )
    return jnp.concatenate([mass * acc, -kp_ang * L_ang - ki_ang * ang_integral])
