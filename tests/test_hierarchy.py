"""Motion-task hierarchy: frame kinematics against C MuJoCo, strict priority, an independent NumPy
hierarchical least-squares reference, the dynamics, and clear errors for bad stacks (float64)."""

import dataclasses

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
import scipy.linalg
from conftest import c_data
from mujoco import mjx

from wbc_jax.control import hierarchy, task_rows, tasks, torques
from wbc_jax.control.gains import default_gains
from wbc_jax.control.hierarchy import TaskLevel
from wbc_jax.robot import dynamics

FRAME0 = 2  # the stack's frames follow the two soles'


@pytest.fixture(scope="module")
def state(robot):
    """A standing state with joint offsets and random velocities, its terms and torque terms."""
    rng = np.random.default_rng(11)
    qpos = robot.home_qpos()
    qpos[robot.index.qpos_joints] += rng.uniform(-0.15, 0.15, robot.index.n)
    qvel = rng.normal(scale=0.5, size=robot.mj_model.nv)
    dx = mjx.make_data(robot.mj_model).replace(qpos=jnp.asarray(qpos), qvel=jnp.asarray(qvel))
    stack = tasks.resolve(
        robot,
        [
            tasks.MotionTask("r_hand", "position", frame="r_hand", kp=50.0),
            tasks.MotionTask("l_hand", "position", frame="l_hand", kp=50.0),
            tasks.MotionTask("chest", "orientation", frame="chest", kp=20.0),
            tasks.MotionTask("posture", "postural"),
        ],
        qpos=robot.home_qpos(),
    )
    # The soles' frames first (the contacts), then the stack's.
    frames = dynamics.sole_frames(robot.index) + stack.frames
    t = jax.jit(lambda m, d: dynamics.terms(m, d, robot.index, frames))(robot.mjx_model, dx)
    g = default_gains(robot.description, jnp.float64)
    tt = torques.torque_terms(
        t,
        t.J_frames[:2].reshape(12, -1),
        t.Jdot_nu_frames[:2].reshape(12),
        postural="stable",
        kp_postural=g.kp_postural,
        kd_postural=g.kd_postural,
        s_des=jnp.asarray(t.s) * 0.9,
    )
    # Feet wrenches: the weight split between the feet plus a random part.
    f = np.tile([0, 0, 9.81 * robot.index.mass / 2, 0, 0, 0], 2) + rng.normal(scale=5.0, size=12)
    return {"qpos": qpos, "qvel": qvel, "t": t, "tt": tt, "f": jnp.asarray(f), "stack": stack, "rng": rng}


def _levels(state, time=0.3):
    return task_rows.levels(state["stack"], state["t"], jnp.asarray(time), FRAME0)


def test_frame_jacobians_match_c_mujoco(robot, state):
    """J of the hand point (mixed representation) against mj_jac, and Jdot nu against mj_jacDot."""
    m = robot.mj_model
    d = c_data(robot, state["qpos"], state["qvel"])
    mujoco.mj_comVel(m, d)
    stack, t = state["stack"], state["t"]
    nu = np.asarray(state["t"].nu)
    for k, (body, offset) in enumerate(zip(stack.bodies, stack.offsets, strict=True)):
        point = d.xpos[body] + d.xmat[body].reshape(3, 3) @ np.asarray(offset)
        # Ours against C MuJoCo's mj_jac/mj_jacDot: measured <= 1.3e-15 abs with XLA held to AVX2.
        np.testing.assert_allclose(t.W_p_frames[FRAME0 + k], point, atol=1e-12)
        jacp, jacr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
        mujoco.mj_jac(m, d, jacp, jacr, point, body)
        # Same point velocity whatever the velocity coordinates: J_mixed nu = J_mj qvel.
        np.testing.assert_allclose(
            t.J_frames[FRAME0 + k] @ nu, np.concatenate([jacp, jacr]) @ state["qvel"], atol=1e-10
        )
        jdp, jdr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
        mujoco.mj_jacDot(m, d, jdp, jdr, point, body)
        np.testing.assert_allclose(t.Jdot_nu_frames[FRAME0 + k], np.concatenate([jdp, jdr]) @ state["qvel"], atol=1e-8)


