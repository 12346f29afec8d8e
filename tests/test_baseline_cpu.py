"""The CPU baseline (benchmarks/baseline_cpu/: C MuJoCo + NumPy controller) against the JAX/MJX
implementation: dynamics terms, one controller tick, references, the closed loop, and its
process pool."""

import importlib.util
import pathlib
import sys
import time

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from conftest import c_data, random_state
from mujoco import mjx

from wbc_jax.control import forces, qp, references, torques
from wbc_jax.control.controller import ControllerConfig, make_controller
from wbc_jax.core import constants
from wbc_jax.robot import dynamics
from wbc_jax.sim import metrics as metrics_lib
from wbc_jax.sim import physics, runner, scenario
from wbc_jax.sim.state import SimConfig

ROOT = pathlib.Path(__file__).resolve().parent.parent


def _load_baseline():
    """benchmarks/baseline_cpu/ (a package of the script folder benchmarks/), imported once."""
    name = "baseline_cpu"
    if name not in sys.modules:
        folder = ROOT / "benchmarks" / name
        spec = importlib.util.spec_from_file_location(
            name, folder / "__init__.py", submodule_search_locations=[str(folder)]
        )
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module  # dataclasses look their module up by name
        spec.loader.exec_module(module)
    return sys.modules[name]


bc = _load_baseline()

PUSH = dict(force=[0.0, 40.0, 0.0], onset=0.3, duration=0.1)  # 40 N lateral on the chest


@pytest.fixture(scope="module")
def terms_fn(robot):
    jitted = jax.jit(lambda d: dynamics.terms(robot.mjx_model, d, robot.index))
    # Commit every leaf: make_data's leaves are committed, jnp.asarray's are not, and jit
    # compiles once per combination (20-30 s each on 2 cores).
    return lambda d: jitted(jax.device_put(d, jax.devices("cpu")[0]))


def _mjx_data(robot, qpos, qvel):
    d = mjx.make_data(robot.mj_model)
    return d.replace(qpos=jnp.asarray(qpos), qvel=jnp.asarray(qvel))


@pytest.fixture(scope="module")
def stand(robot, terms_fn):
    """The setup of a 1 s stand task on C MuJoCo (float64; the program of tests/test_rollout.py's closed
    loop, compiled once for both), its initial controller state and the matching CPU spec."""
    sim = SimConfig(physics=physics.PhysicsConfig(backend="mujoco"))
    st = scenario.setup("stand", duration=1.0, sim=sim)
    assert st.dtype == np.float64 and st.robot is robot
    t_ref = terms_fn(_mjx_data(robot, st.qpos0, np.zeros(robot.index.nv)))
    state0 = st.loop.controller.init(t_ref)
    spec = bc.spec_from_setup(st, state0)
    return st, state0, spec


@pytest.fixture(scope="module")
def step_fn(robot):
    """The jitted controller tick of a forces mode (compiled once per mode for the module)."""
    cache = {}

    def get(forces_mode):
        if forces_mode not in cache:
            ctrl = make_controller(robot, ControllerConfig(forces=forces_mode))
            cache[forces_mode] = jax.jit(ctrl.step)
        return cache[forces_mode]

    return get


def _rel(actual, expected) -> float:
    actual, expected = np.asarray(actual), np.asarray(expected)
    return float(np.abs(actual - expected).max() / max(np.abs(expected).max(), 1e-300))


def test_shared_constants_and_names():
    """The baseline uses wbc_jax/core/constants.py (loaded by path, without JAX) and the library's names."""
    assert pathlib.Path(bc.constants.__file__).resolve() == pathlib.Path(constants.__file__).resolve()
    assert bc.GAIN_FIELDS == constants.GAIN_FIELDS and bc.METRIC_NAMES == constants.METRIC_NAMES
    assert bc.GRAVITY == constants.GRAVITY and bc.RECOVERY_THRESHOLD == constants.RECOVERY_THRESHOLD
    assert bc.FORCE_MODES == forces.FORCE_MODES and bc.POSTURAL_VARIANTS == torques.POSTURAL_VARIANTS
    assert bc.QP_FALLBACK_TOL == qp.default_tolerances(jnp.float64)[1]


