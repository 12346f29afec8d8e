"""The LIP + flywheel bound (wbc_jax.robot.bounds): its limits, a closed form, and its derivation
checked by integrating the ODE and by the discretised optimal control (a linear programme).
numpy/scipy and C MuJoCo only, nothing compiles."""

import dataclasses
import math

import numpy as np
import pytest
from scipy.optimize import linprog

from wbc_jax.core import constants
from wbc_jax.jobs import sweep_table
from wbc_jax.robot import bounds
from wbc_jax.robot import model as model_lib

AZIMUTHS = [i * 11.25 for i in range(32)]


@pytest.fixture(scope="module")
def robot():
    return model_lib.load_robot("icub")


@pytest.fixture(scope="module")
def wheel(robot):
    return bounds.flywheel_model(robot)


def test_flywheel_model_reads_the_mjcf(wheel):
    # Hips: actuatorfrcrange 55.5 (pitch) and 37 (roll) N m below the 60 N m ctrlrange, two in parallel.
    assert (wheel.torque_pitch, wheel.torque_roll) == pytest.approx((111.0, 74.0))
    # Home hip pitch 10 deg in the range [-45, 134] deg; hip roll 0 in [-20, 120] deg (adduction limits).
    assert wheel.flexion == pytest.approx(2.33874119767 - 0.174532925199)
    assert wheel.extension == pytest.approx(0.785398163397 + 0.174532925199)
    assert wheel.roll == pytest.approx(0.349065850399)
    assert 2.0 < wheel.inertia_pitch < 3.0 and 2.0 < wheel.inertia_roll < 3.0  # whole-body centroidal (> trunk's)


@pytest.mark.parametrize("field", ["torque_pitch", "flexion"])
def test_flywheel_bound_is_the_lip_bound_without_torque_or_range(robot, wheel, field):
    none = {
        "torque_pitch": dict(torque_pitch=0.0, torque_roll=0.0),
        "flexion": dict(flexion=0.0, extension=0.0, roll=0.0),
    }
    lip = sweep_table.lip_bound(robot, AZIMUTHS)
    fly = bounds.flywheel_bound(robot, AZIMUTHS, "chest", dataclasses.replace(wheel, **none[field]))
    for az in AZIMUTHS:
        assert fly[az]["impulse_bound_ns"] == pytest.approx(lip[az]["impulse_bound_ns"], rel=1e-12)


def test_flywheel_bound_exceeds_the_lip_bound(robot):
    lip = sweep_table.lip_bound(robot, AZIMUTHS)
    for body in ("chest", "root_link"):
        fly = bounds.flywheel_bound(robot, AZIMUTHS, body)
        ratio = [fly[az]["impulse_bound_ns"] / lip[az]["impulse_bound_ns"] for az in AZIMUTHS]
        assert min(ratio) > 1.1
        # Forward: flexion (2.16 rad) gives D = 0.127 m on top of d = 0.117 m.
        assert ratio[0] == pytest.approx(2.09, abs=0.01)


def test_flywheel_bound_closed_form_on_a_square():
    # omega = 2 (z0 = g / 4), tau / (m g) = 0.5 m, t1 = ln 2 / omega: D = 0.5 (1 - 1/2)^2 = 0.125 m.
    g, omega, mass = constants.GRAVITY, 2.0, 10.0
    t1 = math.log(2.0) / omega
    tau = 0.5 * mass * g
    wheel = bounds.Flywheel(
        mass=mass,
        com_height=g / omega**2,
        inertia_pitch=1.0,
        inertia_roll=1.0,
        torque_pitch=tau,
        torque_roll=tau,
        flexion=tau * t1**2,
        extension=tau * t1**2 / 4,
        roll=tau * t1**2,
    )
    assert wheel.omega == pytest.approx(2.0)
    square = np.array([[0.1, 0.1], [0.1, -0.1], [-0.1, 0.1], [-0.1, -0.1]])
    origin = np.zeros(2)
    assert bounds.flywheel_distance(square, origin, wheel, 0.0) == pytest.approx(0.225)
    assert bounds.flywheel_distance(square, origin, wheel, 90.0) == pytest.approx(0.225)
    # Extension a quarter of the angle: t1 / 2, D = 0.5 (1 - 2^-1/2)^2.
    assert bounds.flywheel_distance(square, origin, wheel, 180.0) == pytest.approx(0.1 + 0.5 * (1 - 2**-0.5) ** 2)
    assert bounds.flywheel_distance(square, origin, wheel, 45.0) == pytest.approx(0.225 * math.sqrt(2.0))
    # Impulse bound m omega (d + D) forward: 10 * 2 * 0.225 = 4.5 N s.
    assert mass * wheel.omega * bounds.flywheel_distance(square, origin, wheel, 0.0) == pytest.approx(4.5)