def test_no_motion_task_is_the_two_level_law(state):
    tt, f = state["tt"], state["f"]
    sol = hierarchy.solve(state["t"], tt, f, ())
    # Two paths to the same torques: measured 1.8e-15 abs, 1.5e-15 relative (AVX2).
    np.testing.assert_allclose(sol.tau, tt.Sigma @ f + tt.tau_model, rtol=1e-12, atol=1e-10)


def test_predicted_accelerations_satisfy_the_dynamics(state):
    t, tt, f = state["t"], state["tt"], state["f"]
    sol = hierarchy.solve(t, tt, f, _levels(state))
    residual = t.M @ sol.nu_dot + (t.h - t.tau_passive) - tt.J_c.T @ f - jnp.zeros_like(t.h).at[6:].set(sol.tau)
    assert float(jnp.max(jnp.abs(residual))) < 1e-8


def test_motion_torques_leave_the_contact_accelerations(state):
    """The motion tasks' torques lie in the null space of Lambda = J_c M^-1 B: they change no contact
    acceleration, so the contact wrenches of the force task are left as commanded."""
    t, tt, f = state["t"], state["tt"], state["f"]
    sol = hierarchy.solve(t, tt, f, _levels(state))
    assert float(jnp.max(jnp.abs(sol.tau_motion))) > 1.0  # the tasks do act
    contact_acc = tt.J_c @ jnp.linalg.solve(t.M, jnp.zeros_like(t.h).at[6:].set(tt.N_Lambda @ sol.tau_motion))
    assert float(jnp.max(jnp.abs(contact_acc))) < 1e-8 * float(jnp.max(jnp.abs(sol.tau_motion)))


def test_strict_priority(state):
    """Adding or changing lower levels leaves the accelerations of the levels above unchanged."""
    t, tt, f, rng = state["t"], state["tt"], state["f"], state["rng"]
    L = _levels(state)
    only_first = hierarchy.solve(t, tt, f, L[:1])
    two = hierarchy.solve(t, tt, f, L[:2])
    changed = L[1].replace(nu_dot_star=L[1].nu_dot_star + rng.normal(scale=10.0, size=3))
    two_changed = hierarchy.solve(t, tt, f, (L[0], changed))
    three = hierarchy.solve(t, tt, f, L)
    # A lower level that conflicts with the first (the same hand, another reference).
    conflict = hierarchy.solve(t, tt, f, (L[0], L[0].replace(nu_dot_star=L[0].nu_dot_star + 5.0)))
    for other in (two, two_changed, three, conflict):
        assert float(jnp.max(jnp.abs(other.task_acc[0] - only_first.task_acc[0]))) < 1e-8
    assert float(jnp.max(jnp.abs(three.task_acc[1] - two.task_acc[1]))) < 1e-8
    # ... while the lower levels do change the torques and their own accelerations.
    assert float(jnp.max(jnp.abs(two_changed.task_acc[1] - two.task_acc[1]))) > 1.0
    # The feasible first level is achieved (its damping is the only error).
    err = only_first.task_acc[0] - L[0].nu_dot_star
    assert float(jnp.max(jnp.abs(err))) < 1e-3 * float(jnp.max(jnp.abs(L[0].nu_dot_star)) + 1.0)