def test_dynamics_terms_match_jax(robot, stand, terms_fn):
    """M, h, passive forces, sole Jacobians, Jdot nu (mj_jacDot), sole frames, CoM, CoM velocity
    and the centroidal angular momentum (mj_subtreeVel) from C MuJoCo equal dynamics.terms, in the
    mixed representation, at general states (random base orientation and velocities)."""
    ctrl = bc.NumpyController(stand[2])
    rot = robot.index.foot_rotations
    for seed in range(3):
        qpos, qvel = random_state(robot, seed)
        t = ctrl.terms([c_data(robot, qpos, qvel)])
        tj = terms_fn(_mjx_data(robot, qpos, qvel))
        sole_R = np.einsum("kij,kjl->kil", np.asarray(tj.W_R_frames), rot)  # body -> sole frame
        pairs = {
            "nu": (t.nu, tj.nu),
            "s": (t.s, tj.s),
            "M": (t.M, tj.M),
            "h": (t.h, tj.h),
            "tau_passive": (t.tau_passive, tj.tau_passive),
            "J_frames": (t.J_feet, tj.J_frames),
            "Jdot_nu_frames": (t.Jdot_nu_feet, tj.Jdot_nu_frames),
            "W_p_frames": (t.W_p_feet, tj.W_p_frames),
            "sole frames": (t.W_R_feet, sole_R),
            "W_p_CoM": (t.W_p_CoM, tj.W_p_CoM),
            "W_v_CoM": (t.W_v_CoM, tj.W_v_CoM),
            "L_ang": (t.L_ang, tj.L_G[3:]),
        }
        for name, (a, b) in pairs.items():
            assert _rel(a[0], b) < 1e-9, f"seed {seed}: {name} rel err {_rel(a[0], b):.2e}"


def _near_home_state(robot, seed):
    rng = np.random.default_rng(seed)
    qpos = robot.home_qpos()
    qpos[robot.index.qpos_joints] += rng.uniform(-0.05, 0.05, robot.index.n)
    return qpos, rng.normal(scale=0.3, size=robot.mj_model.nv)


# (forces, foot activations, lateral CoM reference offset): two feet with an active CoP
# constraint; the left foot alone, whose momentum equality is infeasible there (-> the soft QP
# of one foot); the right foot alone (feasible equality); the blend of the two-feet and the
# right-foot formulations; an infeasible two-feet equality (-> the soft two-feet QP).
TICK_CASES = [
    ("qp", (1.0, 1.0), 0.03),
    ("analytic", (1.0, 1.0), 0.03),
    ("qp", (1.0, 0.0), 0.03),
    ("qp", (0.0, 1.0), 0.03),
    ("analytic", (1.0, 0.0), 0.03),
    ("qp", (0.6, 1.0), 0.03),
    ("analytic", (0.6, 1.0), 0.03),
    ("qp", (1.0, 1.0), 0.06),
    # The right foot alone with an infeasible momentum equality: forces.momentum_equality_qp's
    # null-space basis Z of one sole is rounding noise (~1e-16, not exactly 0 as for the left
    # sole here); qp.solve_qp scales the rows of C Z to unit norm, finds the noise rows
    # "feasible" and returns f = f1 + Z y with |Z y| ~ 100 N, meeting neither A f = w nor C f <= b,
    # unflagged and without the soft QP. The baseline gives the soft QP's wrenches.
    # Right foot alone, CoM reference 10 cm to the right: the single-support equality is
    # infeasible and the soft QP must take over (the null-space basis is then rounding noise).
    ("qp", (0.0, 1.0), -0.1),
]


@pytest.mark.parametrize("forces_mode,activation,offset", TICK_CASES)
def test_controller_tick_matches_jax(robot, stand, terms_fn, step_fn, forces_mode, activation, offset):
    st, state0, spec = stand
    spec = bc.BaselineSpec(**{**spec.to_dict(), "forces": forces_mode})
    qpos, qvel = _near_home_state(robot, 3)
    ref = spec.reference(0)
    ref = {**ref, "activation": np.array(activation), "com_pos": ref["com_pos"] + np.array([0.01, offset, 0.0])}
    integral = np.array([[0.001, -0.002, 0.0005]])
    ctrl = bc.NumpyController(spec)
    out, new_state = ctrl([c_data(robot, qpos, qvel)], bc.gains_to_numpy(st.gains, 1, spec.n), ref, integral)
    out_j, state_j = step_fn(forces_mode)(
        st.gains,
        state0.replace(com_err_integral=jnp.asarray(integral[0])),
        terms_fn(_mjx_data(robot, qpos, qvel)),
        references.Reference(**{k: jnp.asarray(v) for k, v in ref.items()}),
        jnp.asarray(0.0),
    )
    errs = {
        "tau": _rel(out["tau"][0], out_j.tau),
        "tau_unsat": _rel(out["tau_unsat"][0], out_j.tau_unsat),
        "f": _rel(out["f"][0], out_j.f),
        "Ldot_star": _rel(out["Ldot_star"][0], out_j.Ldot_star),
        "Ldot_cmd": _rel(out["Ldot_cmd"][0], out_j.Ldot_cmd),
        "state": _rel(new_state[0], state_j.com_err_integral),
    }
    print(forces_mode, activation, offset, {k: f"{v:.1e}" for k, v in errs.items()})
    for name, err in errs.items():
        assert err < 1e-6, f"{name}: relative error {err:.2e}"
    assert bool(out["qp_infeasible"][0]) == bool(out_j.qp_infeasible)
    viol = float(out_j.qp_violation)
    assert abs(out["qp_violation"][0] - viol) < 1e-6 * (1 + viol)
    if forces_mode == "qp" and (offset > 0.05 or activation == (1.0, 0.0)):
        # The cases meant to exercise a soft QP: A f != L_dot* - f_grav.
        assert _rel(out_j.Ldot_cmd, out_j.Ldot_star) > 1e-3


