"""The TSID peer (benchmarks/tsid_baseline/, benchmarks/tsid_peer.py, wbc_jax/robot/pinocchio.py): the MuJoCo-to-Pinocchio state
map, the copies of wbc_jax's definitions it keeps to stay JAX-free, and TSID's closed loop on the
stand and sinusoid tasks and under pushes. The closed-loop tests need tsid (the dev extra, after
.ci/install_libtsid.py) with the Pinocchio it was built against; they skip otherwise."""

import importlib.util
import json
import pathlib
import sys

import mujoco
import numpy as np
import pytest
from conftest import random_state

from wbc_jax.control import references
from wbc_jax.core import constants
from wbc_jax.jobs import envelope, sweep_table
from wbc_jax.robot import contacts, model
from wbc_jax.robot import pinocchio as robot_pinocchio
from wbc_jax.robot.icub import DESCRIPTION as ICUB
from wbc_jax.robot.talos import DESCRIPTION as TALOS

ROOT = pathlib.Path(__file__).resolve().parent.parent


def _load(name: str, path: pathlib.Path):
    """A script of benchmarks/ (not a package), or a package of it from its folder, imported once."""
    if name not in sys.modules:
        if path.is_dir():
            spec = importlib.util.spec_from_file_location(
                name, path / "__init__.py", submodule_search_locations=[str(path)]
            )
        else:
            spec = importlib.util.spec_from_file_location(name, path)
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    return sys.modules[name]


tb = _load("tsid_baseline", ROOT / "benchmarks" / "tsid_baseline")
tp = _load("tsid_peer", ROOT / "benchmarks" / "tsid_peer.py")
pe = sys.modules["tsid_baseline.push_envelope"]  # (tsid_peer imports it)
bc = sys.modules["baseline_cpu"]

TSID_PROBLEM = tb.tsid_problem()
needs_tsid = pytest.mark.skipif(TSID_PROBLEM is not None, reason=f"TSID closed loop: {TSID_PROBLEM}")


@pytest.fixture(scope="module")
def pin_model():
    pytest.importorskip("pinocchio")
    return robot_pinocchio.pinocchio_model(tb.DRIVEN_JOINTS)


@pytest.fixture(scope="module")
def peer(pin_model):
    if TSID_PROBLEM is not None:
        pytest.skip(TSID_PROBLEM)
    return tb.TsidPeer(pin_model=pin_model)


# --------------------------------------------------------------------------------------
# (a) The state map: Pinocchio's CoM and mass matrix against C MuJoCo's (Pinocchio only)
# --------------------------------------------------------------------------------------


