"""Dynamics terms against C MuJoCo, finite differences, Pinocchio and the equations of motion."""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from conftest import assert_close, c_data, random_state
from mujoco import mjx

from wbc_jax.robot import dynamics
from wbc_jax.robot.icub import DESCRIPTION as ICUB
from wbc_jax.sim import native

SEEDS = range(5)
REL = 1e-6  # issue 4: relative error < 1e-6 (float64)


@pytest.fixture(scope="module")
def terms_fn(robot):
    idx = robot.index
    return jax.jit(lambda m, d: dynamics.terms(m, d, idx))


def mjx_data(robot, qpos, qvel):
    d = mjx.make_data(robot.mj_model)
    return d.replace(qpos=jnp.asarray(qpos), qvel=jnp.asarray(qvel))


def change_of_representation(robot, d: mujoco.MjData) -> np.ndarray:
    """T^-1 = blkdiag(I3, W_R_B^T, I_n) in MuJoCo dof order (qvel = T^-1 nu)."""
    Tinv = np.eye(robot.mj_model.nv)
    Tinv[3:6, 3:6] = d.xmat[robot.index.base_body].reshape(3, 3).T
    return Tinv


@pytest.mark.parametrize("seed", SEEDS)
def test_mass_matrix_and_bias_match_c_mujoco(robot, mx, terms_fn, seed):
    qpos, qvel = random_state(robot, seed)
    d = c_data(robot, qpos, qvel)
    t = terms_fn(mx, mjx_data(robot, qpos, qvel))
    M = np.zeros((robot.mj_model.nv,) * 2)
    mujoco.mj_fullM(robot.mj_model, d, M)
    Tinv, perm = change_of_representation(robot, d), robot.index.dof_perm
    M_ref = (Tinv.T @ M @ Tinv)[np.ix_(perm, perm)]
    h_ref = (Tinv.T @ d.qfrc_bias)[perm]
    err_M = np.abs(t.M - M_ref).max() / np.abs(M_ref).max()
    err_h = np.abs(t.h - h_ref).max() / np.abs(h_ref).max()
    print(f"seed {seed}: M relative error {err_M:.2e}, h relative error {err_h:.2e} vs C MuJoCo")
    assert err_M < REL
    assert err_h < REL
    # Ours against C MuJoCo (two implementations): measured <= 9e-16 abs, here and with XLA held to AVX2.
    assert_close(t.tau_passive, (Tinv.T @ d.qfrc_passive)[perm], "tau_passive", 1e-9, 1e-12)
    # Mixed velocity: nu = T qvel, reordered; and back.
    nu = dynamics.mixed_velocity(robot.index, jnp.asarray(qpos), jnp.asarray(qvel))
    assert_close(nu, np.linalg.solve(Tinv, qvel)[perm], "nu", 1e-12)
    assert_close(dynamics.mujoco_velocity(robot.index, jnp.asarray(qpos), nu), qvel, "qvel", 1e-12)


@pytest.mark.skipif(native.available() is not None, reason=f"native step: {native.available()}")
def test_engine_terms_equal_mjx_terms(robot, mx, terms_fn):
    """The terms from C MuJoCo's own (the compiled loop's: native.step_terms after mj_step1,
    dynamics.terms_from_engine) at 5 random states: every field within 1e-9 of MJX's, relative to
    the field's largest entry (float64; measured <= 2e-15)."""
    m, idx, frames = robot.mj_model, robot.index, dynamics.sole_frames(robot.index)
    sizes = dict(nq=m.nq, nv=m.nv, nbody=m.nbody, base_body=idx.base_body, frames=frames)
    slots = np.zeros((1, 0, 3)), np.zeros((1, 0, 3)), np.zeros((1, 0, 2), np.int32)
    worst = {}
    for seed in SEEDS:
        qpos, qvel = random_state(robot, seed)
        d = c_data(robot, qpos, qvel)  # kept alive: the handles are its address
        ids = native.handles([m], [d])
        zeros = np.zeros((1, m.nu)), np.zeros((1, 0, m.nbody, 6)), np.ones(1, bool)
        q, _, _, _, engine = native.step_terms(ids, *zeros, slots, start=True, **sizes)
        np.testing.assert_array_equal(q[0], qpos)  # nothing stepped
        engine = jax.tree_util.tree_map(lambda x: x[0], engine)
        got = dynamics.terms_from_engine(idx, jnp.asarray(qpos), jnp.asarray(qvel), engine, frames)
        want = terms_fn(mx, mjx_data(robot, qpos, qvel))
        for name, a in vars(got).items():
            b = np.asarray(getattr(want, name))
            err = float(np.abs(np.asarray(a) - b).max() / np.abs(b).max())
            worst[name] = max(worst.get(name, 0.0), err)
    print({k: f"{v:.1e}" for k, v in worst.items()})
    bad = {k: v for k, v in worst.items() if not v < 1e-9}
    assert not bad, f"terms from C MuJoCo differ from MJX's: {bad}"


