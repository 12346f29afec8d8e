"""Free-floating dynamics of eq. (1) of the seed paper, in the mixed representation.

    M(q) nu_dot + h(q, nu) - J(q)^T f = S tau + tau_passive,      J(q) nu_dot + Jdot nu = 0

Every quantity here is expressed in the controller's convention (see :mod:`wbc_jax.core.types`):
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

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax.core.math import quat_mul, quat_to_mat, skew
from wbc_jax.core.mjx import mjx
from wbc_jax.core.types import Array, pytree_dataclass
from wbc_jax.robot.model import RobotIndex


@dataclasses.dataclass(frozen=True)
class Frames:
    """Static list of the k points whose kinematics the controller needs (contacts, then the
    motion tasks' frames): body ids and points in the body frames. Hashable (jit-static)."""

    bodies: tuple[int, ...]
    points: tuple[tuple[float, float, float], ...]

    def __post_init__(self):
        if len(self.bodies) != len(self.points):
            raise ValueError(f"Frames: {len(self.bodies)} bodies but {len(self.points)} points")

    def __len__(self) -> int:
        return len(self.bodies)

    def __add__(self, other: Frames) -> Frames:
        return Frames(self.bodies + other.bodies, self.points + other.points)


def sole_frames(idx: RobotIndex) -> Frames:
    """The origins of the two sole sites (left, right): the frames of the default contact set."""
    return Frames(
        bodies=tuple(int(b) for b in idx.foot_bodies),
        points=tuple(tuple(float(x) for x in p) for p in idx.foot_points),
    )


@pytree_dataclass
class DynamicsTerms:
    """Controller-side dynamics terms at one state (n = controlled joints, nv = 6 + n, k frames).

    Attributes:
      nu:             (nv,)       mixed velocity [W_v_B, W_omega_B, s_dot]
      s, s_dot:       (n,), (n,)  joint positions / velocities, controller order
      W_p_B, W_R_B:   (3,), (3,3) base pose
      M:              (nv, nv)    mass matrix
      h:              (nv,)       Coriolis, centrifugal and gravity forces
      tau_passive:    (nv,)       passive generalised forces (joint damping)
      W_p_frames:     (k, 3)      frame points (body origin + point in body axes)
      W_R_frames:     (k, 3, 3)   orientations of the frames' bodies
      J_frames:       (k, 6, nv)  frame Jacobians [linear of the point; angular]
      Jdot_nu_frames: (k, 6)      their Jdot nu
      W_p_CoM:        (3,)        centre of mass
      W_v_CoM:        (3,)        CoM velocity
      J_CoM:          (3, nv)     CoM Jacobian
      Jdot_nu_CoM:    (3,)        its Jdot nu
      A_G:            (6, nv)     centroidal momentum matrix, G[W]
      L_G:            (6,)        centroidal momentum [m v_CoM; angular momentum about CoM]
      xpos:           (nbody, 3)  body origins (fall detection)
    """

    nu: Array
    s: Array
    s_dot: Array
    W_p_B: Array
    W_R_B: Array
    M: Array
    h: Array
    tau_passive: Array
    W_p_frames: Array
    W_R_frames: Array
    J_frames: Array
    Jdot_nu_frames: Array
    W_p_CoM: Array
    W_v_CoM: Array
    J_CoM: Array
    Jdot_nu_CoM: Array
    A_G: Array
    L_G: Array
    xpos: Array


@pytree_dataclass
class EngineTerms:
    """What the controller's dynamics terms need of C MuJoCo's data after ``mj_step1`` at one
    state, in MuJoCo's order, as :func:`wbc_jax.sim.native.step_terms` returns them (with a batch
    axis) and :func:`terms_from_engine` converts them; k frames.

    Attributes:
      M:           (nv, nv)     mass matrix (``mj_fullM``)
      bias:        (nv,)        ``qfrc_bias``
      passive:     (nv,)        ``qfrc_passive``
      xpos, xmat:  (nbody, 3), (nbody, 3, 3)  body poses
      com:         (3,)         the robot's CoM (``subtree_com`` of its base)
      J:           (k, 6, nv)   frame Jacobians [point; angular] (``mj_jac``)
      Jdot_qvel:   (k, 6)       their ``mj_jacDot`` times qvel
      A_G:         (6, nv)      centroidal momentum matrix [sum m Jp; sum I_W Jr + m S(c_b - c) Jp]
      com_Jdot_qvel: (3,)       sum over bodies of m ``mj_jacDot`` at the body's CoM times qvel
    """

    M: Array
    bias: Array
    passive: Array
    xpos: Array
    xmat: Array
    com: Array
    J: Array
    Jdot_qvel: Array
    A_G: Array
    com_Jdot_qvel: Array


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


def _to_mixed_rows(idx: RobotIndex, x: Array, R: Array) -> Array:
    """x (nv, ...) rows in MuJoCo dof order (generalised forces) -> mixed, controller order (T^-T x)."""
    x = x[idx.dof_perm]
    return x.at[3:6].set(R @ x[3:6])


def _frame_poses(xpos: Array, xmat: Array, frames: Frames) -> tuple[Array, Array]:
    """The frames' points (k, 3) (body origin + point in body axes) and their bodies' orientations
    (k, 3, 3), from the bodies' poses xpos (nbody, 3), xmat (nbody, 3, 3)."""
    bodies = np.asarray(frames.bodies, dtype=int)
    W_R = xmat[bodies]
    return xpos[bodies] + jnp.einsum("kij,kj->ki", W_R, jnp.asarray(np.asarray(frames.points), W_R.dtype)), W_R


def _point_jacobian(cdof: Array, c: Array, point: Array, mask: Array) -> tuple[Array, Array]:
    """The linear (of ``point``, (3,)) and angular Jacobians (3, nv) each of a point of a body whose ancestor dofs
    are ``mask`` (nv,), from MuJoCo's ``cdof`` (nv, 6) [angular; linear] at the com-based origin ``c`` (3,)."""
    jacp = (cdof[:, 3:] + jnp.cross(cdof[:, :3], point - c)) * mask[:, None]
    jacr = cdof[:, :3] * mask[:, None]
    return jacp.T, jacr.T


def _centroidal_matrix(mass: Array, inertia: Array, ximat: Array, xipos: Array, c: Array, jp: Array, jr: Array):
    """The centroidal momentum matrix (6, nv), MuJoCo's columns: the sum over bodies of [m Jp; I_W Jr + m S(c_b - c)
    Jp], from the bodies' masses (B,), principal inertias (B, 3), inertial frames ximat (B, 3, 3) and xipos (B, 3),
    and the Jacobians jp, jr (B, 3, nv) of their CoMs."""
    I_W = jnp.einsum("bij,bj,bkj->bik", ximat, inertia, ximat)
    lin = jnp.einsum("b,bjv->jv", mass, jp)
    ang = jnp.einsum("bij,bjv->iv", I_W, jr) + jnp.einsum("b,bij,bjv->iv", mass, skew(xipos - c), jp)
    return jnp.concatenate([lin, ang], axis=0)


def _kinematics(m: mjx.Model, d: mjx.Data, idx: RobotIndex, qpos: Array, frames: Frames):
    """Frame Jacobians, centroidal momentum matrix and poses as functions of qpos only."""
    d = d.replace(qpos=qpos)
    d = mjx.kinematics(m, d)
    d = mjx.com_pos(m, d)
    R = d.xmat[idx.base_body]
    c = d.subtree_com[idx.base_body]  # com-based frame origin of cdof = whole-robot CoM
    masks = jnp.asarray(idx.body_ancestor_dofs, dtype=d.cdof.dtype)  # (nbody, nv)
    point_jacobian = jax.vmap(lambda point, mask: _point_jacobian(d.cdof, c, point, mask))

    # Frame Jacobians [linear of the point; angular of its body].
    W_p, W_R = _frame_poses(d.xpos, d.xmat, frames)
    jp, jr = point_jacobian(W_p, masks[np.asarray(frames.bodies, dtype=int)])
    J_frames = _to_mixed_cols(idx, jnp.concatenate([jp, jr], axis=1), R)

    all_bodies = np.arange(1, masks.shape[0])
    jp_b, jr_b = point_jacobian(d.xipos[all_bodies], masks[all_bodies])
    A_mj = _centroidal_matrix(
        m.body_mass[all_bodies], m.body_inertia[all_bodies], d.ximat[all_bodies], d.xipos[all_bodies], c, jp_b, jr_b
    )
    A_G = _to_mixed_cols(idx, A_mj, R)
    return (J_frames, A_G, W_p, W_R), d


def terms(m: mjx.Model, d: mjx.Data, idx: RobotIndex, frames: Frames | None = None) -> DynamicsTerms:
    """All controller-side dynamics terms at the state (``d.qpos``, ``d.qvel``).

    Args:
      m: MJX model of the robot (JAX implementation).
      d: MJX data (JAX implementation); only ``qpos`` (nq,) and ``qvel`` (nv,) are read.
      idx: the robot's static index.
      frames: the points whose Jacobians are needed (static); None: the two soles.

    Returns:
      :class:`DynamicsTerms`, mixed representation, controller joint order.
    """
    frames = sole_frames(idx) if frames is None else frames
    qpos, qvel = d.qpos, d.qvel
    _check_shape("qpos", qpos, (idx.nq,))
    _check_shape("qvel", qvel, (idx.nv,))
    nu = mixed_velocity(idx, qpos, qvel)

    # One pass of the kinematics and its derivative along q(t) with nu held fixed:
    # d/dt (J nu) = Jdot nu, for the frames and the CoM.
    def kinematics(q: Array):
        return _kinematics(m, d, idx, q, frames)

    (kin, dk), (dkin, _) = jax.jvp(kinematics, (qpos,), (qpos_rate(idx, qpos, nu),))
    J_frames, A_G, W_p_frames, W_R_frames = kin
    dJ_frames, dA_G = dkin[0], dkin[1]
    R = dk.xmat[idx.base_body]

    dk = mjx.crb(m, dk)
    dk = mjx.com_vel(m, dk)
    dk = mjx.passive(m, dk)
    dk = mjx.rne(m, dk)
    return _assemble(
        idx,
        qpos,
        nu,
        R,
        dk.xpos,
        mjx.full_m(m, dk),
        dk.qfrc_bias,
        dk.qfrc_passive,
        W_p_frames,
        W_R_frames,
        J_frames,
        dJ_frames @ nu,
        dk.subtree_com[idx.base_body],
        A_G,
        dA_G[:3] @ nu / idx.mass,
    )


def _assemble(
    idx, qpos, nu, R, xpos, M, bias, passive, W_p_frames, W_R_frames, J_frames, Jdot_nu_frames, com, A_G, Jdot_nu_CoM
) -> DynamicsTerms:
    """:class:`DynamicsTerms` of every engine's terms (:func:`terms`, :func:`terms_from_engine`,
    :func:`terms_from_split`): M, the bias and the passive forces in MuJoCo's representation (made mixed here with the
    base rotation R); the frame Jacobians, their Jdot nu, A_G and the CoM's Jdot nu already mixed."""
    L_G = A_G @ nu
    return DynamicsTerms(
        nu=nu,
        s=qpos[idx.qpos_joints],
        s_dot=nu[6:],
        W_p_B=xpos[idx.base_body],
        W_R_B=R,
        M=_to_mixed_rows(idx, _to_mixed_cols(idx, M, R), R),
        h=_to_mixed_rows(idx, bias, R),
        tau_passive=_to_mixed_rows(idx, passive, R),
        W_p_frames=W_p_frames,
        W_R_frames=W_R_frames,
        J_frames=J_frames,
        Jdot_nu_frames=Jdot_nu_frames,
        W_p_CoM=com,
        W_v_CoM=L_G[:3] / idx.mass,
        J_CoM=A_G[:3] / idx.mass,
        Jdot_nu_CoM=Jdot_nu_CoM,
        A_G=A_G,
        L_G=L_G,
        xpos=xpos,
    )


def terms_from_engine(idx: RobotIndex, qpos: Array, qvel: Array, e: EngineTerms, frames: Frames) -> DynamicsTerms:
    """The controller-side dynamics terms at (``qpos`` (nq,), ``qvel`` (nv,)) from C MuJoCo's own
    (:class:`EngineTerms` at that state, one environment): :func:`terms`'s, up to rounding.

    The frame Jacobians' derivative needs no term of the representation's: with
    ``J_mixed = J_mj T^-1``, ``Jdot_mixed nu = Jdot_mj qvel + J_mj d/dt(T^-1) nu`` and the last term is
    zero (module docstring), so ``mj_jacDot`` times ``qvel`` is the mixed ``Jdot nu``.
    """
    nu = mixed_velocity(idx, qpos, qvel)
    R = e.xmat[idx.base_body]
    W_p, W_R = _frame_poses(e.xpos, e.xmat, frames)
    return _assemble(
        idx,
        qpos,
        nu,
        R,
        e.xpos,
        e.M,
        e.bias,
        e.passive,
        W_p,
        W_R,
        _to_mixed_cols(idx, e.J, R),
        e.Jdot_qvel,
        e.com,
        _to_mixed_cols(idx, e.A_G, R),
        e.com_Jdot_qvel / idx.mass,
    )


def terms_from_split(idx: RobotIndex, mj_model, d, frames: Frames) -> DynamicsTerms:
    """The controller-side dynamics terms from MJX-Warp data after MuJoCo Warp's ``step1`` at the state
    (:mod:`wbc_jax.sim.warp_split`; one environment): :func:`terms`'s, up to float32 rounding, without computing
    the kinematics again.

    ``mj_model``: the robot's MjModel (static: masses, inertias and the sparse layout of the mass matrix). The
    Jacobians come from ``cdof`` at the root's subtree CoM, as in :func:`terms`; their derivative along the motion
    from ``cdof_dot`` (the spatial acceleration at that fixed point) plus omega x v of the point (the classical
    acceleration of a moving point), so ``Jdot nu`` needs no derivative of the kinematics."""
    qpos, qvel = d.qpos, d.qvel
    dtype = qpos.dtype
    nu = mixed_velocity(idx, qpos, qvel)
    R = d.xmat[idx.base_body]
    c = d.subtree_com[idx.base_body]
    dot_ang, dot_lin = d.cdof_dot[:, :3], d.cdof_dot[:, 3:]
    masks = jnp.asarray(idx.body_ancestor_dofs, dtype=dtype)  # (nbody, nv)

    def point(p: Array, mask: Array, body: Array):
        jacp, jacr = _point_jacobian(d.cdof, c, p, mask)
        omega, v_at_c = d.cvel[body, :3], d.cvel[body, 3:]
        v_p = v_at_c + jnp.cross(omega, p - c)
        bias_lin = ((dot_lin + jnp.cross(dot_ang, p - c)) * mask[:, None]).T @ qvel + jnp.cross(omega, v_p)
        bias_ang = (dot_ang * mask[:, None]).T @ qvel
        return jacp, jacr, jnp.concatenate([bias_lin, bias_ang])

    bodies = np.asarray(frames.bodies, dtype=int)
    W_p, W_R = _frame_poses(d.xpos, d.xmat, frames)
    jp, jr, jdot = jax.vmap(point)(W_p, masks[bodies], jnp.asarray(bodies))
    all_bodies = np.arange(1, masks.shape[0])
    jp_b, jr_b, jdot_b = jax.vmap(point)(d.xipos[all_bodies], masks[all_bodies], jnp.asarray(all_bodies))
    mass_b = jnp.asarray(mj_model.body_mass[all_bodies], dtype)
    inertia_b = jnp.asarray(mj_model.body_inertia[all_bodies], dtype)
    A_mj = _centroidal_matrix(mass_b, inertia_b, d.ximat[all_bodies], d.xipos[all_bodies], c, jp_b, jr_b)
    # The mass matrix: MuJoCo's sparse lower triangle (rows of M_rownnz entries at columns M_colind), made dense and
    # symmetric by one gather (a scatter of the entries cost the GPU several passes over the batch's matrices).
    rows = np.repeat(np.arange(idx.nv), mj_model.M_rownnz)
    entry = np.full((idx.nv, idx.nv), len(rows))  # the index of each (i, j) among the entries; the last: a zero
    entry[rows, np.asarray(mj_model.M_colind)] = entry[np.asarray(mj_model.M_colind), rows] = np.arange(len(rows))
    M = jnp.concatenate([d._impl.M.astype(dtype), jnp.zeros(1, dtype)])[entry]
    return _assemble(
        idx,
        qpos,
        nu,
        R,
        d.xpos,
        M,
        d.qfrc_bias,
        d.qfrc_passive,
        W_p,
        W_R,
        _to_mixed_cols(idx, jnp.concatenate([jp, jr], axis=1), R),
        jdot,
        c,
        _to_mixed_cols(idx, A_mj, R),
        jnp.einsum("b,bj->j", mass_b, jdot_b[:, :3]) / idx.mass,
    )