def test_state_map_com_mass_matrix_and_momentum_match_mujoco(robot, pin_model):
    import pinocchio as pin

    m = tb.load_mj_model()
    smap = robot_pinocchio.StateMap(m, pin_model, tb.DRIVEN_JOINTS)
    # Why 1e-8 holds: no armature on either side (it would add to M's diagonal), the MJCF carries the
    # URDF's inertias at 12 digits, the static links fused into the same parents; the URDF damping
    # is what the controller compensates.
    assert np.all(m.dof_armature == 0) and np.all(pin_model.armature == 0)
    np.testing.assert_array_equal(pin_model.damping[smap.pin_v], m.dof_damping[smap.mj_dof])
    assert pin.computeTotalMass(pin_model) == pytest.approx(float(m.body_subtreemass[smap.base_body]), rel=1e-12)
    pd = pin_model.createData()
    worst = {"com": 0.0, "M": 0.0, "momentum": 0.0}
    for seed in range(3):
        qpos, qvel = random_state(robot, 300 + seed, joint_scale=0.6)  # any base orientation, joints +-0.6 rad
        d = mujoco.MjData(m)
        d.qpos[:], d.qvel[:] = qpos, qvel
        mujoco.mj_forward(m, d)
        mujoco.mj_subtreeVel(m, d)
        R = d.xmat[smap.base_body].reshape(3, 3)
        q, v = smap.q_v(qpos, qvel)  # R from the quaternion: the same as MuJoCo's xmat
        np.testing.assert_allclose(smap.q_v(qpos, qvel, R)[1], v, atol=1e-14)
        com = pin.centerOfMass(pin_model, pd, q)
        worst["com"] = max(worst["com"], np.abs(com - d.subtree_com[smap.base_body]).max())
        pin.crba(pin_model, pd, q)
        M_pin = np.triu(pd.M) + np.triu(pd.M, 1).T
        M_mj = np.zeros((m.nv, m.nv))
        mujoco.mj_fullM(m, d, M_mj)
        T = smap.velocity_matrix(R)
        np.testing.assert_allclose(T @ qvel, v, atol=1e-14)
        worst["M"] = max(worst["M"], np.abs(T.T @ M_pin @ T - M_mj).max())
        # The velocity map through the centroidal momentum (MuJoCo: m v_CoM, L about the CoM).
        pin.computeCentroidalMomentum(pin_model, pd, q, v)
        h_mj = np.concatenate([m.body_subtreemass[1] * d.subtree_linvel[1], d.subtree_angmom[1]])
        worst["momentum"] = max(worst["momentum"], np.abs(np.concatenate([pd.hg.linear, pd.hg.angular]) - h_mj).max())
        pin.framesForwardKinematics(pin_model, pd, q)
        for site in tb.FEET:
            oMf = pd.oMf[pin_model.getFrameId(site)]
            # Pinocchio vs C MuJoCo: measured <= 6.7e-16 abs.
            np.testing.assert_allclose(oMf.translation, d.site_xpos[m.site(site).id], atol=1e-12)
            np.testing.assert_allclose(oMf.rotation, d.site_xmat[m.site(site).id].reshape(3, 3), atol=1e-12)
    print(f"worst over 3 states: {worst}")  # measured ~1e-13 (CoM), ~2e-12 (M, entries up to 33 kg)
    assert worst["com"] < 1e-8 and worst["M"] < 1e-8 and worst["momentum"] < 1e-8, worst


def test_state_map_pieces():
    np.testing.assert_array_equal(robot_pinocchio.quat_wxyz_to_xyzw([1.0, 2.0, 3.0, 4.0]), [2.0, 3.0, 4.0, 1.0])
    Rz = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # base yawed +90 deg
    # World +x velocity is base -y; the angular part is already in base axes.
    np.testing.assert_allclose(
        robot_pinocchio.base_velocity_to_pinocchio(Rz, [1.0, 0, 0, 0.1, 0.2, 0.3]), [0, -1, 0, 0.1, 0.2, 0.3]
    )


def test_state_map_joint_orders(pin_model):
    m = tb.load_mj_model()
    smap = robot_pinocchio.StateMap(m, pin_model, tb.DRIVEN_JOINTS)
    x = np.arange(len(tb.DRIVEN_JOINTS), dtype=float)
    np.testing.assert_array_equal(smap.joints_from_pin(smap.joints_to_pin(x)), x)
    # Pinocchio's actuated order is the URDF tree's (legs first), not the controller's.
    assert pin_model.names[2] == "l_hip_pitch" and tb.DRIVEN_JOINTS[0] == "torso_pitch"
    for k, name in enumerate(tb.DRIVEN_JOINTS):
        assert smap.joints_to_pin(x)[pin_model.idx_vs[pin_model.getJointId(name)] - 6] == k
    with pytest.raises(ValueError, match="'nope' is not in the MuJoCo model"):
        robot_pinocchio.StateMap(m, pin_model, joints=("nope",))


# --------------------------------------------------------------------------------------
# The copies of wbc_jax's definitions (the peer stays JAX-free)
# --------------------------------------------------------------------------------------


