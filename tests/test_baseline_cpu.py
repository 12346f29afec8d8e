"""The CPU baseline (C MuJoCo + NumPy controller) against the JAX/MJX reference implementation."""

import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import c_data, random_state
from mujoco import mjx

from wbc_jax import balance, dynamics
from wbc_jax import baseline_cpu as bc
from wbc_jax import controller as C
from wbc_jax import references
from wbc_jax import rollout as rollout_lib

PUSH = rollout_lib.Push(  # 40 N lateral on the chest for 0.1 s at 0.3 s
    force=jnp.array([[0.0, 40.0, 0.0]]), onset=jnp.array([0.3]), duration=jnp.array([0.1])
)


@pytest.fixture(scope="module")
def terms_fn(robot):
    terms = dynamics.terms
    jitted = jax.jit(lambda d: terms(robot.mjx_model, d, robot.index))
    # Commit every leaf: make_data's leaves are committed, jnp.asarray's are not, and jit
    # compiles once per combination (20-30 s each on 2 cores).
    return lambda d: jitted(jax.device_put(d, jax.devices("cpu")[0]))


@pytest.fixture(scope="module")
def stand(robot, terms_fn):
    """The JAX pieces of a 1 s stand task and the matching CPU spec (float64)."""
    # balance.setup evaluates dynamics.terms eagerly (~1 min on 2 busy cores): use the jitted one.
    eager = dynamics.terms

    def terms(m, d, idx):
        return terms_fn(d) if (m is robot.mjx_model and idx is robot.index) else eager(m, d, idx)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(dynamics, "terms", terms)
        rollout, d0, gains, consts, schedule = balance.setup(robot, "stand", duration=1.0)
    assert d0.qpos.dtype == jnp.float64
    spec = bc.spec_from_setup(robot, rollout, consts, schedule)
    return rollout, d0, gains, consts, spec


@pytest.fixture(scope="module")
def step_fn():
    return jax.jit(C.step, static_argnames=("config", "mass", "dt"))


def _mjx_data(robot, qpos, qvel):
    d = mjx.make_data(robot.mj_model)
    return d.replace(qpos=jnp.asarray(qpos), qvel=jnp.asarray(qvel))


def _rel(actual, expected) -> float:
    actual, expected = np.asarray(actual), np.asarray(expected)
    return float(np.abs(actual - expected).max() / max(np.abs(expected).max(), 1e-300))


def test_dynamics_terms_match_jax(robot, stand, terms_fn):
    """M, h, passive forces, sole Jacobians, Jdot nu (mj_jacDot), CoM, CoM velocity and the
    centroidal angular momentum (mj_subtreeVel) from C MuJoCo equal dynamics.terms, in the mixed
    representation, at general states (random base orientation and velocities)."""
    ctrl = bc.NumpyController(stand[4])
    for seed in range(3):
        qpos, qvel = random_state(robot, seed)
        t = ctrl.terms([c_data(robot, qpos, qvel)])
        tj = terms_fn(_mjx_data(robot, qpos, qvel))
        pairs = {
            "nu": (t.nu, tj.nu), "s": (t.s, tj.s), "M": (t.M, tj.M), "h": (t.h, tj.h),
            "tau_passive": (t.tau_passive, tj.tau_passive), "J_feet": (t.J_feet, tj.J_feet),
            "Jdot_nu_feet": (t.Jdot_nu_feet, tj.Jdot_nu_feet),
            "W_p_feet": (t.W_p_feet, tj.W_p_feet), "W_R_feet": (t.W_R_feet, tj.W_R_feet),
            "W_p_CoM": (t.W_p_CoM, tj.W_p_CoM), "W_v_CoM": (t.W_v_CoM, tj.W_v_CoM),
            "L_ang": (t.L_ang, tj.L_G[3:]),
        }  # fmt: skip
        for name, (a, b) in pairs.items():
            assert _rel(a[0], b) < 1e-9, f"seed {seed}: {name} rel err {_rel(a[0], b):.2e}"


def _near_home_state(robot, seed):
    rng = np.random.default_rng(seed)
    qpos = robot.home_qpos()
    qpos[robot.index.qpos_joints] += rng.uniform(-0.05, 0.05, robot.index.n)
    return qpos, rng.normal(scale=0.3, size=robot.mj_model.nv)


# (forces, activation, lateral CoM reference offset): two feet with an active CoP constraint,
# one foot, a blend, and an infeasible two-feet QP (-> the soft two-feet momentum QP).
TICK_CASES = [
    ("qp", (1.0, 1.0), 0.03),
    ("analytic", (1.0, 1.0), 0.03),
    ("qp", (1.0, 0.0), 0.03),
    ("qp", (0.6, 1.0), 0.03),
    ("analytic", (0.6, 1.0), 0.03),
    ("qp", (1.0, 1.0), 0.06),
]


