"""The crocoddyl cross-check of the limit (:mod:`wbc_jax.jobs.limit_ddp`): bad input named before
anything solves, the state map between Pinocchio and C MuJoCo, a short DDP from a pushed standing
state whose contact wrenches keep the friction pyramid, the CoP rectangle and the torque bounds,
and (slow) the controller tracking the DDP of a zero push in C MuJoCo, upright by the strict test."""

import dataclasses

import numpy as np
import pytest

from wbc_jax.jobs import limit_ddp
from wbc_jax.robot import bounds

PROBLEM = limit_ddp.crocoddyl_problem()
needs_crocoddyl = pytest.mark.skipif(PROBLEM is not None, reason=PROBLEM or "")
GAINS = "experiments/gains/tuned_gradient.json"


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("ddp_horizon", 0.0, "--ddp-horizon"),
        ("max_iterations", 0, "--max-iterations"),
        ("directions", (), "--directions"),
        ("body", "nose", "--body"),
        ("cop_scale", 1.2, "--cop-scale"),
    ],
)
def test_bad_input_is_named_before_anything_solves(field, value, message):
    cfg = limit_ddp.DdpConfig(**{field: value})
    with pytest.raises(ValueError, match=message) as err:
        cfg.check()
    assert "\n" not in str(err.value)


def test_next_impulse_steps_up_down_then_halves_the_bracket():
    def tests(*pairs):
        return [{"impulse_ns": j, "verified": ok} for j, ok in pairs]

    assert limit_ddp.next_impulse([], 8.0, 30.0) == 8.0
    assert limit_ddp.next_impulse(tests((8.0, True)), 8.0, 30.0) == pytest.approx(10.0)
    assert limit_ddp.next_impulse(tests((8.0, True)), 8.0, 9.0) == 9.0  # capped at the flywheel bound
    assert limit_ddp.next_impulse(tests((8.0, False)), 8.0, 30.0) == pytest.approx(6.4)
    assert limit_ddp.next_impulse(tests((8.0, False), (6.4, False)), 8.0, 30.0) == pytest.approx(5.12)
    assert limit_ddp.next_impulse(tests((8.0, False), (6.4, True)), 8.0, 30.0) == pytest.approx(7.2)
    assert limit_ddp.next_impulse(tests((8.0, True), (10.0, False)), 8.0, 30.0) == pytest.approx(9.0)


class _Threshold:
    """A stand-in for CrossCheck: a push passes up to its direction's threshold; counts the pushes run."""

    def __init__(self, thresholds, tests):
        self.cfg = limit_ddp.DdpConfig(tests=tests)
        self.thresholds, self.runs = np.asarray(thresholds), []

    def run(self, d, impulse):
        self.runs.append((tuple(d), tuple(impulse)))
        return [{"impulse_ns": float(j), "verified": bool(j <= self.thresholds[i])} for i, j in zip(d, impulse)]


def test_bisect_resumes_where_it_stopped():
    start, cap = np.array([8.0, 8.0]), np.array([30.0, 30.0])
    whole = limit_ddp.bisect(_Threshold([9.5, 5.0], 4), start, cap)
    tried = [[r["impulse_ns"] for r in t] for t in whole]
    np.testing.assert_allclose(tried, [[8.0, 10.0, 9.0, 9.5], [8.0, 6.4, 5.12, 4.096]])
    again = _Threshold([9.5, 5.0], 4)  # cut off after 2 tests in direction 0, 3 in direction 1
    resumed = limit_ddp.bisect(again, start, cap, [whole[0][:2], whole[1][:3]])
    assert resumed == whole
    assert [d for d, _ in again.runs] == [(0, 1), (0,)]  # only what was missing, the finished direction left out


def test_resume_refuses_a_file_of_other_settings():
    cfg = limit_ddp.DdpConfig(max_iterations=20, tests=6, directions=(90.0,))
    previous = {
        "config": {**{k: getattr(cfg, k) for k in cfg.__dataclass_fields__}, "tests": 4, "directions": [0.0]},
        "directions": {"0.0": {"tests": [{"impulse_ns": 1.0}]}},
    }
    assert limit_ddp.resumed_tests(previous, cfg, "ddp.json") == {0.0: [{"impulse_ns": 1.0}]}  # more tests, directions
    assert limit_ddp.resumed_tests(None, cfg, "ddp.json") == {}
    del previous["config"]["cop_scale"]  # a file older than the field: its default
    assert limit_ddp.resumed_tests(previous, cfg, "ddp.json") == {0.0: [{"impulse_ns": 1.0}]}
    with pytest.raises(ValueError, match=r"cop_scale=1.0, this run has 0.8"):
        limit_ddp.resumed_tests(previous, dataclasses.replace(cfg, cop_scale=0.8), "ddp.json")
    previous["config"]["max_iterations"] = 40
    with pytest.raises(ValueError, match=r"ddp.json was written with max_iterations=40, this run has 20") as err:
        limit_ddp.resumed_tests(previous, cfg, "ddp.json")
    assert "\n" not in str(err.value)