def test_copies_match_wbc_jax(robot):
    params = contacts.ContactParams()
    assert tb.FOOT_SIZE == params.foot_size and tb.FZ_MIN == params.fz_min
    assert tb.DRIVEN_JOINTS == ICUB.joints
    m, ref_m = tb.load_mj_model(), model.load_mj_model()
    assert (m.nq, m.nv, m.nu, m.nbody, m.ngeom) == (ref_m.nq, ref_m.nv, ref_m.nu, ref_m.nbody, ref_m.ngeom)
    np.testing.assert_array_equal(m.body_mass, ref_m.body_mass)
    np.testing.assert_array_equal(m.key("home").qpos, robot.home_qpos())
    assert tb.floor_friction(m) == 1.0  # the MJCF's contact pairs (assets/build_icub_mjcf.FLOOR_FRICTION)
    for task in tb.TASKS:
        spec, _ = bc.make_spec(task)
        np.testing.assert_array_equal(tb.non_foot_bodies(m), spec.non_foot_bodies)
        assert tb.FOOT_SIZE == spec.foot_size
        peer_sched = tb.make_schedule(task, spec.ref_com_pos[0], spec.ref_s_des[0])  # sin(0) = 0: com0
        ref_sched = references.make_schedule(
            task,
            com0=spec.ref_com_pos[0],
            s0=spec.ref_s_des[0],
            left_sole=np.zeros(3),
            joints=ICUB.joints,
            foot_lift_deg=ICUB.foot_lift_deg,
        )
        assert peer_sched.duration == ref_sched.duration == spec.n_ticks * spec.control_dt
        times = np.arange(spec.n_ticks) * spec.control_dt
        ours, theirs = bc.schedule_table(peer_sched, times), bc.schedule_table(ref_sched, times)
        for key in ours:
            np.testing.assert_array_equal(ours[key], theirs[key])
        np.testing.assert_allclose(ours["com_pos"], spec.ref_com_pos, atol=1e-15)
    with pytest.raises(ValueError, match="unknown task 'one-foot'"):
        tb.make_schedule("one-foot", np.zeros(3), np.zeros(23))


def test_lip_bound_and_bisection_match_wbc_jax(robot):
    azimuths = [0.0, 45.0, 90.0, 191.25]
    ours = pe.lip_bound(tb.load_mj_model(), robot.home_qpos(), azimuths)
    theirs = sweep_table.lip_bound(robot, azimuths)
    for az in azimuths:
        assert ours[az]["impulse_bound_ns"] == pytest.approx(theirs[az]["impulse_bound_ns"], rel=1e-12)
    assert ours[0.0]["impulse_bound_ns"] == pytest.approx(16.34, abs=0.01)  # 33.06 kg x 4.225 /s x 0.117 m, forward
    grid = np.linspace(10.0, 400.0, 64) * 0.1
    thresholds = np.random.default_rng(5).uniform(0.0, 41.0, 40)
    oracle = lambda k, impulse: impulse <= thresholds[k]  # noqa: E731
    a, b = pe.bisect(grid, oracle, thresholds.size, 0.25), envelope.bisect(grid, oracle, thresholds.size, 0.25)
    for key in ("lo", "hi", "grid_lo", "at_cap", "rollouts", "rounds"):
        np.testing.assert_array_equal(a[key], b[key])
    assert a["rollouts"] <= 8 * thresholds.size  # 6 grid rounds + 2 refinements per direction


# --------------------------------------------------------------------------------------
# (b), (c) TSID's closed loop
# --------------------------------------------------------------------------------------