def _reference_hls(t, tt, f, levels):
    """Dense hierarchical least squares in NumPy (written from the equations, not from the JAX code):
    the motion torque, restricted to the null space of Lambda = J_c M^-1 B (explicit SVD basis),
    solves level by level min |J_i M^-1 B x - b_i| over the solutions of the levels above (explicit
    null-space bases), on top of the model part of the postural torque; the postural feedback u_0
    is projected on the null space of the stacked J_i M^-1 B N_Lambda (pinv)."""
    M, J_c = np.asarray(t.M), np.asarray(tt.J_c)
    h = np.asarray(t.h - t.tau_passive)
    n, nv = tt.N_Lambda.shape[0], M.shape[0]
    f = np.asarray(f)
    B = np.eye(nv)[:, 6:]
    Lam = J_c @ np.linalg.solve(M, B)
    Lam_pinv = Lam.T @ np.linalg.inv(Lam @ Lam.T + 1.0 * np.eye(12))  # damping 1: the controller's
    N_lam = np.eye(n) - Lam_pinv @ Lam
    tau_c = Lam_pinv @ (J_c @ np.linalg.solve(M, h - J_c.T @ f) - np.asarray(tt.Jdot_nu_c))
    Mb, Msb = M[:6, :6], M[6:, :6]
    tau0_model = h[6:] - Msb @ np.linalg.solve(Mb, h[:6]) - (J_c[:, 6:].T - Msb @ np.linalg.solve(Mb, J_c[:, :6].T)) @ f
    nu_dot_c = np.linalg.solve(M, B @ (tau_c + N_lam @ tau0_model) + J_c.T @ f - h)
    x, Z = np.zeros(n), scipy.linalg.null_space(Lam, rcond=1e-10)  # motion torques: x + Z y
    stacked = np.zeros((0, n))
    for level in levels:
        J = np.asarray(level.J)
        A = J @ np.linalg.solve(M, B)
        b = np.asarray(level.nu_dot_star - level.Jdot_nu) - J @ nu_dot_c
        y, *_ = np.linalg.lstsq(A @ Z, b - A @ x, rcond=1e-10)
        x = x + Z @ y
        Z = Z @ scipy.linalg.null_space(A @ Z, rcond=1e-10)
        stacked = np.vstack([stacked, A @ N_lam])
    P = np.eye(n) - np.linalg.pinv(stacked, rcond=1e-10) @ stacked if len(stacked) else np.eye(n)
    tau0 = tau0_model + x + P @ np.asarray(tt.u0)
    return tau_c + N_lam @ tau0


def test_matches_an_independent_hierarchical_least_squares(state):
    t, tt, f = state["t"], state["tt"], state["f"]
    L = _levels(state)
    sol = hierarchy.solve(t, tt, f, L, solution_damping=1e-14, projector_reg=1e-15, effort_damping=0.0)
    ref = _reference_hls(t, tt, f, L)
    np.testing.assert_allclose(sol.tau, ref, rtol=1e-6, atol=1e-6 * np.abs(ref).max())
    # ... and with the postural task alone (two-level problem of the seed paper).
    np.testing.assert_allclose(
        hierarchy.solve(t, tt, f, (), effort_damping=0.0).tau,
        _reference_hls(t, tt, f, ()),
        rtol=1e-8,
        atol=1e-8 * np.abs(ref).max(),
    )


def test_equal_priority_weights(robot, state):
    """Two tasks in one level: a heavier weight pulls the compromise towards that task."""
    t, tt, f = state["t"], state["tt"], state["f"]
    errors = []
    for w in (1.0, 100.0):
        stack = tasks.resolve(
            robot,
            [
                tasks.MotionTask("a", "position", frame="r_hand", priority=0, weight=w),
                tasks.MotionTask(
                    "b",
                    "position",
                    frame="r_hand",
                    offset=(0.0, 0.0, 0.0),
                    priority=0,
                    reference=tasks.TaskReference(target=(0.3, -0.2, 0.8)),
                ),
                tasks.MotionTask("posture", "postural", priority=1),
            ],
        )
        assert stack.n_levels == 1
        L = task_rows.levels(stack, t, jnp.asarray(0.0), FRAME0)  # r_hand is the stack's frame 0 in both
        sol = hierarchy.solve(t, tt, f, L)
        star_a = L[0].nu_dot_star[:3] / np.sqrt(w)
        errors.append(float(jnp.linalg.norm(sol.task_acc[0][:3] / np.sqrt(w) - star_a)))
    assert errors[1] < 0.1 * errors[0]


def test_gradients_are_finite_at_a_singular_level(state):
    """Two copies of one task in a level (rank-deficient): torques and gradients stay finite."""
    t, tt, f = state["t"], state["tt"], state["f"]
    L0 = _levels(state)[0]
    singular = TaskLevel(
        J=jnp.concatenate([L0.J, L0.J]),
        Jdot_nu=jnp.concatenate([L0.Jdot_nu] * 2),
        nu_dot_star=jnp.concatenate([L0.nu_dot_star, L0.nu_dot_star + 1.0]),
    )
    loss = lambda ff: jnp.sum(hierarchy.solve(t, tt, ff, (singular, _levels(state)[2])).tau ** 2)  # noqa: E731
    value, grad = jax.value_and_grad(loss)(f)
    assert np.isfinite(float(value)) and bool(jnp.all(jnp.isfinite(grad)))


