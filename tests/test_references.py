"""References: the minimum-jerk ramp and its derivatives, the task schedules."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from wbc_jax.control import references
from wbc_jax.core import constants
from wbc_jax.robot import model


def test_min_jerk_derivatives_match_finite_differences():
    u = np.linspace(-0.2, 1.2, 141)
    p, v, a = constants.min_jerk(u)
    h = 1e-6
    pp, vp, _ = constants.min_jerk(u + h)
    pm, vm, _ = constants.min_jerk(u - h)
    inside = (u > 1e-3) & (u < 1 - 1e-3)
    np.testing.assert_allclose(v[inside], ((pp - pm) / (2 * h))[inside], atol=1e-6)
    np.testing.assert_allclose(a[inside], ((vp - vm) / (2 * h))[inside], atol=1e-5)
    assert p[0] == 0 and p[-1] == 1 and v[0] == v[-1] == 0 and a[0] == a[-1] == 0
    # The same function on JAX arrays, and its autodiff derivative is mj'.
    # Closed forms against NumPy: measured <= 4.1e-15 abs.
    np.testing.assert_allclose(constants.min_jerk(jnp.asarray(u))[0], p, atol=1e-12)
    grad = jax.vmap(jax.grad(lambda x: constants.min_jerk(x)[0]))(jnp.asarray(u))
    np.testing.assert_allclose(grad[inside], v[inside], atol=1e-9)


def _schedule(task, **kw):
    robot = model.load_robot()
    return references.make_schedule(
        task,
        com0=np.array([0.0, 0.0, 0.55]),
        s0=np.zeros(robot.index.n),
        left_sole=np.array([0.0, 0.07, 0.0]),
        joints=robot.index.joints,
        foot_lift_deg=robot.description.foot_lift_deg,
        **kw,
    )


def test_sinusoid_reference_is_consistent():
    sched = _schedule("sinusoid", amplitude=0.02, frequency=0.2)
    ts = np.linspace(0, 5, 11)
    ref = [sched.at(jnp.asarray(t), jnp.float64) for t in ts]
    pos = np.array([r.com_pos for r in ref])
    np.testing.assert_allclose(pos[:, 1], 0.02 * np.sin(2 * np.pi * 0.2 * ts), atol=1e-12)
    vel = jax.jacfwd(lambda t: sched.at(t, jnp.float64).com_pos)(jnp.asarray(1.3))
    np.testing.assert_allclose(vel, sched.at(jnp.asarray(1.3), jnp.float64).com_vel, atol=1e-12)


def test_one_foot_schedule():
    sched = _schedule("one-foot")
    act = lambda t: np.asarray(sched.at(jnp.asarray(t), jnp.float64).activation)  # noqa: E731
    np.testing.assert_allclose(act(3.9), [1, 1])
    np.testing.assert_allclose(act(4.5), [1, 0.5], atol=1e-12)
    np.testing.assert_allclose(act(6.0), [1, 0])
    np.testing.assert_allclose(act(13.0), [1, 1])
    # The CoM is over the left sole during single support, back in the middle at the end.
    np.testing.assert_allclose(sched.at(jnp.asarray(8.0), jnp.float64).com_pos[1], 0.07, atol=1e-12)
    np.testing.assert_allclose(sched.at(jnp.asarray(15.9), jnp.float64).com_pos, [0, 0, 0.55], atol=1e-12)
    assert sched.duration == 16.0


@pytest.mark.parametrize(
    "task, kw, message",
    [
        ("walk", {}, "unknown task 'walk'; valid tasks"),
        ("stand", {"duration": -1.0}, "duration must be positive"),
        ("sinusoid", {"frequency": 0.0}, "frequency > 0"),
    ],
)
def test_bad_schedules_are_named(task, kw, message):
    with pytest.raises(ValueError, match=message):
        _schedule(task, **kw)
