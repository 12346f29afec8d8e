"""MJX physics on the iCub: the batched rollout does not hang on the CPU, and reverse-mode
gradients through foot contact are the derivative of the loss, through the model's solver and with
the contact solver differentiated implicitly (the tuning issue depends on both)."""

import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from mujoco import mjx

from wbc_jax.sim import physics

ROLLOUT_SCRIPT = textwrap.dedent(
    """
    import jax, jax.numpy as jnp
    from mujoco import mjx
    from wbc_jax.robot import model
    r = model.load_robot("icub")
    mx = r.mjx_model
    d0 = mjx.make_data(r.mj_model).replace(qpos=jnp.asarray(r.home_qpos()))
    batch = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (256,) + x.shape), d0)
    batch = batch.replace(qvel=batch.qvel + 0.01 * jax.random.normal(jax.random.key(0), batch.qvel.shape))
    @jax.jit
    def rollout(d):
        return jax.lax.scan(lambda d, _: (jax.vmap(mjx.step, in_axes=(None, 0))(mx, d), None), d, None, length=10)[0]
    for _ in range(3):  # jax 0.10.2 returned the first call and wedged on a later one
        out = rollout(batch)
        out.qpos.block_until_ready()
    print("finite", bool(jnp.all(jnp.isfinite(out.qpos))))
    """
)