def test_schedule_table_matches_schedule(robot, stand, terms_fn):
    """The NumPy references equal Schedule.at for the tasks with every kind of segment."""
    st = stand[0]
    t0 = terms_fn(_mjx_data(robot, st.qpos0, np.zeros(robot.index.nv)))
    kwargs = dict(
        com0=np.asarray(t0.W_p_CoM),
        s0=np.asarray(t0.s),
        left_sole=np.asarray(t0.W_p_frames[0]),
        joints=robot.index.joints,
        foot_lift_deg=robot.description.foot_lift_deg,
    )
    sched = references.make_schedule("one-foot", **kwargs)
    sine = references.make_schedule("sinusoid", **kwargs)
    times = np.array([0.0, 1.7, 4.5, 6.0, 8.0, 10.2, 12.0, 14.0, 15.99])
    for s in (sched, sine, st.loop.schedule):
        table = bc.schedule_table(s, times)
        refs = jax.jit(jax.vmap(lambda t, s=s: s.at(t, jnp.float64)))(jnp.asarray(times))
        for k in table:
            # NumPy vs JAX: measured 1.9e-16 relative, here and with XLA held to AVX2 (OpenBLAS Haswell).
            np.testing.assert_allclose(table[k], getattr(refs, k), rtol=1e-12, atol=1e-14, err_msg=f"{s.name} {k}")


def test_make_spec_matches_setup(robot, stand):
    """make_spec (no JAX evaluation: C MuJoCo J_G,ang) builds the spec that spec_from_setup builds
    from the JAX controller state; the default gains are the library's; the model copy never
    auto-resets (as physics.solver_mj_model)."""
    spec, gains = bc.make_spec("stand", duration=1.0)
    ref = stand[2].to_dict()
    for name, value in spec.to_dict().items():
        if isinstance(value, np.ndarray):
            # C MuJoCo's J_G,ang vs the JAX controller's: measured 6.4e-13 relative, 8.9e-16 abs (with AVX2 too).
            np.testing.assert_allclose(value, ref[name], rtol=1e-10, atol=1e-14, err_msg=name)
        elif name != "mj_model":
            assert value == ref[name], name
    for name in constants.GAIN_FIELDS:
        np.testing.assert_allclose(gains[name], getattr(stand[0].gains, name), rtol=1e-15)
    expected = physics.solver_mj_model(robot.mj_model, physics.PhysicsConfig(solver_iterations=3))
    other, _ = bc.make_spec("stand", duration=0.1, solver_iterations=3)
    for m in (spec.mj_model, other.mj_model):
        assert m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_AUTORESET
    assert other.mj_model.opt.iterations == expected.opt.iterations == 3
    assert robot.mj_model.opt.iterations != 3  # a copy: the robot's model is untouched