def _sole_pose(robot, qpos, foot):
    d = mujoco.MjData(robot.mj_model)
    d.qpos[:] = qpos
    mujoco.mj_kinematics(robot.mj_model, d)
    s = robot.index.foot_sites[foot]
    return d.site_xpos[s].copy(), d.site_xmat[s].reshape(3, 3).copy()


def _integrate(robot, qpos, qvel, eps):
    q = qpos.copy()
    mujoco.mj_integratePos(robot.mj_model, q, qvel, eps)
    return q


@pytest.mark.parametrize("seed", SEEDS)
def test_sole_jacobians_and_jdot_nu_match_finite_differences(robot, mx, terms_fn, seed):
    qpos, qvel = random_state(robot, seed)
    t = terms_fn(mx, mjx_data(robot, qpos, qvel))
    eps = 1e-6
    qp, qm = _integrate(robot, qpos, qvel, eps), _integrate(robot, qpos, qvel, -eps)
    for foot in range(2):
        (pp, Rp), (pm, Rm) = _sole_pose(robot, qp, foot), _sole_pose(robot, qm, foot)
        v_fd = (pp - pm) / (2 * eps)
        dR = Rp @ Rm.T  # rotation over 2 eps, world axes
        w_fd = np.array([dR[2, 1] - dR[1, 2], dR[0, 2] - dR[2, 0], dR[1, 0] - dR[0, 1]]) / (4 * eps)
        twist = np.asarray(t.J_frames[foot] @ t.nu)
        assert_close(twist[:3], v_fd, f"sole {foot} linear velocity", 1e-6, 1e-7)
        assert_close(twist[3:], w_fd, f"sole {foot} angular velocity", 1e-6, 1e-7)
    # Jdot nu = d/dt (J(q) nu) along the motion with nu fixed: central difference of J nu.
    nu = np.asarray(t.nu)
    eps = 1e-5
    qp, qm = _integrate(robot, qpos, qvel, eps), _integrate(robot, qpos, qvel, -eps)
    Jp = terms_fn(mx, mjx_data(robot, qp, qvel)).J_frames
    Jm = terms_fn(mx, mjx_data(robot, qm, qvel)).J_frames
    # qvel (MuJoCo) is constant along this path; nu = T(q) qvel is not, so hold nu fixed.
    fd = (np.asarray(Jp) @ nu - np.asarray(Jm) @ nu) / (2 * eps)
    err = np.abs(np.asarray(t.Jdot_nu_frames) - fd).max() / np.abs(fd).max()
    print(f"seed {seed}: sole twist vs FD of the pose ok; Jdot nu relative error {err:.2e} vs FD")
    assert_close(t.Jdot_nu_frames, fd, "Jdot nu", 1e-6, 1e-6)


def _pinocchio_model(robot):
    pin = pytest.importorskip("pinocchio")
    import icub_models

    urdf = str(icub_models.get_model_file("iCubGazeboV2_5"))
    full = pin.buildModelFromUrdf(urdf, pin.JointModelFreeFlyer())
    locked = [full.getJointId(n) for n in full.names if n not in ("universe", "root_joint") and n not in ICUB.joints]
    reduced = pin.buildReducedModel(full, locked, pin.neutral(full))
    return pin, reduced