def _bang_bang(v0: float, wheel, edge: float, settle: float = 1.5, dt: float = 1e-5):
    """Integrate x'' = omega^2 (x - edge - tau / (m g)) (CoP at the edge, x from the CoM) and the
    flywheel I theta'' = tau under +tau for t1, -tau for t1, then the CoP alone for ``settle`` s:
    (capture point - edge at 2 t1, flywheel angle and rate at 2 t1, final x)."""
    omega, g = wheel.omega, constants.GRAVITY
    tau, inertia = wheel.torque_pitch, wheel.inertia_pitch
    t1 = math.sqrt(inertia * wheel.flexion / tau)
    x, v, theta, rate = 0.0, v0, 0.0, 0.0
    steps = int(round(2 * t1 / dt))
    for k in range(steps + int(settle / dt)):
        torque = tau if k * dt < t1 else (-tau if k < steps else 0.0)
        if k == steps:
            at_stop = (x + v / omega - edge, theta, rate)
        v += dt * omega**2 * (x - edge - torque / (wheel.mass * g))  # semi-implicit Euler
        x += dt * v
        rate += dt * torque / inertia
        theta += dt * rate
    return (*at_stop, x)


def test_bang_bang_recovers_just_below_the_bound_and_not_above(robot, wheel):
    edge = sweep_table.lip_bound(robot, [0.0])[0.0]["edge_distance_m"]
    v_max = bounds.flywheel_bound(robot, [0.0], "chest", wheel)[0.0]["velocity_bound_mps"]
    below, theta, rate, _ = _bang_bang(0.99 * v_max, wheel, edge)
    assert below < 0.0  # the capture point back inside the support: recoverable from here
    assert theta == pytest.approx(wheel.flexion, rel=1e-3) and abs(rate) < 1e-3  # the wheel stopped at its limit
    above, _, _, x_end = _bang_bang(1.01 * v_max, wheel, edge)
    assert above > 0.0 and x_end > 1.0  # beyond the edge: the CoM runs away with the CoP at the edge
    assert _bang_bang(v_max, wheel, edge)[0] == pytest.approx(0.0, abs=2e-4)


def _optimal_shift(wheel, spin0: float, steps: int = 300, horizon: float = 2.0) -> float:
    """The largest capture-point shift [m] over all torque profiles |tau| <= tau_max (discretised,
    a linear programme): flywheel (pitch) from spin ``spin0`` [N m s] to rest, angle within
    [-extension, flexion]."""
    dt = horizon / steps
    t = (np.arange(steps) + 0.5) * dt
    weight = wheel.omega * np.exp(-wheel.omega * t) * dt / (wheel.mass * constants.GRAVITY)
    integrate = np.tril(np.ones((steps, steps))) * dt
    angle = integrate @ integrate / wheel.inertia_pitch
    drift = spin0 * np.cumsum(np.full(steps, dt)) / wheel.inertia_pitch
    res = linprog(
        -weight,
        A_ub=np.vstack([angle, -angle]),
        b_ub=np.concatenate([wheel.flexion - drift, wheel.extension + drift]),
        A_eq=np.full((1, steps), dt),
        b_eq=[-spin0],
        bounds=[(-wheel.torque_pitch, wheel.torque_pitch)] * steps,
        method="highs",
    )
    assert res.success, res.message
    return -res.fun


def test_bang_bang_is_optimal_and_a_push_above_the_com_lowers_it(robot, wheel):
    closed = bounds.flywheel_shift(wheel.torque_pitch, wheel.inertia_pitch, wheel.flexion, wheel.mass, wheel.omega)
    assert _optimal_shift(wheel, 0.0) == pytest.approx(closed, rel=2e-3)
    # The chest push's angular impulse h J (h = 0.25 m, J = 20 N s) spins the wheel the helpful way: lower.
    assert _optimal_shift(wheel, 0.25 * 20.0) < 0.9 * closed


