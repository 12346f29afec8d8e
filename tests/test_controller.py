"""The torque law against its definition, the momentum task, and controller input checks."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import random_state
from mujoco import mjx

from wbc_jax.control import constraints, torques
from wbc_jax.control import controller as C
from wbc_jax.control import gains as G
from wbc_jax.control.references import Reference
from wbc_jax.robot import contacts, dynamics
from wbc_jax.robot.icub import DESCRIPTION as ICUB


@functools.cache
def _compiled_terms(robot):
    """dynamics.terms compiled once for the module's three states: every leaf committed to the CPU (make_data's
    leaves are, jnp.asarray's are not, and jit compiles once per combination: 13 CPU s each)."""
    jitted = jax.jit(lambda d: dynamics.terms(robot.mjx_model, d, robot.index))
    return lambda d: jitted(jax.device_put(d, jax.devices("cpu")[0]))


def _terms_at(robot, qpos, qvel):
    return _compiled_terms(robot)(mjx.make_data(robot.mj_model).replace(qpos=jnp.asarray(qpos), qvel=jnp.asarray(qvel)))


@pytest.fixture(scope="module")
def state_terms(robot):
    return _terms_at(robot, *random_state(robot, 11, joint_scale=0.2))


def _torque_terms(t, damping, postural="stable", rows=None):
    gains = G.default_gains(ICUB, jnp.float64)
    J_c, Jdot_nu_c = t.J_frames.reshape(12, -1), t.Jdot_nu_frames.reshape(12)  # both soles, active
    if rows is not None:  # contact rows scaled by their activations
        J_c, Jdot_nu_c = J_c * rows[:, None], Jdot_nu_c * rows
    return torques.torque_terms(
        t,
        J_c,
        Jdot_nu_c,
        postural=postural,
        kp_postural=gains.kp_postural,
        kd_postural=gains.kd_postural,
        s_des=t.s + 0.05,
        pinv_damping=damping,
    )


@pytest.mark.parametrize("postural", ["stable", "seed"])
def test_torque_law_satisfies_its_definition(state_terms, postural):
    """Lambda tau = J M^-1 (h - J^T f) - Jdot nu for the commanded f; the postural part lies in
    the null space of Lambda. Exact with an undamped pseudo-inverse."""
    t = state_terms
    tt = _torque_terms(t, 1e-12, postural)
    f = jnp.asarray(np.random.default_rng(0).normal(scale=50.0, size=12))
    tau = tt.tau_model + tt.Sigma @ f
    h = t.h - t.tau_passive
    rhs = tt.J_c @ jnp.linalg.solve(t.M, h - tt.J_c.T @ f) - tt.Jdot_nu_c
    rel = float(jnp.linalg.norm(tt.Lambda @ tau - rhs) / jnp.linalg.norm(rhs))
    assert rel < 1e-6, rel
    assert float(jnp.abs(tt.Lambda @ tt.N_Lambda).max()) < 1e-6 * float(jnp.abs(tt.Lambda).max())
    # Then the feet do not accelerate: J_c nu_dot + Jdot nu = 0 with M nu_dot = B tau + J^T f - h.
    nu_dot = jnp.linalg.solve(t.M, jnp.concatenate([jnp.zeros(6), tau]) + tt.J_c.T @ f - h)
    acc = tt.J_c @ nu_dot + tt.Jdot_nu_c
    assert float(jnp.linalg.norm(acc)) < 1e-6 * float(jnp.linalg.norm(tt.Jdot_nu_c) + 1.0)