def test_joint_torque_limits_are_the_plants():
    """ctrlrange capped by actuatorfrcrange: the hips' pitch 55.5, roll 37 N m, the arms' 60."""
    from wbc_jax.robot import model

    m = model.load_robot().mj_model
    np.testing.assert_allclose(
        bounds.joint_torque_limits(m, ("l_hip_pitch", "r_hip_roll", "l_elbow")), [55.5, 37.0, 60.0]
    )
    with pytest.raises(ValueError, match="lacks a joint"):
        bounds.joint_torque_limits(m, ("l_hip_pitch", "tail"))


@pytest.fixture(scope="module")
def check():
    return limit_ddp.CrossCheck(limit_ddp.DdpConfig(directions=(0.0,), gains=GAINS, max_iterations=20))


@needs_crocoddyl
def test_state_map_round_trips(check):
    rng = np.random.default_rng(0)
    qpos = check.search.replay_setup.qpos0.astype(float).copy()
    quat = rng.normal(size=4)
    qpos[3:7] = quat / np.linalg.norm(quat)
    qvel = rng.normal(size=check.state.nv)
    q, v = check.to_mujoco(check.to_pin(qpos, qvel))
    np.testing.assert_allclose(q, qpos, atol=1e-12)
    np.testing.assert_allclose(v, qvel, atol=1e-12)


@needs_crocoddyl
def test_short_ddp_keeps_the_wrench_cone_and_torque_bounds(check):
    """From the standing posture with the CoM moving forward at 0.2 m/s: 10 ticks of BoxFDDP."""
    standing = check.to_pin(check.search.replay_setup.qpos0.astype(float), np.zeros(check.state.nv))
    pushed = standing.copy()
    pushed[check.state.nq] = 0.2  # base x velocity (base axes = world at home)
    sol = check.solve(pushed, standing, T=10)
    assert np.all(np.isfinite(sol["us"])) and sol["iterations"] >= 1
    assert np.all(np.abs(sol["us"]) <= check.torque_limit + 1e-9)
    w = check.contact_forces(sol["solver"])  # (T, 2, 6): force, torque in the CoP-rectangle frame
    fz = w[..., 2]
    mu, tol = check.params.mu, 0.05
    assert fz.min() >= check.params.fz_min * (1 - tol)
    assert np.all(np.abs(w[..., 0]) <= mu * fz * (1 + tol) + 1e-6)
    assert np.all(np.abs(w[..., 1]) <= mu * fz * (1 + tol) + 1e-6)
    half = check.box / 2  # CoP = (-tau_y, tau_x) / f_z inside the rectangle
    assert np.all(np.abs(-w[..., 4] / fz) <= half[0] * (1 + tol))
    assert np.all(np.abs(w[..., 3] / fz) <= half[1] * (1 + tol))
    weight = 9.81 * sum(inertia.mass for inertia in check.pin_model.inertias)
    assert abs(fz.sum(1).mean() / weight - 1.0) < 0.25  # the soles carry the robot


@needs_crocoddyl
@pytest.mark.slow
def test_zero_push_tracked_stays_upright(check):
    """The DDP from the unpushed state, tracked by the controller with feedforward torques in C
    MuJoCo: upright by the strict criterion."""
    rec = check.run(np.array([0]), np.array([0.0]))[0]
    assert rec["verified"], rec
    assert rec["replay_max_foot_slip_m"] < 0.005
    # the stored witness (the torques replayed from the onset) replays to the same outcome on its own
    assert rec["feedforward"].shape == (check.k1 - check.k0 + check.T, len(check.map.joints))
    alone = check.replay_alone(0, 0.0, rec["feedforward"])
    assert alone["verified"] and alone["replay_max_foot_tilt_deg"] == pytest.approx(rec["replay_max_foot_tilt_deg"])