def test_centroidal_momentum_matrix_matches_pinocchio(robot, mx, terms_fn):
    pin, pm = _pinocchio_model(robot)
    pd = pm.createData()
    assert pm.nv == robot.mj_model.nv
    idx_q = [pm.joints[pm.getJointId(n)].idx_q for n in ICUB.joints]
    idx_v = [pm.joints[pm.getJointId(n)].idx_v for n in ICUB.joints]
    assert pin.computeTotalMass(pm) == pytest.approx(robot.index.mass, rel=1e-9)
    worst = 0.0
    for seed in range(20):
        qpos, qvel = random_state(robot, 100 + seed, joint_scale=0.6)
        t = terms_fn(mx, mjx_data(robot, qpos, qvel))
        R = np.asarray(t.W_R_B)
        q = np.zeros(pm.nq)
        q[:3] = qpos[:3]
        q[3:7] = [*qpos[4:7], qpos[3]]  # Pinocchio stores (x, y, z, w)
        q[idx_q] = qpos[robot.index.qpos_joints]
        # Pinocchio's free-flyer velocity is in base axes: v = [R^T W_v_B, R^T W_omega_B].
        nu = np.asarray(t.nu)
        v = np.zeros(pm.nv)
        v[:3], v[3:6] = R.T @ nu[:3], R.T @ nu[3:6]
        v[idx_v] = nu[6:]
        Ag = pin.computeCentroidalMap(pm, pd, q)
        to_pin = np.zeros((pm.nv, pm.nv))  # v = to_pin @ nu
        to_pin[:3, :3], to_pin[3:6, 3:6] = R.T, R.T
        to_pin[idx_v, np.arange(6, pm.nv)] = 1.0
        A_ref = Ag @ to_pin
        err = np.abs(np.asarray(t.A_G) - A_ref).max() / np.abs(A_ref).max()
        worst = max(worst, err)
        assert err < REL, f"seed {seed}: CMM relative error {err:.2e}"
        pin.computeCentroidalMomentum(pm, pd, q, v)
        L_ref = np.concatenate([pd.hg.linear, pd.hg.angular])
        # Against Pinocchio: measured 6.8e-12 (momentum), 8.2e-14 (CoM), 7.1e-15 abs (m v_CoM), with AVX2 too.
        assert_close(t.L_G, L_ref, "centroidal momentum", 1e-6, 1e-9)
        assert_close(t.W_p_CoM, pin.centerOfMass(pm, pd, q), "CoM", 1e-9, 1e-12)
        # m * CoM velocity = linear momentum (and CoM velocity by finite differences).
        assert_close(robot.index.mass * t.W_v_CoM, t.L_G[:3], "m v_CoM", 1e-12)
    print(f"worst CMM relative error vs Pinocchio over 20 states: {worst:.2e}")


def test_com_velocity_matches_finite_differences(robot, mx, terms_fn):
    qpos, qvel = random_state(robot, 7)
    t = terms_fn(mx, mjx_data(robot, qpos, qvel))
    eps = 1e-6
    cp = c_data(robot, _integrate(robot, qpos, qvel, eps), qvel).subtree_com[1]
    cm = c_data(robot, _integrate(robot, qpos, qvel, -eps), qvel).subtree_com[1]
    assert_close(t.W_v_CoM, (cp - cm) / (2 * eps), "CoM velocity", 1e-6, 1e-8)