@pytest.mark.parametrize("forces,activation,offset", TICK_CASES)
def test_controller_tick_matches_jax(robot, stand, terms_fn, step_fn, forces, activation, offset):
    _, _, gains, consts, spec = stand
    spec = bc.BaselineSpec(**{**spec.to_dict(), "forces": forces})
    qpos, qvel = _near_home_state(robot, 3)
    ref = spec.reference(0)
    ref = {**ref, "activation": np.array(activation),
           "com_pos": ref["com_pos"] + np.array([0.01, offset, 0.0])}  # fmt: skip
    state = np.array([[0.001, -0.002, 0.0005]])
    ctrl = bc.NumpyController(spec)
    out, new_state = ctrl(
        [c_data(robot, qpos, qvel)], bc.gains_to_numpy(gains, 1, spec.n), ref, state
    )
    out_j, state_j = step_fn(
        gains, consts, C.ControllerState(com_err_integral=jnp.asarray(state[0])),
        terms_fn(_mjx_data(robot, qpos, qvel)),
        C.Reference(**{k: jnp.asarray(v) for k, v in ref.items()}),
        config=C.ControllerConfig(forces=forces), mass=robot.index.mass, dt=spec.control_dt,
    )  # fmt: skip
    errs = {
        "tau": _rel(out["tau"][0], out_j.tau),
        "tau_unsat": _rel(out["tau_unsat"][0], out_j.tau_unsat),
        "f": _rel(out["f"][0], out_j.f), "Ldot_star": _rel(out["Ldot_star"][0], out_j.Ldot_star),
        "Ldot_cmd": _rel(out["Ldot_cmd"][0], out_j.Ldot_cmd),
        "state": _rel(new_state[0], state_j.com_err_integral),
    }  # fmt: skip
    print(forces, activation, offset, {k: f"{v:.1e}" for k, v in errs.items()})
    for name, err in errs.items():
        assert err < 1e-6, f"{name}: relative error {err:.2e}"
    assert bool(out["qp_infeasible"][0]) == bool(out_j.qp_infeasible)
    viol = float(out_j.qp_violation)
    assert abs(out["qp_violation"][0] - viol) < 1e-6 * (1 + viol)
    if offset > 0.05:  # the case meant to exercise the soft QP: A f != L_dot* - f_grav
        assert _rel(out_j.Ldot_cmd, out_j.Ldot_star) > 1e-3


def test_schedule_table_matches_schedule(robot, stand, terms_fn):
    """The NumPy references equal Schedule.at for the tasks with every kind of segment."""
    t0 = terms_fn(stand[1])
    sched = references.make_schedule(
        "one-foot", com0=np.asarray(t0.W_p_CoM), s0=np.asarray(t0.s),
        left_sole=np.asarray(t0.W_p_feet[0]), joints=robot.index.joints,
    )  # fmt: skip
    sine = references.make_schedule(
        "sinusoid", com0=np.asarray(t0.W_p_CoM), s0=np.asarray(t0.s),
        left_sole=np.asarray(t0.W_p_feet[0]), joints=robot.index.joints,
    )  # fmt: skip
    times = np.array([0.0, 1.7, 4.5, 6.0, 8.0, 10.2, 12.0, 14.0, 15.99])
    for s in (sched, sine):
        table = bc.schedule_table(s, times)
        refs = jax.jit(jax.vmap(lambda t: s.at(t, jnp.float64)))(jnp.asarray(times))
        for k in table:
            np.testing.assert_allclose(table[k], getattr(refs, k), rtol=1e-12, atol=1e-14,
                                       err_msg=f"{s.name} {k}")  # fmt: skip
    assert bc.GAIN_FIELDS == C.GAIN_FIELDS


def test_make_spec_matches_balance_setup(robot, stand):
    """make_spec (no JAX evaluation: C MuJoCo + NumPy J_G,ang) builds the spec that
    spec_from_setup builds from balance.setup, and the default gains are the library's."""
    spec, gains = bc.make_spec(robot, "stand", duration=1.0)
    ref = stand[4].to_dict()
    for name, value in spec.to_dict().items():
        if isinstance(value, np.ndarray):
            np.testing.assert_allclose(value, ref[name], rtol=1e-10, atol=1e-14, err_msg=name)
        elif name != "mj_model":
            assert value == ref[name], name
    for name in C.GAIN_FIELDS:
        np.testing.assert_allclose(gains[name], getattr(stand[2], name), rtol=1e-15)