def test_circle_reference_derivatives(robot):
    stack = tasks.resolve(
        robot,
        [
            tasks.MotionTask(
                "hand",
                "position",
                frame="r_hand",
                reference=tasks.TaskReference(kind="circle", radius=0.05, frequency=0.5, ramp=1.0),
            ),
            tasks.MotionTask("posture", "postural"),
        ],
    )
    task = stack.tasks[0]
    p0, v0, a0 = task_rows.reference_at(task, 0.0, jnp.float64)
    np.testing.assert_allclose(p0, task.target, atol=1e-12)  # starts at the hand, at rest
    assert float(jnp.abs(v0).max()) == 0.0 and float(jnp.abs(a0).max()) == 0.0
    t, eps = 2.3, 1e-5
    p, v, a = task_rows.reference_at(task, t, jnp.float64)
    pp, vp, _ = task_rows.reference_at(task, t + eps, jnp.float64)
    pm, vm, _ = task_rows.reference_at(task, t - eps, jnp.float64)
    np.testing.assert_allclose(v, (pp - pm) / (2 * eps), atol=1e-8)
    np.testing.assert_allclose(a, (vp - vm) / (2 * eps), atol=1e-6)
    # After the ramp: a circle of radius 5 cm in the y-z plane.
    center = np.asarray(task.target) - np.array([0, 0.05, 0])
    assert abs(float(jnp.linalg.norm(p - center)) - 0.05) < 1e-12 and abs(float(p[0] - center[0])) < 1e-12
    # Signed axes: plane (-z, y) leaves the start point along +y and reaches 2 r above it at half a period.
    signed = dataclasses.replace(task, reference=dataclasses.replace(task.reference, plane=("-z", "y")))
    p_half, _, _ = task_rows.reference_at(signed, 3.0, jnp.float64)  # t = 3 s: after the ramp, w t = 3 pi
    np.testing.assert_allclose(p_half - np.asarray(task.target), [0.0, 0.0, 0.1], atol=1e-12)
    p_quarter, _, _ = task_rows.reference_at(signed, 2.5, jnp.float64)  # w t = 2.5 pi: +r along y, +r along z
    np.testing.assert_allclose(p_quarter - np.asarray(task.target), [0.0, 0.05, 0.05], atol=1e-12)


POSTURE = tasks.MotionTask("posture", "postural")


@pytest.mark.parametrize(
    "stack, message",
    [
        ([tasks.MotionTask("h", "position", frame="r_palm"), POSTURE], "unknown frame 'r_palm'"),
        (
            [
                tasks.MotionTask("h", "position", frame="r_hand", reference=tasks.TaskReference(target=(0.1, 0.2))),
                POSTURE,
            ],
            "must have 3 finite entries",
        ),
        (
            [tasks.MotionTask("h", "position", frame="r_hand"), tasks.MotionTask("h", "com"), POSTURE],
            "duplicate task names ['h']",
        ),
        ([tasks.MotionTask("h", "position", frame="r_hand")], "must end with the postural task"),
        ([POSTURE, tasks.MotionTask("h", "position", frame="r_hand")], "must end with the postural task"),
        ([tasks.MotionTask("h", "pose", frame="r_hand"), POSTURE], "unknown kind 'pose'"),
        ([tasks.MotionTask("j", "joints", joints=("r_elbow", "r_wrist")), POSTURE], "unknown joint 'r_wrist'"),
        ([tasks.MotionTask("h", "position", frame="r_hand", kp=-1.0), POSTURE], "task gain kp"),
        (
            [tasks.MotionTask("h", "position", frame="r_hand", weight=0.0), POSTURE],
            "weight must be in (0, 1e+06], got 0.0",
        ),
        (
            [
                tasks.MotionTask(
                    "h",
                    "com",
                    reference=tasks.TaskReference(kind="circle", radius=0.05, frequency=0.5, plane=("-y", "y")),
                ),
                POSTURE,
            ],
            "circle plane must be two different axes",
        ),
        (
            [tasks.MotionTask("h", "com", reference=tasks.TaskReference(kind="spiral")), POSTURE],
            "unknown reference kind 'spiral'",
        ),
        (
            [
                tasks.MotionTask("h", "position", frame="r_hand", priority=2),
                tasks.MotionTask("posture", "postural", priority=1),
            ],
            "lowest priority",
        ),
    ],
)
def test_bad_stacks_are_named(robot, stack, message):
    with pytest.raises(ValueError) as err:
        tasks.resolve(robot, stack)
    assert message in str(err.value)