def test_vmapped_rollout_of_256_envs_completes_on_cpu():
    """Regression for the jax 0.10.2 CPU deadlock (shared/reference/measured.md): a jitted,
    vmapped rollout of 256 iCubs x 10 steps (the hang came on a later call, not a longer one), called
    three times, must finish. It runs in a subprocess so that a wedged XLA thread pool fails this test
    instead of hanging CI."""
    proc = subprocess.run(
        [sys.executable, "-c", ROLLOUT_SCRIPT],
        capture_output=True,
        text=True,
        timeout=420,
        env={**__import__("os").environ, "JAX_PLATFORMS": "cpu"},
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "finite True" in proc.stdout


@pytest.mark.slow  # the unrolled solver's derivative; the default suite checks the implicit one (below): nightly
def test_reverse_mode_gradient_through_standing_contact_is_the_derivative(robot, mx):
    """Reverse mode through 100 steps of MJX with both feet on the floor equals the central difference
    of the loss, in magnitude (float64).

    The loss is piecewise smooth in kp: the contact solver's discrete choices (one Newton iteration,
    its line search, the active constraint rows) change with kp and the loss jumps between pieces
    (secant slopes over +-1e-2 range over +-1.7e-5 against a derivative of -1.5e-8). A central
    difference over +-5 (2.5 % of kp, the earlier check) spans many jumps and came out 2.2x off,
    with the right sign by luck; over +-1e-5 and +-3e-5 it stays on the piece at kp = 200, where
    it equals the reverse-mode gradient (and forward mode) to 3e-4. So the gradient is the exact
    derivative of the computed loss; what a gradient step sees beyond a piece is the solver's jumps."""
    idx = robot.index
    mx1 = mx.replace(opt=mx.opt.replace(iterations=1, ls_iterations=4))  # scan-safe solver
    qpos0 = jnp.asarray(robot.home_qpos())
    s_home = qpos0[idx.qpos_joints]
    d0 = mjx.make_data(robot.mj_model).replace(qpos=qpos0)

    def loss(kp):
        def step(d, _):
            s, s_dot = d.qpos[idx.qpos_joints], d.qvel[idx.dof_joints]
            # PD around home plus the joint part of the bias (gravity compensation).
            tau = kp * (s_home - s) - 5.0 * s_dot + d.qfrc_bias[idx.dof_joints]
            d = mjx.step(mx1, d.replace(ctrl=jnp.zeros(idx.nu).at[idx.actuators].set(tau)))
            return d, (d.qpos[2], d._impl.contact.dist)

        _, (z, dist) = jax.lax.scan(step, d0, None, length=100)
        return jnp.mean((z - qpos0[2]) ** 2), dist

    (value, dist), grad = jax.jit(jax.value_and_grad(loss, has_aux=True))(200.0)
    # Contact is active all along: each foot touches the floor at every step (dist <= 0.5 mm;
    # one solver iteration lets the soles rock by ~1 mm at the far corners).
    per_foot = np.asarray(dist).reshape(-1, 2, 4).min(axis=2)
    assert np.all(per_foot < 5e-4), per_foot.max()
    assert np.isfinite(float(value)) and float(value) > 0 and np.isfinite(float(grad))
    kps = 200.0 + np.array([3e-5, -3e-5, 1e-5, -1e-5])
    values = np.asarray(jax.jit(jax.vmap(lambda kp: loss(kp)[0]))(jnp.asarray(kps)))
    fd = [(values[0] - values[1]) / 6e-5, (values[2] - values[3]) / 2e-5]
    print(f"reverse-mode dL/dkp = {float(grad):.6e}, central differences = {fd[0]:.6e}, {fd[1]:.6e}")
    np.testing.assert_allclose(fd, float(grad), rtol=1e-3)


def _standing_loss(robot, mx, push=0.0):
    """loss(kp): mean squared height (and, pushed, forward) drift of the base over 100 steps of a PD law
    around the home posture, the base pushed forward with ``push`` N."""
    idx = robot.index
    qpos0 = jnp.asarray(robot.home_qpos())
    s_home = qpos0[idx.qpos_joints]
    d0 = mjx.make_data(robot.mj_model).replace(qpos=qpos0)
    xfrc = jnp.zeros((robot.mj_model.nbody, 6)).at[1, 0].set(push)

    def loss(kp):
        def step(d, _):
            s, s_dot = d.qpos[idx.qpos_joints], d.qvel[idx.dof_joints]
            # PD around home plus the joint part of the bias (gravity compensation).
            tau = kp * (s_home - s) - 5.0 * s_dot + d.qfrc_bias[idx.dof_joints]
            d = mjx.step(mx, d.replace(ctrl=jnp.zeros(idx.nu).at[idx.actuators].set(tau), xfrc_applied=xfrc))
            return d, (d.qpos[2] + d.qpos[0], d._impl.contact.dist)

        _, (z, dist) = jax.lax.scan(step, d0, None, length=100)
        return jnp.mean((z - qpos0[2] - qpos0[0]) ** 2), dist

    return loss


# A block standing on four sphere feet (the iCub's soles are spheres on the floor plane, pyramidal cones, Newton).
FOUR_FEET = """
<mujoco>
  <option timestep="0.005"/>
  <worldbody>
    <geom type="plane" size="1 1 0.1"/>
    <body pos="0 0 0.05">
      <freejoint/>
      <geom type="sphere" size="0.02" pos="0.1 0.05 -0.03" mass="0.5"/>
      <geom type="sphere" size="0.02" pos="0.1 -0.05 -0.03" mass="0.5"/>
      <geom type="sphere" size="0.02" pos="-0.1 0.05 -0.03" mass="0.5"/>
      <geom type="sphere" size="0.02" pos="-0.1 -0.05 -0.03" mass="0.5"/>
    </body>
  </worldbody>
</mujoco>
"""


# Its reverse-mode compile took 60 s of the 2-core suite: nightly (`slow`). The default suite keeps the implicit
# solver derivative's own checks (the friction-loss rows below, in each regime, and their gradient).
@pytest.mark.slow
def test_implicit_gradient_through_four_standing_feet_matches_central_differences():
    """The implicit solver derivative through standing contact at small size (the iCub's, below, took 117 s of
    the 2-core suite): a block on four sphere feet held by
    static friction (the pyramid's rows active at every step), a PD force and torque of gain kp on it;
    reverse mode through 50 steps equals a central difference of the plain rollout (float64)."""
    import mujoco

    m = mujoco.MjModel.from_xml_string(FOUR_FEET)
    mx, d0 = mjx.put_model(m), mjx.make_data(m)

    def loss(kp):
        def step(d, _):
            force = kp * (0.02 - d.qpos[0]) - 2.0 * d.qvel[0]
            torque = 0.02 * kp * (0.1 - d.qpos[6])
            d = mjx.step(mx, d.replace(xfrc_applied=jnp.zeros((m.nbody, 6)).at[1, 0].set(force).at[1, 5].set(torque)))
            return d, (d.qpos[0], d._impl.contact.dist)

        _, (x, dist) = jax.lax.scan(step, d0, None, length=50)
        return jnp.mean((x - 0.02) ** 2), dist

    with physics.implicit_solver():
        (value, dist), grad = jax.jit(jax.value_and_grad(loss, has_aux=True))(20.0)
    assert np.asarray(dist).max() < 1e-12, "every foot touches the floor at every step (0 at the first)"
    assert np.isfinite(float(value)) and float(grad) != 0.0
    plain = jax.jit(lambda kp: loss(kp)[0])
    eps = 1e-2
    fd = (float(plain(20.0 + eps)) - float(plain(20.0 - eps))) / (2 * eps)
    assert float(grad) == pytest.approx(fd, rel=1e-6)  # measured: 2.4e-10 (the unrolled solver's gradient: 3e-15)


@pytest.mark.slow  # 117 s of the 2-core suite (compiling reverse mode through the iCub's step); the four feet above
def test_reverse_mode_gradient_through_standing_contact_matches_central_differences(robot, mx):
    """Through 100 steps of standing contact with the model's solver (Newton, 4 iterations), reverse mode
    with the implicit solver derivative (physics.implicit_solver) equals a central difference of the
    plain rollout (float64)."""
    loss = _standing_loss(robot, mx, push=30.0)
    with physics.implicit_solver():
        (value, dist), grad = jax.jit(jax.value_and_grad(loss, has_aux=True))(200.0)
    # Contact is active all along: each foot touches the floor at every step.
    per_foot = np.asarray(dist).reshape(-1, 2, 4).min(axis=2)
    assert np.all(per_foot < 5e-4), per_foot.max()
    assert np.isfinite(float(value)) and float(grad) != 0.0
    loss_jit = jax.jit(lambda kp: loss(kp)[0])
    eps = 0.1
    fd = (float(loss_jit(200.0 + eps)) - float(loss_jit(200.0 - eps))) / (2 * eps)
    assert float(grad) == pytest.approx(fd, rel=1e-4)  # measured: 4.5e-7


@pytest.mark.slow
def test_implicit_and_unrolled_solver_gradients_agree(robot, mx):
    """The implicit derivative at the solver's solution and reverse mode through its unrolled iterations
    (physics.fixed_iteration_solver) give the same gradient (measured: within 1e-15 relative)."""
    loss = _standing_loss(robot, mx, push=30.0)
    grads = {}
    for kind in physics.SOLVER_GRADIENTS:
        with physics.gradient_solver(kind, int(robot.mj_model.opt.iterations)):
            grads[kind] = float(jax.jit(jax.grad(lambda kp: loss(kp)[0]))(200.0))
    assert grads["implicit"] == pytest.approx(grads["unrolled"], rel=1e-9)


# A pendulum whose hinge has friction loss (as Talos's joints): it slides (the friction-loss row
# saturated, a constant force) and sticks (the row quadratic) within one rollout.
FRICTION_PENDULUM = """
<mujoco>
  <option timestep="0.01"/>
  <worldbody>
    <body>
      <joint name="hinge" axis="0 1 0" frictionloss="0.8" damping="0.05"/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.4" size="0.03" mass="1"/>
    </body>
  </worldbody>
  <actuator><motor joint="hinge"/></actuator>
</mujoco>
"""


def test_implicit_solver_derivative_of_a_friction_loss_row_in_each_regime():
    """Issue 47: d qacc / d ctrl of the friction pendulum through the implicit solver step is 1 / I
    while it slides (the friction-loss row's force is the constant -+f) and 1 / (I + D) at rest (the
    row quadratic, stiffness D): the regime held fixed at the solution, as MJX's solver defines it."""
    import mujoco

    m = mujoco.MjModel.from_xml_string(FRICTION_PENDULUM)
    mx, d0 = mjx.put_model(m), mjx.make_data(m)

    def acc(u, qvel):
        d = mjx.forward(mx, d0.replace(qvel=jnp.array([qvel]), ctrl=u[None]))
        return d.qacc[0], (d._impl.efc_D[0], d._impl.efc_force[0])

    with physics.implicit_solver():
        grad, (D, force) = jax.jit(jax.vmap(jax.grad(acc, has_aux=True), in_axes=(None, 0)))(
            jnp.asarray(0.0), jnp.array([1.0, 0.0])
        )
    inertia = float(m.body_inertia[1, 1] + m.body_mass[1] * m.body_ipos[1, 2] ** 2)  # about the hinge
    assert abs(float(force[0])) == pytest.approx(0.8) and abs(float(force[1])) < 0.79  # sliding, sticking
    assert float(grad[0]) == pytest.approx(1.0 / inertia, rel=1e-9)
    assert float(grad[1]) == pytest.approx(1.0 / (inertia + float(D[1])), rel=1e-9)


@pytest.mark.slow  # 35 s on the loaded 2-core machine (compiling a reverse-mode rollout)
def test_implicit_solver_gradient_through_joint_friction_loss_matches_central_differences():
    """Issue 47: the implicit solver derivative holds the friction-loss rows' regime (sliding:
    constant force; sticking: quadratic) fixed at the solution, as MJX's solver defines the rows; reverse
    mode through 1.5 s of a PD pendulum with friction loss equals a central difference (float64)."""
    import mujoco

    m = mujoco.MjModel.from_xml_string(FRICTION_PENDULUM)
    mx = mjx.put_model(m)

    def loss(kp):
        def step(d, _):
            tau = kp * (0.6 - d.qpos[0]) - 0.3 * d.qvel[0]
            d = mjx.step(mx, d.replace(ctrl=tau[None]))
            return d, (d.qpos[0], d._impl.efc_force[0])

        _, (q, f) = jax.lax.scan(step, mjx.make_data(m), None, length=150)
        return jnp.mean((q - 0.6) ** 2), f

    # One program: the gradient at kp and the losses at kp +- eps (the implicit step's value is the
    # solver's solution, so these are the plain rollout's losses).
    eps = 1e-4
    with physics.implicit_solver():
        (values, force), grads = jax.jit(jax.vmap(jax.value_and_grad(loss, has_aux=True)))(
            jnp.array([4.0, 4.0 + eps, 4.0 - eps])
        )
    force = np.abs(np.asarray(force[0]))
    assert np.any(np.isclose(force, 0.8)) and np.any(force < 0.79), "both regimes of the friction-loss row"
    fd = (float(values[1]) - float(values[2])) / (2 * eps)
    assert float(grads[0]) == pytest.approx(fd, rel=1e-6)  # measured: 1e-10