def test_closed_loop_matches_mjx_rollout(robot, stand):
    """C MuJoCo + NumPy vs the MJX/JAX rollout: same 1 s stand with a 40 N lateral push."""
    rollout, d0, gains, consts, spec = stand
    res = bc.simulate(spec, gains, PUSH, timing=True)
    metrics, traj = jax.jit(rollout)(robot.mjx_model, d0, gains, consts, PUSH)
    com_j, com_n = np.asarray(traj.com), res["com"][0]
    diff = np.linalg.norm(com_j - com_n, axis=1)
    excursion = np.abs(com_j - com_j[0]).max()
    print(f"max CoM difference vs MJX over {spec.n_ticks} ticks: {diff.max():.3e} m "
          f"(CoM excursion {excursion:.3e} m); timing {res['timing']}")  # fmt: skip
    assert excursion > 5e-3  # the push does move the robot
    assert diff.max() < 1e-3  # the requirement; measured: ~1e-11 m (same physics, float64)
    assert diff.max() < 1e-6, "C MuJoCo and MJX agree far better than this in float64"
    np.testing.assert_allclose(res["tau"][0], np.asarray(traj.tau), rtol=0, atol=1e-5)
    ours = bc.summarize(res["metrics"], push_end=0.4)[0]
    theirs = rollout_lib.summarize(metrics, push_end=0.4)
    assert ours["fell"] == theirs["fell"] is False and ours["nan"] == theirs["nan"] is False
    assert ours["qp_infeasible_ticks"] == theirs["qp_infeasible_ticks"]
    for key in ("com_rmse_m", "com_max_err_m", "max_abs_torque_nm", "min_com_height_m",
                "time_to_recover_s", "max_foot_slip_m"):  # fmt: skip
        assert ours[key] == pytest.approx(theirs[key], rel=1e-3, abs=1e-6), key


def test_batch_environments_are_independent(stand):
    """Per-environment gains and pushes: a batch of 3 equals the 3 environments run alone."""
    spec = stand[4]
    g = bc.gains_to_numpy(stand[2], 3, spec.n)
    g["kp_com"] = g["kp_com"] * np.array([[1.0], [1.5], [0.7]])
    push = {"force": np.array([[[0.0, 40.0, 0.0]], [[0.0, 0.0, 0.0]], [[30.0, -20.0, 0.0]]]),
            "onset": np.full((3, 1), 0.05), "duration": np.full((3, 1), 0.1)}  # fmt: skip
    batch = bc.simulate(spec, g, push, n_ticks=25)
    assert batch["com"].shape == (3, 25, 3)
    for i in range(3):
        alone = bc.simulate(spec, {k: v[i] for k, v in g.items()},
                            {k: v[i] for k, v in push.items()}, n_ticks=25)  # fmt: skip
        np.testing.assert_allclose(batch["com"][i], alone["com"][0], rtol=0, atol=1e-12)
    assert np.abs(batch["com"][0] - batch["com"][1]).max() > 1e-4  # the pushes differ


def test_run_parallel_two_workers(stand):
    spec = stand[4]
    res = bc.run_parallel(4, 2, spec=spec, n_ticks=5, record=True, timeout=240)
    print({k: res[k] for k in ("wall_s", "total_wall_s", "steps_per_s", "timing")})
    assert res["n_workers"] == 2 and res["physics_steps"] == 4 * 5 * spec.n_sub
    assert res["steps_per_s"] > 0 and all(s > 0 for s in res["steps_per_s_per_worker"])
    assert res["com"].shape == (4, 5, 3) and res["metrics"]["ticks"].tolist() == [5] * 4
    main = sys.modules["__main__"]
    if "pytest" in (getattr(main, "__file__", None) or "") + str(getattr(main, "__spec__", "")):
        # Workers run without JAX (unless spawn re-imports a __main__ script that imports it).
        assert not any(w["jax_imported"] for w in res["workers"])
    assert res["timing"]["controller_us_per_env_tick"] > 0
    assert res["timing"]["physics_us_per_mj_step"] > 0
    # Same numbers as in this process.
    here = bc.simulate(spec, n_envs=4, n_ticks=5)
    np.testing.assert_allclose(res["com"], here["com"], rtol=0, atol=1e-12)


def test_run_parallel_times_out_instead_of_hanging(stand):
    # 2 x 200 environments over the 1 s horizon take each worker well over 10 s of work: a
    # 1.5 s timeout must stop them (a tiny job could finish inside the timeout and not raise).
    start = time.monotonic()
    with pytest.raises(TimeoutError, match="did not answer"):
        bc.run_parallel(400, 2, spec=stand[4], timeout=1.5)
    assert time.monotonic() - start < 30


def test_run_parallel_reports_a_failing_worker(stand):
    broken = bc.BaselineSpec(**{**stand[4].to_dict(), "qpos0": np.zeros(3)})  # wrong size
    with pytest.raises(RuntimeError, match="worker 0 failed"):
        bc.run_parallel(2, 2, spec=broken, n_ticks=2, timeout=120)