def test_closed_loop_matches_the_jax_closed_loop(stand):
    """C MuJoCo + NumPy vs the JAX controller's closed loop on C MuJoCo (the MJX one equals it:
    tests/test_rollout.py, nightly): same 1 s stand with a 40 N lateral push; the metrics under the same
    names (constants.METRIC_NAMES)."""
    st, _, spec = stand
    push = scenario.make_push(PUSH["force"], PUSH["onset"], PUSH["duration"], st.dtype)
    run = runner.run(st, scenario.single(st, push))
    res = bc.simulate(spec, st.gains, push, timing=True)
    com_j, com_n = np.asarray(run.records.com[0]), res["com"][0]
    diff = np.linalg.norm(com_j - com_n, axis=1)
    excursion = np.abs(com_j - com_j[0]).max()
    print(
        f"max CoM difference vs the JAX loop over {spec.n_ticks} ticks: {diff.max():.3e} m "
        f"(CoM excursion {excursion:.3e} m); compile {run.compile_s:.1f} s; timing {res['timing']}"
    )
    assert com_j.shape == com_n.shape == (spec.n_ticks, 3)
    assert excursion > 5e-3  # the push does move the robot
    # Two controllers (NumPy, JAX) on one physics: they differ by rounding alone. Measured against the MJX loop:
    # ~1e-11 m of CoM, 8.4e-9 N m of torque (7.1e-9 with XLA held to AVX2); the bars are the requirement (1 mm)
    # and 1e-6 m / 1e-5 N m, far above that noise and far below a wrong tick (the push moves the CoM > 5 mm).
    assert diff.max() < 1e-3  # the requirement
    assert diff.max() < 1e-6, "the NumPy and JAX controllers agree far better than this in float64"
    np.testing.assert_allclose(res["tau"][0], np.asarray(run.records.tau[0]), rtol=0, atol=1e-5)
    push_end = PUSH["onset"] + PUSH["duration"]
    ours = bc.summarize(res["metrics"], push_end)[0]
    theirs = metrics_lib.summarize(jax.tree_util.tree_map(lambda x: x[0], run.metrics), push_end)
    assert tuple(ours) == tuple(theirs) == constants.METRIC_NAMES
    assert ours["fell"] == theirs["fell"] is False and ours["nan"] == theirs["nan"] is False
    for key in ("survived", "upright", "qp_infeasible_ticks"):
        assert ours[key] == theirs[key], key
    for key in constants.METRIC_NAMES:
        if key not in ("survived", "upright", "fell", "nan", "qp_infeasible_ticks"):
            assert ours[key] == pytest.approx(theirs[key], rel=1e-3, abs=1e-6), key


def test_batch_environments_are_independent(stand):
    """Per-environment gains and pushes: a batch of 3 equals the 3 environments run alone."""
    st, _, spec = stand
    g = bc.gains_to_numpy(st.gains, 3, spec.n)
    g["kp_com"] = g["kp_com"] * np.array([[1.0], [1.5], [0.7]])
    push = {
        "force": np.array([[[0.0, 40.0, 0.0]], [[0.0, 0.0, 0.0]], [[30.0, -20.0, 0.0]]]),
        "onset": np.full((3, 1), 0.05),
        "duration": np.full((3, 1), 0.1),
    }
    batch = bc.simulate(spec, g, push, n_ticks=25)
    assert batch["com"].shape == (3, 25, 3)
    for i in range(3):
        alone = bc.simulate(spec, {k: v[i] for k, v in g.items()}, {k: v[i] for k, v in push.items()}, n_ticks=25)
        # NumPy batch vs alone (other BLAS calls): measured 6.7e-16 m here, 1.3e-15 m with OpenBLAS's Haswell kernels.
        np.testing.assert_allclose(batch["com"][i], alone["com"][0], rtol=0, atol=1e-12)
    assert np.abs(batch["com"][0] - batch["com"][1]).max() > 1e-4  # the pushes differ


def test_run_parallel_two_workers(stand):
    spec = stand[2]
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
    # The same NumPy code in a worker process: measured bit-equal (here and with OpenBLAS's Haswell kernels).
    np.testing.assert_allclose(res["com"], here["com"], rtol=0, atol=1e-12)


def test_run_parallel_times_out_instead_of_hanging(stand):
    # 2 x 200 environments over the 1 s horizon take each worker well over 10 s of work: a
    # 1.5 s timeout must stop them (a tiny job could finish inside the timeout and not raise).
    start = time.monotonic()
    with pytest.raises(TimeoutError, match="did not answer"):
        bc.run_parallel(400, 2, spec=stand[2], timeout=1.5)
    assert time.monotonic() - start < 30


def test_run_parallel_reports_a_failing_worker(stand):
    broken = bc.BaselineSpec(**{**stand[2].to_dict(), "qpos0": np.zeros(3)})  # wrong size
    with pytest.raises(RuntimeError, match="worker 0 failed"):
        bc.run_parallel(2, 2, spec=broken, n_ticks=2, timeout=120)
