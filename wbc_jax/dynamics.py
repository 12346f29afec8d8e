"""[dynamics terms] Free-floating dynamics of eq. (1) of the seed paper, in the mixed representation.

    M(q) nu_dot + h(q, nu) - J(q)^T f = S tau + tau_passive,      J(q) nu_dot + Jdot nu = 0

Every quantity here is expressed in the controller's convention (see :mod:`wbc_jax.types`):
``nu = [W_v_B, W_omega_B, s_dot]`` with the joints in controller order. MuJoCo's free joint
stores ``[W_v_B, B_omega_B]`` (angular velocity in *base* axes), so with
``T = blkdiag(I3, W_R_B, I_n)`` (``nu = T qvel``, up to the joint permutation):

    M_mixed = T^-T M_mj T^-1,   h_mixed = T^-T h_mj,   J_mixed = J_mj T^-1.

The bias needs no extra term: d/dt(T^-1) nu = -S(B_omega) W_R_B^T W_omega = 0.
All functions are pure, jit/vmap/grad-safe, and take an MJX ``Data`` whose ``qpos``/``qvel``
are set; they recompute the kinematics themselves, so they are valid right after ``mjx.step``
(whose derived fields describe the state *before* the step).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from mujoco import mjx

from wbc_jax.math import quat_mul, quat_to_mat, skew
from wbc_jax.model import RobotIndex
from wbc_jax.types import Array, pytree_dataclass


@pytree_dataclass
class DynamicsTerms:
    """Controller-side dynamics terms at one state (n = controlled joints, nv = 6 + n).

    Attributes:
      nu:            (nv,)       mixed velocity [W_v_B, W_omega_B, s_dot]
      s, s_dot:      (n,), (n,)  joint positions / velocities, controller order
      W_p_B, W_R_B:  (3,), (3,3) base pose
      M:             (nv, nv)    mass matrix
      h:             (nv,)       Coriolis, centrifugal and gravity forces
      tau_passive:   (nv,)       passive generalised forces (joint damping)
      J_feet:        (2, 6, nv)  sole Jacobians [linear; angular], left then right
      Jdot_nu_feet:  (2, 6)      Jdot nu of each sole
      W_p_feet:      (2, 3)      sole origins
      W_R_feet:      (2, 3, 3)   sole orientations
      W_p_CoM:       (3,)        centre of mass
      W_v_CoM:       (3,)        CoM velocity
      J_CoM:         (3, nv)     CoM Jacobian
      A_G:           (6, nv)     centroidal momentum matrix, G[W]
      L_G:           (6,)        centroidal momentum [m v_CoM; angular momentum about CoM]
    """

    nu: Array
    s: Array
    s_dot: Array
    W_p_B: Array
    W_R_B: Array
    M: Array
    h: Array
    tau_passive: Array
    J_feet: Array
    Jdot_nu_feet: Array
    W_p_feet: Array
    W_R_feet: Array
    W_p_CoM: Array
    W_v_CoM: Array
    J_CoM: Array
    A_G: Array
    L_G: Array


def mixed_velocity(idx: RobotIndex, qpos: Array, qvel: Array) -> Array:
    """MuJoCo ``qvel`` (nv,) -> mixed ``nu`` (nv,): rotate the base angular velocity to world
    axes and reorder the joints into controller order. The only place this conversion lives."""
    _check_shape("qpos", qpos, (idx.nq,))
    _check_shape("qvel", qvel, (idx.nv,))
    R = quat_to_mat(qpos[3:7])
    return jnp.concatenate([qvel[:3], R @ qvel[3:6], qvel[idx.dof_joints]])


def mujoco_velocity(idx: RobotIndex, qpos: Array, nu: Array) -> Array:
    """Mixed ``nu`` (nv,) -> MuJoCo ``qvel`` (nv,); inverse of :func:`mixed_velocity`."""
    _check_shape("qpos", qpos, (idx.nq,))
    _check_shape("nu", nu, (idx.nv,))
    R = quat_to_mat(qpos[3:7])
    qvel = jnp.zeros(idx.nv, nu.dtype).at[:3].set(nu[:3]).at[3:6].set(R.T @ nu[3:6])
    return qvel.at[idx.dof_joints].set(nu[6:])


def qpos_rate(idx: RobotIndex, qpos: Array, nu: Array) -> Array:
    """d qpos / dt (nq,) for the mixed velocity ``nu``; the quaternion rate is (1/2) q (0, B_omega)."""
    R = quat_to_mat(qpos[3:7])
    omega_B = R.T @ nu[3:6]
    quat_dot = 0.5 * quat_mul(qpos[3:7], jnp.concatenate([jnp.zeros(1, nu.dtype), omega_B]))
    qdot = jnp.zeros(idx.nq, nu.dtype).at[:3].set(nu[:3]).at[3:7].set(quat_dot)
    return qdot.at[idx.qpos_joints].set(nu[6:])


def _check_shape(name: str, x: Array, shape: tuple[int, ...]) -> None:
    if tuple(x.shape) != shape:
        raise ValueError(f"{name} must have shape {shape}, got {tuple(x.shape)}")


def _to_mixed_cols(idx: RobotIndex, J_mj: Array, R: Array) -> Array:
    """J_mj (..., nv) in MuJoCo dof order/velocity -> mixed, controller order (J T^-1)."""
    J = J_mj[..., idx.dof_perm]
    return J.at[..., 3:6].set(J[..., 3:6] @ R.T)


def _kinematics(m: mjx.Model, d: mjx.Data, idx: RobotIndex, qpos: Array):
    """Sole Jacobians, centroidal momentum matrix, poses and CoM as functions of qpos only."""
    d = d.replace(qpos=qpos)
    d = mjx.kinematics(m, d)
    d = mjx.com_pos(m, d)
    R = d.xmat[idx.base_body]
    c = d.subtree_com[idx.base_body]  # com-based frame origin of cdof = whole-robot CoM
    cdof_ang, cdof_lin = d.cdof[:, :3], d.cdof[:, 3:]
    masks = jnp.asarray(idx.body_ancestor_dofs, dtype=d.cdof.dtype)  # (nbody, nv)

    def point_jacobian(point: Array, mask: Array) -> tuple[Array, Array]:
        jacp = (cdof_lin + jnp.cross(cdof_ang, point - c)) * mask[:, None]
        jacr = cdof_ang * mask[:, None]
        return jacp.T, jacr.T  # (3, nv) each

    # Sole Jacobians [linear; angular] of the site origins.
    foot_masks = masks[idx.foot_bodies]
    jp, jr = jax.vmap(point_jacobian)(d.site_xpos[idx.foot_sites], foot_masks)
    J_feet = _to_mixed_cols(idx, jnp.concatenate([jp, jr], axis=1), R)

    # Centroidal momentum matrix: sum over bodies of [m Jp; I_W Jr + m S(c_b - c) Jp].
    bodies = np.arange(1, masks.shape[0])
    jp_b, jr_b = jax.vmap(point_jacobian)(d.xipos[bodies], masks[bodies])
    mass_b = m.body_mass[bodies]
    ximat = d.ximat[bodies]
    I_W = jnp.einsum("bij,bj,bkj->bik", ximat, m.body_inertia[bodies], ximat)
    lin = jnp.einsum("b,bjv->jv", mass_b, jp_b)
    ang = jnp.einsum("bij,bjv->iv", I_W, jr_b) + jnp.einsum(
        "b,bij,bjv->iv", mass_b, skew(d.xipos[bodies] - c), jp_b
    )
    A_G = _to_mixed_cols(idx, jnp.concatenate([lin, ang], axis=0), R)
    poses = (d.site_xpos[idx.foot_sites], d.site_xmat[idx.foot_sites], c, d.xpos[idx.base_body], R)
    return J_feet, A_G, poses, d


def terms(m: mjx.Model, d: mjx.Data, idx: RobotIndex) -> DynamicsTerms:
    """All controller-side dynamics terms at the state (``d.qpos``, ``d.qvel``).

    Args:
      m: MJX model of the robot.
      d: MJX data; only ``qpos`` (nq,) and ``qvel`` (nv,) are read.
      idx: the robot's static index.

    Returns:
      :class:`DynamicsTerms`, mixed representation, controller joint order.
    """
    qpos, qvel = d.qpos, d.qvel
    _check_shape("qpos", qpos, (idx.nq,))
    _check_shape("qvel", qvel, (idx.nv,))
    nu = mixed_velocity(idx, qpos, qvel)

    # J(q) nu along the motion q(t) with nu held fixed: its time derivative is Jdot nu.
    def feet_velocity(q: Array) -> Array:
        J_feet, *_ = _kinematics(m, d, idx, q)
        return J_feet @ nu

    (J_feet, A_G, poses, dk) = _kinematics(m, d, idx, qpos)
    _, Jdot_nu_feet = jax.jvp(feet_velocity, (qpos,), (qpos_rate(idx, qpos, nu),))
    W_p_feet, W_R_feet, W_p_CoM, W_p_B, R = poses

    dk = mjx.crb(m, dk)
    dk = mjx.com_vel(m, dk)
    dk = mjx.passive(m, dk)
    dk = mjx.rne(m, dk)
    perm = idx.dof_perm

    def rows_to_mixed(x: Array) -> Array:  # T^-T applied on the left
        x = x[perm]
        return x.at[3:6].set(R @ x[3:6])

    M = rows_to_mixed(_to_mixed_cols(idx, mjx.full_m(m, dk), R))
    L_G = A_G @ nu
    return DynamicsTerms(
        nu=nu,
        s=qpos[idx.qpos_joints],
        s_dot=nu[6:],
        W_p_B=W_p_B,
        W_R_B=R,
        M=M,
        h=rows_to_mixed(dk.qfrc_bias),
        tau_passive=rows_to_mixed(dk.qfrc_passive),
        J_feet=J_feet,
        Jdot_nu_feet=Jdot_nu_feet,
        W_p_feet=W_p_feet,
        W_R_feet=W_R_feet.reshape(-1, 3, 3),
        W_p_CoM=W_p_CoM,
        W_v_CoM=L_G[:3] / idx.mass,
        J_CoM=A_G[:3] / idx.mass,
        A_G=A_G,
        L_G=L_G,
    )


@pytree_dataclass
class FrameTerms:
    """Kinematics of the k task frames and of the CoM at one state (mixed representation).

    Attributes:
      W_p:          (k, 3)      frame points (body origin + offset in body axes)
      W_R:          (k, 3, 3)   frame orientations (the body's)
      J:            (k, 6, nv)  Jacobians [linear of the point; angular]
      Jdot_nu:      (k, 6)      their Jdot nu
      Jdot_nu_CoM:  (3,)        Jdot nu of the CoM Jacobian
    """

    W_p: Array
    W_R: Array
    J: Array
    Jdot_nu: Array
    Jdot_nu_CoM: Array


def _frame_kinematics(m, d, idx: RobotIndex, qpos: Array, bodies: np.ndarray, offsets: np.ndarray):
    _, A_G, _, dk = _kinematics(m, d, idx, qpos)
    R_B = dk.xmat[idx.base_body]
    c = dk.subtree_com[idx.base_body]
    cdof_ang, cdof_lin = dk.cdof[:, :3], dk.cdof[:, 3:]
    masks = jnp.asarray(idx.body_ancestor_dofs[bodies], dtype=dk.cdof.dtype)  # (k, nv)
    W_R = dk.xmat[bodies]
    W_p = dk.xpos[bodies] + jnp.einsum("kij,kj->ki", W_R, jnp.asarray(offsets, W_R.dtype))
    jacp = (cdof_lin[None] + jnp.cross(cdof_ang[None], (W_p - c)[:, None])) * masks[..., None]
    jacr = cdof_ang[None] * masks[..., None]
    J = _to_mixed_cols(idx, jnp.concatenate([jacp, jacr], axis=2).transpose(0, 2, 1), R_B)
    return W_p, W_R, J, A_G[:3] / idx.mass


def frame_terms(m: mjx.Model, d: mjx.Data, idx: RobotIndex, bodies, offsets) -> FrameTerms:
    """Task-frame kinematics at the state (``d.qpos``, ``d.qvel``).

    Args:
      m, d, idx: as :func:`terms`.
      bodies: (k,) body ids (static numpy); offsets: (k, 3) points in the body frames (numpy).

    Returns:
      :class:`FrameTerms` (k may be 0: CoM terms only).
    """
    bodies = np.asarray(bodies, dtype=int).reshape(-1)
    offsets = np.asarray(offsets, dtype=float).reshape(-1, 3)
    qpos = d.qpos
    nu = mixed_velocity(idx, qpos, d.qvel)

    def velocities(q: Array):
        _, _, J, J_CoM = _frame_kinematics(m, d, idx, q, bodies, offsets)
        return J @ nu, J_CoM @ nu

    W_p, W_R, J, _ = _frame_kinematics(m, d, idx, qpos, bodies, offsets)
    _, (Jdot_nu, Jdot_nu_CoM) = jax.jvp(velocities, (qpos,), (qpos_rate(idx, qpos, nu),))
    return FrameTerms(W_p=W_p, W_R=W_R, J=J, Jdot_nu=Jdot_nu, Jdot_nu_CoM=Jdot_nu_CoM)