@needs_tsid
def test_stand_10s_survives_with_small_drift(peer):
    r = peer.simulate("stand")
    s = r["summary"]
    drift = float(np.linalg.norm(r["com"][-1] - r["com_ref"][-1]))
    print(f"stand: drift {drift:.2e} m, {s}")
    assert s["survived"] and s["qp_infeasible_ticks"] == 0 and not s["nan"]
    # Measured 8.5e-5 m (the WBC controller: 4.7e-5 m RMSE, results/balance_acceptance.json).
    assert drift < 2e-4 and s["com_rmse_m"] < 2e-4
    assert s["max_foot_slip_m"] < 1e-4 and s["max_foot_tilt_deg"] < 0.05
    # Standing still asks the static torques only (measured 3.54 N m, the WBC's 3.47 N m).
    assert 3.0 < s["max_abs_torque_nm"] < 4.0
    assert s["max_constraint_violation"] < 1e-9
    # One tick through the controller's own interface, at the first tick's state: the loop's torques.
    ctrl = tb.TsidController(peer.pin_model, peer.map, peer.mj_model, peer.qpos0, peer.s0)
    ref0 = {"com_pos": r["com_ref"][0], "com_vel": np.zeros(3), "com_acc": np.zeros(3)}
    tau, info = ctrl(0.0, peer.qpos0, np.zeros(peer.mj_model.nv), ref0)
    assert info["status"] == 0 and not info["infeasible"]
    np.testing.assert_allclose(tau, r["tau"][0], rtol=1e-9, atol=1e-9)


@needs_tsid
def test_sinusoid_20s_tracks_the_com(peer):
    r = peer.simulate("sinusoid", timing=True)
    s = r["summary"]
    print(f"sinusoid: {s}; timing {r['timing']}")
    assert s["survived"] and s["qp_infeasible_ticks"] == 0
    # Measured 0.83 mm; the bar: the WBC controller's 1.00 mm on the same task and plant
    # (results/balance_acceptance.json), under the project's tuning bound SINUSOID_MAX_COM_RMSE_M (1.5 mm).
    # Standing still instead of tracking would give 2 cm / sqrt(2) = 14 mm.
    assert s["com_rmse_m"] < 1.0e-3 < constants.SINUSOID_MAX_COM_RMSE_M
    late = r["t"] >= 10.0
    swing = np.ptp(r["com"][late, 1])
    assert swing == pytest.approx(2 * tb.SINE_AMPLITUDE, rel=0.05)  # 4 cm peak to peak along y
    assert np.ptp(r["com"][late, 0]) < 2e-3


@needs_tsid
def test_pushes_act_on_the_named_body(peer):
    push = pe.push_of(40.0, 90.0, 0.5, 0.1)  # 40 N to the left on the chest: recovered
    s = peer.simulate("stand", duration=3.0, push=push, record=False)["summary"]
    assert s["survived"] and s["com_max_err_m"] > 2e-3, s  # it moved the CoM, and the robot recovered
    s = peer.simulate("stand", duration=3.0, push=pe.push_of(400.0, 0.0, 0.5, 0.1), record=False)["summary"]
    assert s["fell"] and not s["survived"], s  # 40 N s forward: over twice the LIP bound
    with pytest.raises(ValueError, match="unknown body 'torso'; valid bodies: .*'chest'"):
        peer.simulate("stand", duration=1.0, push=push, push_body="torso")


def test_config_checks():
    with pytest.raises(ValueError, match="w_posture must be a finite number >= 0"):
        tb.TsidConfig(w_posture=-1.0)
    with pytest.raises(ValueError, match="fz_min <= fz_max"):
        tb.TsidConfig(fz_min=20.0, fz_max=10.0)
    with pytest.raises(ValueError, match="kp_posture must be 23 finite numbers"):
        tb.TsidConfig(kp_posture=(1.0, 2.0)).gains(ICUB, 23)
    g = tb.TsidConfig().gains(ICUB, 23)
    np.testing.assert_array_equal(g["kp_com"], ICUB.gains.kp_com)
    np.testing.assert_allclose(g["kd_com"], 2 * np.sqrt(ICUB.gains.kp_com) / 20)
    np.testing.assert_allclose(g["kd_posture"], 2 * np.sqrt(ICUB.gains.kp_postural))
    np.testing.assert_array_equal(tb.TsidConfig().corners(ICUB)[:, 0], [-0.07, -0.045, 0.0])
    # Another robot's defaults are its own: Talos's postural gains and CoP rectangle.
    np.testing.assert_array_equal(tb.TsidConfig().gains(TALOS)["kp_posture"], TALOS.gains.kp_postural)
    np.testing.assert_array_equal(tb.TsidConfig().corners(TALOS)[:, 0], [-0.1, -0.06, 0.0])