@pytest.mark.parametrize("damping, active", [(1.0, (1.0, 1.0)), (0.1, (1.0, 1.0)), (10.0, (1.0, 0.0))])
@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_postural_projector_equals_pinv_of_the_svd(state_terms, damping, active, dtype):
    """P = pinv(X, tol) X with X = N_Lambda Mbar, against NumPy's float64 SVD of X: the same rank
    (tol 1e-5 cuts X's smallest singular values here) and the same projector."""
    rows = jnp.repeat(jnp.asarray(active), 6)
    tt = _torque_terms(state_terms, damping, rows=rows)
    Lambda, Mbar = np.asarray(tt.Lambda), np.asarray(tt.Mbar)
    X = np.linalg.inv(np.eye(23) + Lambda.T @ Lambda / damping) @ Mbar
    _, s, Vt = np.linalg.svd(X)
    keep = s > 1e-5
    assert 0 < keep.sum() < 23 if active[1] else keep.all(), s
    P_ref = (Vt.T * keep) @ Vt
    P = np.asarray(torques.postural_projector(jnp.asarray(Lambda, dtype), jnp.asarray(Mbar, dtype), damping, 1e-5))
    assert P.dtype == dtype
    # Against NumPy's float64 SVD (another path): measured <= 3e-14 in float64, 5.5e-7 in float32; bars ~100x that.
    np.testing.assert_allclose(P, P_ref, atol=3e-12 if dtype == jnp.float64 else 5e-5)
    # X's own pseudo-inverse, the definition, in float64.
    np.testing.assert_allclose(
        np.asarray(torques.postural_projector(tt.Lambda, tt.Mbar, damping, 1e-5)),
        np.linalg.pinv(X, rcond=1e-5 / s[0]) @ X,
        atol=1e-10,
    )


@pytest.mark.parametrize("damping, active", [(1.0, (1.0, 1.0)), (1.0, (1.0, 0.3)), (0.1, (1.0, 1.0))])
def test_projector_from_ritz_vectors_equals_the_whole_eigenproblem(state_terms, damping, active):
    """In float32 postural_projector takes the cut directions from Ritz vectors on 12 columns (a 12 x
    12 eigh), certified here: the same projector as the 23 x 23 eigh of the same matrix, to float32's
    rounding (measured 1.4e-6 on the sinusoid's states; a start that missed a cut direction differs
    by O(1))."""
    rows = jnp.repeat(jnp.asarray(active), 6)
    tt = _torque_terms(state_terms, damping, rows=rows)
    Lambda, Mbar = tt.Lambda.astype(jnp.float32), tt.Mbar.astype(jnp.float32)
    Mbar_inv = jnp.linalg.inv(Mbar)
    X_inv = Mbar_inv @ (damping * jnp.eye(23) + Lambda.T @ Lambda)
    cut = (damping / 1e-5) ** 2
    ritz, certified = torques.ritz_projector(X_inv @ X_inv.T, cut, Mbar_inv @ Lambda.T)
    assert bool(certified)
    whole = torques.spectral_projector(X_inv @ X_inv.T, cut)
    assert 0 < int(jnp.round(jnp.trace(whole))) <= 12
    np.testing.assert_allclose(np.asarray(ritz), np.asarray(whole), atol=1e-5)
    P = torques.postural_projector(Lambda, Mbar, damping, 1e-5, Mbar_inv)
    np.testing.assert_allclose(np.asarray(P), np.eye(23) - np.asarray(whole), atol=1e-5)


def test_projector_where_ritz_vectors_fail_solves_the_whole_eigenproblem(state_terms):
    """A tolerance of 0.1 cuts more of X's singular values (17) than the start has columns (12): the
    Ritz projector is O(1) off and not certified, and postural_projector, from the whole
    eigenproblem, is the definition pinv(X, tol) X (float64 SVD)."""
    tt = _torque_terms(state_terms, 1.0)
    Lambda, Mbar = np.asarray(tt.Lambda), np.asarray(tt.Mbar)
    X = np.linalg.inv(np.eye(23) + Lambda.T @ Lambda) @ Mbar
    _, s, Vt = np.linalg.svd(X)
    keep = s > 0.1
    assert (~keep).sum() > 12, s
    reference = (Vt.T * keep) @ Vt
    Mbar_inv = np.linalg.inv(Mbar)
    X_inv = Mbar_inv @ (np.eye(23) + Lambda.T @ Lambda)
    ritz, certified = torques.ritz_projector(jnp.asarray(X_inv @ X_inv.T), 100.0, jnp.asarray(Mbar_inv @ Lambda.T))
    assert not bool(certified)
    assert np.abs(np.eye(23) - np.asarray(ritz) - reference).max() > 0.1
    P = torques.postural_projector(tt.Lambda, tt.Mbar, 1.0, 0.1)
    np.testing.assert_allclose(np.asarray(P), reference, atol=1e-5)