def test_flywheel_refuses_bad_input(robot):
    with pytest.raises(ValueError, match="below the CoM"):
        bounds.flywheel_bound(robot, [0.0], "r_ankle_2")
    with pytest.raises(ValueError, match="outside the support polygon"):
        bounds.ray_distance(np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]), np.array([2.0, 2.0]), 0.0)
    with pytest.raises(ValueError, match="torque, inertia, theta_max >= 0"):
        bounds.flywheel_shift(-1.0, 1.0, 1.0, 30.0, 4.0)


def test_limit_table_rows_carry_the_flywheel_bound(robot):
    from wbc_jax.jobs import limit_table

    envelopes = {"tuned": {"envelope": {"0": {"0.0": {"impulse_ns": 8.0}, "90.0": {"impulse_ns": 9.0}}}}}
    found = {
        "directions": {
            "0.0": {"limit_ns": 10.0, "bracket_ns": [10.0, 12.0]},
            "90.0": {"limit_ns": 20.0, "bracket_ns": [20.0, 21.0]},
        }
    }
    rows = limit_table.body_table(found, envelopes, [0.0, 90.0], robot, "chest")
    fly = bounds.flywheel_bound(robot, [0.0, 90.0], "chest")
    lip = sweep_table.lip_bound(robot, [0.0, 90.0])
    for az, lim in ((0.0, 10.0), (90.0, 20.0)):
        assert rows[az]["flywheel_bound_ns"] == fly[az]["impulse_bound_ns"]
        assert rows[az]["fraction_of_flywheel"] == pytest.approx(lim / fly[az]["impulse_bound_ns"])
        assert rows[az]["lip_fraction_of_flywheel"] == pytest.approx(
            lip[az]["impulse_bound_ns"] / fly[az]["impulse_bound_ns"]
        )
    med = limit_table.medians(rows)
    expect = np.median([10.0 / fly[0.0]["impulse_bound_ns"], 20.0 / fly[90.0]["impulse_bound_ns"]])
    assert med["limit"]["fraction_of_flywheel"]["median"] == pytest.approx(expect)
    assert med["lip_bound"]["fraction_of_flywheel"]["min"] == pytest.approx(
        min(r["lip_fraction_of_flywheel"] for r in rows.values())
    )
    assert expect == pytest.approx(0.61, abs=0.01)
    summary = {"targets": {"every_limit_replayed_in_c_mujoco": True}}
    assert limit_table._targets(rows, summary)["limit_within_10pct_of_flywheel_bound_median"] is False  # 0.61
    near = {az: dict(r, fraction_of_flywheel=0.95) for az, r in rows.items()}
    assert limit_table._targets(near, summary)["limit_within_10pct_of_flywheel_bound_median"] is True
    # issue 43's other target: limit / best envelope (8 and 9 N s here) in the median over directions
    assert [rows[az]["limit_over_best_envelope"] for az in (0.0, 90.0)] == pytest.approx([10.0 / 8.0, 20.0 / 9.0])
    targets = limit_table._targets(rows, summary)
    assert targets["limit_over_best_envelope"] == pytest.approx({"median": (1.25 + 20 / 9) / 2, "min": 1.25})
    assert targets["limit_at_least_1p1x_best_envelope_median"] is True
    found["directions"]["90.0"]["limit_ns"] = 9.5  # 1.25 and 1.056: median 1.153; then 1.056 and 1.056
    rows = limit_table.body_table(found, envelopes, [0.0, 90.0], robot, "chest")
    assert limit_table._targets(rows, summary)["limit_at_least_1p1x_best_envelope_median"] is True
    found["directions"]["0.0"]["limit_ns"] = 8.0 * 9.5 / 9.0
    rows = limit_table.body_table(found, envelopes, [0.0, 90.0], robot, "chest")
    assert limit_table._targets(rows, summary)["limit_over_best_envelope"]["median"] == pytest.approx(9.5 / 9.0)
    assert limit_table._targets(rows, summary)["limit_at_least_1p1x_best_envelope_median"] is False
    assert limit_table._targets(rows, None)["limit_at_least_1p1x_best_envelope_median"] is None