@pytest.mark.slow  # 30 CPU s; the mass matrix and bias against C MuJoCo stay in the default set
def test_equation_of_motion_holds_with_mujoco_contact_forces(robot, mx, terms_fn):
    """M nu_dot + h - sum_k J_k^T f_k = S tau + tau_passive after an MJX step in contact."""
    from mujoco.mjx._src import support

    m = robot.mj_model
    idx = robot.index
    rng = np.random.default_rng(3)
    tau = rng.uniform(-5, 5, idx.n)
    ctrl = np.zeros(m.nu)
    ctrl[idx.actuators] = tau
    d = mjx.make_data(m).replace(qpos=jnp.asarray(robot.home_qpos()), ctrl=jnp.asarray(ctrl))
    d = jax.jit(mjx.step)(mx, d)  # settle into contact for one step
    d = jax.jit(mjx.forward)(mx, d)
    ncon = int(np.sum(np.asarray(d._impl.contact.dist) <= 0))
    assert ncon >= 4, "feet should be in contact"
    t = terms_fn(mx, d)
    # nu_dot = T qacc (the rate of T contributes R S(w_B) w_B = 0), reordered.
    R = np.asarray(t.W_R_B)
    qacc = np.asarray(d.qacc)
    nu_dot = np.concatenate([qacc[:3], R @ qacc[3:6], qacc[idx.dof_joints]])
    # Contact wrenches about each sole origin, world axes, from MuJoCo's own solver forces.
    contact = d._impl.contact
    wrench = np.zeros((2, 6))
    for i in range(contact.dist.shape[0]):
        if float(contact.dist[i]) > 0:
            continue
        geom = int(contact.geom[i, 1])
        foot = [k for k in range(2) if geom in idx.foot_geoms[k]][0]
        f_local = np.asarray(support.contact_force(mx, d, i, to_world_frame=True))[:3]
        p = np.asarray(contact.pos[i]) - np.asarray(t.W_p_frames[foot])
        wrench[foot] += np.concatenate([f_local, np.cross(p, f_local)])
    lhs = np.asarray(t.M) @ nu_dot + np.asarray(t.h)
    lhs -= sum(np.asarray(t.J_frames[k]).T @ wrench[k] for k in range(2))
    rhs = np.concatenate([np.zeros(6), tau]) + np.asarray(t.tau_passive)
    residual = np.abs(lhs - rhs).max() / np.abs(np.asarray(t.h)).max()
    print(f"equation (1) residual, relative to |h|: {residual:.2e}")
    assert residual < 1e-6
    # The contact term is not negligible in the identity (one step after touching down).
    assert wrench[:, 2].min() > 30.0


@pytest.mark.slow  # compiles the terms under vmap and under grad (minutes on the 2-core CPU): nightly
def test_batched_and_differentiable(robot, mx):
    idx = robot.index
    states = [random_state(robot, s) for s in range(64)]
    qpos = jnp.asarray(np.stack([s[0] for s in states]))
    qvel = jnp.asarray(np.stack([s[1] for s in states]))
    d0 = mjx.make_data(robot.mj_model)
    batched = jax.jit(jax.vmap(lambda q, v: dynamics.terms(mx, d0.replace(qpos=q, qvel=v), idx)))(qpos, qvel)
    assert batched.M.shape == (64, 29, 29) and batched.J_frames.shape == (64, 2, 6, 29)
    single = dynamics.terms(mx, d0.replace(qpos=qpos[5], qvel=qvel[5]), idx)
    # vmap vs single (two programs, one evaluation): rounding alone, ~1e-15 relative; the bar is far above it.
    assert_close(batched.A_G[5], single.A_G, "vmap vs single", 1e-10, 1e-12)

    def scalar(s):
        q = qpos[0].at[idx.qpos_joints].set(s)
        t = dynamics.terms(mx, d0.replace(qpos=q, qvel=qvel[0]), idx)
        return jnp.sum(t.M**2) + jnp.sum(t.h**2) + jnp.sum(t.J_frames**2) + jnp.sum(t.Jdot_nu_frames)

    g = jax.jit(jax.grad(scalar))(qpos[0][idx.qpos_joints])
    assert g.shape == (idx.n,) and bool(jnp.all(jnp.isfinite(g)))
    assert float(jnp.abs(g).max()) > 0


def test_wrong_shapes_are_rejected(robot, mx):
    d0 = mjx.make_data(robot.mj_model)
    with pytest.raises(ValueError, match=r"qvel must have shape \(29,\)"):
        dynamics.terms(mx, d0.replace(qvel=jnp.zeros(28)), robot.index)
    with pytest.raises(ValueError, match=r"nu must have shape \(29,\)"):
        dynamics.mujoco_velocity(robot.index, d0.qpos, jnp.zeros((2, 29)))