@pytest.mark.parametrize("damping", [1.0, 0.01])
def test_damped_pseudo_inverse_residual_is_its_closed_form(state_terms, damping):
    """With a damped pseudo-inverse (WBC simulation: lambda = 1) the law is exact only up to the
    damping's residual. With tau = Lambda^+ b + N_Lambda tau_0, Lambda Lambda^+ = I - lambda G^-1
    and Lambda N_Lambda = lambda G^-1 Lambda (G = Lambda Lambda^T + lambda I), so
    Lambda tau - b = -lambda G^-1 (b - Lambda tau_0): the residual must be that, to rounding."""
    t = state_terms
    tt = _torque_terms(t, damping)
    f = jnp.asarray(np.random.default_rng(1).normal(scale=50.0, size=12))
    tau = tt.tau_model + tt.Sigma @ f
    b = tt.J_c @ jnp.linalg.solve(t.M, t.h - t.tau_passive - tt.J_c.T @ f) - tt.Jdot_nu_c
    tau_0 = tt.Sigma_0 @ f + tt.tau_0
    G = tt.Lambda @ tt.Lambda.T + damping * jnp.eye(12)
    expected = -damping * jnp.linalg.solve(G, b - tt.Lambda @ tau_0)
    residual = tt.Lambda @ tau - b
    np.testing.assert_allclose(residual, expected, rtol=1e-7, atol=1e-9 * float(jnp.linalg.norm(b)))
    # The damping matters: the residual is far above rounding and grows with lambda.
    assert float(jnp.linalg.norm(residual) / jnp.linalg.norm(b)) > 1e-6


def test_torque_law_blocks_from_one_cholesky_equal_the_direct_solves(state_terms):
    """torque_terms reads Mbar, M_sb M_b^-1 (J_b^T, h_b) and the postural projector's solves off one
    Cholesky factor of M: each against NumPy's float64 LU solves of its definition (a wrong block of
    the factor gives O(1) errors; measured <= 6e-16 relative, bars 1e-11)."""
    t = state_terms
    tt = _torque_terms(t, 1.0)
    M, h = np.asarray(t.M), np.asarray(t.h - t.tau_passive)
    J_c = np.asarray(tt.J_c)
    M_b, M_bs, M_sb, M_s = M[:6, :6], M[:6, 6:], M[6:, :6], M[6:, 6:]
    Mbar = M_s - M_sb @ np.linalg.solve(M_b, M_bs)
    np.testing.assert_allclose(np.asarray(tt.Mbar), Mbar, rtol=0, atol=1e-11 * np.abs(Mbar).max())
    Sigma_0 = -(J_c[:, 6:].T - M_sb @ np.linalg.solve(M_b, J_c[:, :6].T))
    np.testing.assert_allclose(np.asarray(tt.Sigma_0), Sigma_0, rtol=0, atol=1e-11 * np.abs(Sigma_0).max())
    Lambda = (J_c @ np.linalg.solve(M, np.eye(29)))[:, 6:]
    np.testing.assert_allclose(np.asarray(tt.Lambda), Lambda, rtol=0, atol=1e-11 * np.abs(Lambda).max())
    tau_0 = np.asarray(tt.tau_0 - tt.u0)
    np.testing.assert_allclose(tau_0, h[6:] - M_sb @ np.linalg.solve(M_b, h[:6]), rtol=0, atol=1e-11 * np.abs(h).max())
    # The projector with Mbar^-1 handed over equals the one that solves with Mbar itself.
    P_given = torques.postural_projector(tt.Lambda, tt.Mbar, 1.0, 1e-5, jnp.asarray(np.linalg.inv(Mbar)))
    np.testing.assert_allclose(
        np.asarray(P_given), np.asarray(torques.postural_projector(tt.Lambda, tt.Mbar, 1.0, 1e-5)), atol=1e-10
    )


@pytest.fixture(scope="module")
def standing_terms(robot):
    """Near the home posture: feet almost flat, so the two-feet QP is feasible."""
    rng = np.random.default_rng(5)
    qpos = robot.home_qpos()
    qpos[robot.index.qpos_joints] += rng.uniform(-0.03, 0.03, robot.index.n)
    qvel = rng.normal(scale=0.05, size=robot.mj_model.nv)
    return _terms_at(robot, qpos, qvel)


def _reference(t) -> Reference:
    return Reference(
        com_pos=t.W_p_CoM + jnp.array([0.0, 0.01, 0.0]),
        com_vel=jnp.zeros(3),
        com_acc=jnp.zeros(3),
        s_des=t.s,
        activation=jnp.ones(2),
    )