def test_limit_table_takes_the_best_optimiser_per_direction(robot):
    """The crocoddyl cross-check's limit where it is larger (found_by names it), the MJX search's elsewhere; the
    bracket's upper end is where every optimiser failed; envelopes are fractions of that limit."""
    from wbc_jax.jobs import limit_table

    envelopes = {"tuned": {"envelope": {"0": {"0.0": {"impulse_ns": 8.0}, "90.0": {"impulse_ns": 9.0}}}}}
    mjx = {
        "directions": {
            "0.0": {"limit_ns": 10.0, "bracket_ns": [10.0, 15.0]},
            "90.0": {"limit_ns": 20.0, "bracket_ns": [20.0, 21.0]},
        }
    }
    ddp = {
        "config": {},
        "directions": {
            "0.0": {"limit_ns": 11.0, "bracket_ns": [11.0, 11.5], "limit_replayed_alone": {"impulse_ns": 11.0}},
            "90.0": {"limit_ns": 18.0, "bracket_ns": [18.0, 19.0]},
        },
    }
    rows = limit_table.body_table(mjx, envelopes, [0.0, 90.0], robot, "chest", [ddp])
    assert (rows[0.0]["limit_ns"], rows[0.0]["found_by"], rows[0.0]["bracket_ns"]) == (11.0, "crocoddyl", [11.0, 15.0])
    assert (rows[90.0]["limit_ns"], rows[90.0]["found_by"], rows[90.0]["bracket_ns"]) == (20.0, "mjx", [20.0, 21.0])
    assert rows[0.0]["limit_by_optimiser_ns"] == {"mjx": 10.0, "crocoddyl": 11.0}
    ddp["directions"]["0.0"]["limit_replayed_alone"]["verified"] = False  # ddp_limit.py --recheck: failed alone
    again = limit_table.body_table(mjx, envelopes, [0.0, 90.0], robot, "chest", [ddp])
    assert again[0.0]["limit_replayed_alone"] is False and again[90.0]["limit_replayed_alone"] is None  # mjx's
    assert rows[0.0]["limit_replayed_alone"] is None  # no verdict recorded
    assert rows[0.0]["envelopes"]["tuned"]["fraction_of_limit"] == pytest.approx(8.0 / 11.0)
    alone = limit_table.body_table(None, envelopes, [0.0], robot, "chest", [ddp])  # the cross-check alone
    assert alone[0.0]["limit_ns"] == 11.0 and alone[0.0]["found_by"] == "crocoddyl"
    # a second setting of the cross-check (a smaller CoP rectangle) is an optimiser of its own; nothing failed above 12
    margin = {"config": {"cop_scale": 0.8}, "directions": {"0.0": {"limit_ns": 12.0, "bracket_ns": [12.0, None]}}}
    both = limit_table.body_table(mjx, envelopes, [0.0], robot, "chest", [ddp, margin])[0.0]
    assert (both["limit_ns"], both["found_by"], both["bracket_ns"]) == (12.0, "crocoddyl cop x0.8", [12.0, None])
    assert both["limit_by_optimiser_ns"] == {"mjx": 10.0, "crocoddyl": 11.0, "crocoddyl cop x0.8": 12.0}
    none = limit_table.body_table(None, envelopes, [0.0], robot, "chest")
    assert none[0.0]["limit_ns"] is None and none[0.0]["found_by"] is None and none[0.0]["bracket_ns"] is None
    # a file that names its optimiser (controller_witness.py: the controller's own trajectory) is found by that name
    own = {
        "optimiser": "tuned controller (u = 0)",
        "config": {"cop_scale": 1.0},
        "directions": {"0.0": {"limit_ns": 13.0, "bracket_ns": [13.0, 13.5]}},
    }
    assert limit_table.ddp_label(own) == "tuned controller (u = 0)"
    mixed = limit_table.body_table(mjx, envelopes, [0.0], robot, "chest", [ddp, margin, own])[0.0]
    assert (mixed["limit_ns"], mixed["found_by"], mixed["bracket_ns"]) == (
        13.0,
        "tuned controller (u = 0)",
        [13.0, None],
    )