def test_stack_from_dicts(robot):
    stack = tasks.resolve(
        robot,
        [
            {
                "name": "hand",
                "kind": "position",
                "frame": "r_hand",
                "kp": [10, 20, 30],
                "reference": {"kind": "circle", "radius": 0.05, "frequency": 0.5},
            },
            {"name": "posture", "kind": "postural"},
        ],
    )
    assert stack.tasks[0].kp == (10.0, 20.0, 30.0) and stack.tasks[0].reference.kind == "circle"
    with pytest.raises(ValueError, match="unknown keys"):
        tasks.resolve(robot, [{"name": "hand", "kind": "position", "frame": "r_hand", "gain": 3}, POSTURE])


def test_joints_all_is_every_joint_at_home(robot):
    stack = tasks.resolve(
        robot,
        [
            {"name": "all_joints", "kind": "joints", "joints": "all", "kp": 100.0},
            {"name": "posture", "kind": "postural"},
        ],
    )
    task = stack.tasks[0]
    assert len(task.kp) == robot.index.n == 23
    home = robot.home_qpos()
    np.testing.assert_allclose(task.target, [home[robot.index.qpos_joints[k]] for k in range(robot.index.n)])
    # The Python API with a bare string (not a list): the same task, not one-letter joint names.
    bare = tasks.resolve(
        robot,
        [tasks.MotionTask("all_joints", "joints", joints="all", kp=100.0), tasks.MotionTask("posture", "postural")],
    )
    assert bare.tasks[0].dofs == task.dofs == tuple(range(23))
    one = tasks.resolve(
        robot, [tasks.MotionTask("elbow", "joints", joints="r_elbow"), tasks.MotionTask("p", "postural")]
    )
    assert one.tasks[0].dofs == (robot.index.joints.index("r_elbow"),)


def test_effort_bounded_gain_is_the_stated_filter():
    """hierarchy._effort_gain: with G_hat = L M L^T (M's eigenvalues rho^2 in [0, 1]) and G_0 = L L^T,
    G_hat W = L phi(M) L^-1 with phi(rho^2) = rho^4 / (rho^4 + mu (1 - rho^2)^2) (module docstring);
    mu = 0 is the plain pseudo-inverse of the projected task (phi = 1 where rho > 0)."""
    rng = np.random.default_rng(3)
    m = 4
    L = np.tril(rng.normal(size=(m, m))) + 3 * np.eye(m)
    Q, _ = np.linalg.qr(rng.normal(size=(m, m)))
    rho2 = np.array([1.0, 0.81, 0.49, 0.16])
    M = Q @ np.diag(rho2) @ Q.T
    G_0, G_hat = L @ L.T, L @ M @ L.T
    for mu, phi in ((1.0, np.array([1.0, 0.95, 0.48, 0.035])), (0.0, np.ones(m))):
        W = np.asarray(hierarchy._effort_gain(jnp.asarray(G_hat), jnp.asarray(G_0), mu, 1e-14))
        expected = L @ Q @ np.diag(rho2**2 / (rho2**2 + mu * (1 - rho2) ** 2)) @ Q.T @ np.linalg.inv(L)
        np.testing.assert_allclose(G_hat @ W, expected, atol=1e-9)
        # the docstring's figures: 100 % at rho = 1, 95 % at 0.9, 48 % at 0.7, 3.5 % at 0.4
        np.testing.assert_allclose(rho2**2 / (rho2**2 + mu * (1 - rho2) ** 2), phi, atol=3e-3)