@functools.cache
def _compiled_tick(robot, forces: str):
    """The controller's first tick from terms t, compiled once per forces mode for the module (op by op,
    a tick cost several times the CPU time of its compile)."""
    ctrl = C.make_controller(robot, C.ControllerConfig(forces=forces))
    return jax.jit(lambda gains, t: ctrl.step(gains, ctrl.init(t), t, _reference(t), 0.0)[0])


def _step(robot, t, forces):
    gains = G.default_gains(ICUB, jnp.float64)
    return gains, _reference(t), _compiled_tick(robot, forces)(gains, t)


@pytest.mark.parametrize("forces", ["qp", "analytic"])
def test_force_distribution_realises_the_momentum_rate(robot, standing_terms, forces):
    t = standing_terms
    gains, ref, out = _step(robot, t, forces)
    assert bool(jnp.all(jnp.isfinite(out.tau)))
    assert not bool(out.qp_infeasible)
    # Two feet, feasible: A f + f_grav = L_dot* exactly.
    np.testing.assert_allclose(out.Ldot_cmd, out.Ldot_star, atol=1e-6, err_msg=forces)
    # Desired linear momentum rate: m (-Kp (x - x_d) - Kd v).
    lin = robot.index.mass * (-gains.kp_com * (t.W_p_CoM - ref.com_pos) - gains.kd_com * t.W_v_CoM)
    np.testing.assert_allclose(out.Ldot_star[:3], lin, rtol=1e-10)
    if forces == "qp":
        # The QP wrenches satisfy friction, torsional friction, unilaterality and CoP.
        assert float(out.qp_violation) < 1e-6


@pytest.mark.slow
def test_warm_started_force_qp_carries_the_last_ticks_solution(robot, standing_terms):
    """With ``qp_warm_start`` the state carries the force QP's multipliers and slacks (NaN before
    the first tick), and the second tick of the same problem, warm-started, gives the first
    tick's wrenches within the QP's tolerance (the cheap check of the solver's warm start:
    tests/test_forces.py::test_solve_qp_warm_start_same_solution_fewer_steps)."""
    t = standing_terms
    gains = G.default_gains(ICUB, jnp.float64)
    ctrl = C.make_controller(robot, C.ControllerConfig(qp_warm_start=True))

    @jax.jit
    def two_ticks(gains, t):
        state0 = ctrl.init(t)
        out1, state1 = ctrl.step(gains, state0, t, _reference(t), 0.0)
        out2, state2 = ctrl.step(gains, state1, t, _reference(t), 0.0)
        return state0.qp_start, state1.qp_start, out1.f, out2.f

    start0, start1, f1, f2 = two_ticks(gains, t)
    assert np.all(np.isnan(start0)) and np.all(np.isfinite(start1)) and np.all(np.asarray(start1) > 0)
    np.testing.assert_allclose(f2, f1, rtol=0, atol=1e-8 * float(jnp.max(jnp.abs(f1))))


def test_unrealisable_momentum_rate_keeps_the_contact_constraints(robot, state_terms):
    """Random base orientation: the feet are tilted, the momentum rate cannot be realised by
    admissible wrenches. The QP path then keeps the wrenches admissible (soft momentum QP)
    instead of returning the unconstrained, inadmissible ones; the analytic path does not."""
    t = state_terms
    _, _, out_qp = _step(robot, t, "qp")
    _, _, out_an = _step(robot, t, "analytic")
    assert bool(jnp.all(jnp.isfinite(out_qp.tau)))
    np.testing.assert_allclose(out_an.Ldot_cmd, out_an.Ldot_star, atol=1e-6)
    assert float(jnp.abs(out_qp.Ldot_cmd - out_qp.Ldot_star).max()) > 1.0
    assert float(out_an.qp_violation) > 0.1
    assert float(out_qp.qp_violation) < 1e-3 or bool(out_qp.qp_infeasible)


def test_wrench_map_matches_moment_arithmetic(robot):
    rng = np.random.default_rng(2)
    p, c, f = rng.normal(size=(2, 3)), rng.normal(size=3), rng.normal(size=12)
    A = np.asarray(constraints.wrench_map(contacts.feet_contact_set(robot), jnp.asarray(p), jnp.asarray(c)))
    net_force = f[:3] + f[6:9]
    net_moment = f[3:6] + f[9:] + np.cross(p[0] - c, f[:3]) + np.cross(p[1] - c, f[6:9])
    # Measured 3.8e-15 relative.
    np.testing.assert_allclose(A @ f, np.concatenate([net_force, net_moment]), rtol=1e-12)