@needs_tsid
def test_the_peer_runs_on_talos():
    """Issue 47: TSID's controller on Talos (example-robot-data's URDF in Pinocchio, assets/talos/'s
    MJCF on C MuJoCo): the URDF's sole frames sit on the MJCF's sole sites, the masses agree, and it
    stands; a body of the iCub is refused in one line."""
    import pinocchio as pin

    peer = tb.TsidPeer(robot="talos")
    m, pm = peer.mj_model, peer.pin_model
    assert peer.map.joints == TALOS.joints and (pm.nq, pm.nv) == (m.nq, m.nv) == (29, 28)
    assert pin.computeTotalMass(pm) == pytest.approx(float(m.body_subtreemass[1]), rel=1e-9)
    d, pd = mujoco.MjData(m), pm.createData()
    d.qpos[:] = peer.qpos0
    mujoco.mj_kinematics(m, d)
    pin.framesForwardKinematics(pm, pd, peer.map.q_v(peer.qpos0, np.zeros(m.nv))[0])
    for site, frame in zip(TALOS.feet, TALOS.pinocchio_feet):
        np.testing.assert_allclose(pd.oMf[pm.getFrameId(frame)].translation, d.site_xpos[m.site(site).id], atol=1e-9)
    s = peer.simulate("stand", duration=1.0, record=False)["summary"]
    assert s["survived"] and s["com_max_err_m"] < 1e-3 and s["qp_infeasible_ticks"] == 0, s
    with pytest.raises(SystemExit, match="unknown body 'chest'"):
        tp.main(["--robot", "talos", "--body", "chest", "--out", "/nonexistent/tsid.json"])


@needs_tsid
def test_measurement_script_writes_its_json(tmp_path):
    out = tmp_path / "tsid.json"
    argv = [
        "--out",
        str(out),
        "--directions",
        "2",
        "--magnitudes",
        "10",
        "400",
        "4",
        "--horizon",
        "1.5",
        "--sinusoid-duration",
        "2",
        "--stand-duration",
        "1",
        "--resolution",
        "20",
    ]
    result = tp.main(argv)
    saved = json.loads(out.read_text())
    assert saved["command"] == "python benchmarks/tsid_peer.py " + " ".join(argv)
    for section in ("timing", "sinusoid", "stand", "envelope"):
        assert saved[section]["command"] == saved["command"]
    assert set(constants.METRIC_NAMES) <= set(saved["sinusoid"])
    assert saved["versions"]["tsid"] and saved["cpu"] and saved["threads"]["OMP_NUM_THREADS"] == "1"
    e = saved["envelope"]
    # 4 grid forces (1, 14, 27, 40 N s): 2 bisection rounds, no refinement at a 20 N s resolution.
    assert sorted(e["directions"]) == ["0", "180"] and e["rollouts"] <= 2 * 2
    assert result["timing"]["controller_us_per_tick"] > 0
    for row in e["directions"].values():
        assert row["impulse_ns"] in (0.0, 1.0, 14.0, 27.0) and 10.0 < row["bound_impulse_ns"] < 25.0
    with pytest.raises(SystemExit):
        tp.main(["--out", str(out), "--body", "torso"])


def test_measurement_script_without_pushes_writes_the_tick_only(tmp_path):
    out = tmp_path / "tsid_timing.json"
    tp.main(
        [
            "--out",
            str(out),
            "--no-envelope",
            "--sinusoid-duration",
            "1",
            "--stand-duration",
            "0.5",
            "--timing-repeats",
            "2",
        ]
    )
    saved = json.loads(out.read_text())
    assert "envelope" not in saved and "grid" not in saved
    assert len(saved["timing"]["repeats"]["controller_us_per_tick"]) == 2
    assert saved["timing"]["ticks"] == 100 and saved["timing"]["controller_cpu_us_per_tick"] > 0