@pytest.mark.parametrize(
    "field,value,match",
    [
        ("kp_com", [1.0, np.nan, 1.0], "NaN"),
        ("kd_com", [1.0, -1.0, 1.0], "negative"),
        ("kp_postural", [1.0] * 5, "23 entries"),
        ("kp_com", [1e30, 1.0, 1.0], r"above its range \[0, 10000\]"),
    ],
)
def test_bad_gains_rejected(field, value, match):
    gains = G.default_gains(ICUB).replace(**{field: jnp.asarray(value)})
    with pytest.raises(ValueError, match=match):
        G.validate_gains(gains, 23)


def test_bad_modes_and_gain_files(tmp_path):
    with pytest.raises(ValueError, match=r"unknown forces mode 'lp'.*qp"):
        C.ControllerConfig(forces="lp")
    with pytest.raises(ValueError, match=r"unknown postural variant 'x'.*stable"):
        C.ControllerConfig(postural="x")
    with pytest.raises(ValueError, match=r"qp_warm_start must be True or False, got 1"):
        C.ControllerConfig(qp_warm_start=1)
    with pytest.raises(ValueError, match=r"unknown keys \['kp_foo'\], missing keys \['kp_com'\]"):
        d = G.gains_to_dict(G.default_gains(ICUB))
        d["kp_foo"] = d.pop("kp_com")
        G.gains_from_dict(d)
    with pytest.raises(FileNotFoundError, match="does not exist"):
        G.load_gains(tmp_path / "nope.json")
    with pytest.raises(ValueError, match="is not a file"):
        G.load_gains(tmp_path)
    round_trip = G.gains_from_dict(G.gains_to_dict(G.default_gains(ICUB)))
    np.testing.assert_allclose(round_trip.kp_postural, G.default_gains(ICUB).kp_postural)


def test_postural_projector_derivative_at_a_symmetric_posture(robot):
    """At the home posture (left-right symmetric: mirrored limbs give near-equal eigenvalues of
    X^-1 X^-T) eigh's own JVP of the projector is NaN in float32; spectral_projector's is finite,
    equals eigh's in float64 and matches central differences of the postural projector."""
    tt = _torque_terms(_terms_at(robot, robot.home_qpos(), np.zeros(robot.mj_model.nv)), 1.0)
    A = jnp.linalg.solve(tt.Mbar, jnp.eye(23) + tt.Lambda.T @ tt.Lambda)
    A = A @ A.T
    rng = np.random.default_rng(2)
    dA = jnp.asarray(rng.normal(size=A.shape))
    dA = dA + dA.T
    cut = 1e10  # (damping / tol)^2, as postural_projector's

    def by_eigh(a):
        w, V = jnp.linalg.eigh(a)
        return (V * (w > cut)) @ V.T

    derivative = {}
    for dtype in (jnp.float64, jnp.float32):
        a, da = A.astype(dtype), dA.astype(dtype)
        mine = jax.jvp(lambda x, a=a: torques.spectral_projector(x, cut), (a,), (da,))[1]
        ref = jax.jvp(by_eigh, (a,), (da,))[1]
        assert bool(jnp.all(jnp.isfinite(mine)))
        derivative[dtype] = (mine, ref)
    mine, ref = derivative[jnp.float64]
    np.testing.assert_allclose(mine, ref, atol=1e-9 * float(jnp.abs(ref).max()))
    mine32, ref32 = derivative[jnp.float32]
    assert not bool(jnp.all(jnp.isfinite(ref32)))
    np.testing.assert_allclose(mine32, mine, atol=1e-3 * float(jnp.abs(mine).max()))
    # Through the whole postural projector, against central differences (float64).
    dL = jnp.asarray(rng.normal(size=tt.Lambda.shape))

    def proj(s):
        return torques.postural_projector(tt.Lambda + s * dL, tt.Mbar, 1.0, 1e-5)

    dP = jax.jvp(proj, (0.0,), (1.0,))[1]
    h = 1e-6
    np.testing.assert_allclose(dP, (proj(h) - proj(-h)) / (2 * h), atol=1e-5 * float(jnp.abs(dP).max()))
