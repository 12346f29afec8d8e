"""rerun visualisation: a real balance run viewed and its .rrd read back; CLI errors; (nightly) a tiny real sweep, the
replay of its envs and the .rrd of one.

The default suite compiles nothing of its own: the balance run is the session's shared 1 s C MuJoCo loop
(conftest.SHARED_BALANCE, compiled by tests/test_rollout.py and loaded from the compilation cache). The sweep path
compiles the vmapped sweep and the recording replay (109 s of the 2-core suite): nightly (`slow`)."""

import collections
import dataclasses

import mujoco
import numpy as np
import pytest
from conftest import SHARED_BALANCE

from wbc_jax import cli
from wbc_jax.core import io
from wbc_jax.jobs import sweep, sweep_config
from wbc_jax.report import recording as viz

rr = pytest.importorskip("rerun")
from rerun.chunk import RrdReader  # noqa: E402

# Two envs that differ in every scenario axis but the push: gain set 0 (default) and 1 (scaled),
# random joint offsets, friction and mass scale of the plant.
CFG = sweep_config.SweepConfig(
    magnitudes=(150.0,),
    directions=(90.0,),
    gain_sets=2,
    horizon=0.3,
    push_onset=0.05,
    push_duration=0.1,
    joint_noise=0.01,
    friction=(0.5, 1.0),
    mass_scale=(0.9, 1.1),
    chunk_size=2,
    seed=3,
)
COMPARED = ("com_max_err_m", "com_rmse_m", "max_abs_torque_nm", "min_com_height_m", "max_foot_slip_m")
# The balance run: 40 N to the left on the trunk for 0.1 s from 0.3 s (inputs of the shared program, not its shape).
PUSH = ["--push-force", "0", "40", "0", "--push-onset", "0.3", "--push-duration", "0.1"]


@pytest.fixture(scope="module")
def balance_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("balance") / "run"
    assert cli.main([*SHARED_BALANCE, *PUSH, "--out", str(out), "--quiet"]) == 0
    return out


@pytest.fixture(scope="module")
def sweep_dir(tmp_path_factory, robot):
    out = tmp_path_factory.mktemp("sweep") / "run"
    sweep.run_sweep(dataclasses.replace(CFG, out=str(out)), progress=False)
    return out


@pytest.fixture(scope="module")
def replays(sweep_dir):
    return [sweep.replay_env(sweep_dir, env)[1:] for env in range(CFG.size)]


def read_rrd(path):
    """Per entity: the set of sim_time values (ns) of its temporal rows; the static entities;
    the temporal record batches per entity."""
    times, static, batches = collections.defaultdict(set), set(), collections.defaultdict(list)
    for chunk in RrdReader(path).stream():
        if chunk.is_static:
            static.add(chunk.entity_path)
            continue
        rb = chunk.to_record_batch()
        if viz.TIMELINE in rb.schema.names:
            times[chunk.entity_path].update(rb.column(viz.TIMELINE).cast("int64").to_pylist())
            batches[chunk.entity_path].append(rb)
    return times, static, batches


def column_by_time(batches, component: str) -> dict:
    """{sim_time ns: value} of one component over an entity's record batches."""
    out = {}
    for rb in batches:
        t = rb.column(viz.TIMELINE).cast("int64").to_pylist()
        for k, v in zip(t, rb.column(component).to_pylist()):
            out[k] = v
    return out


@pytest.mark.slow
def test_replay_equals_the_sweep_metrics(replays):
    for env, (traj, metrics, row) in enumerate(replays):
        assert traj["t"].shape == (int(round(CFG.horizon / 0.01)),)
        assert bool(metrics["fell"]) == bool(row["fell"]) and bool(metrics["nan"]) == bool(row["nan"])
        for name in COMPARED:
            assert metrics[name] == pytest.approx(row[name], rel=1e-6, abs=1e-9), f"env {env} {name}"
        # The recorded push is this env's push: 150 N to the left during [0.05, 0.15) s.
        on = (traj["t"] >= CFG.push_onset) & (traj["t"] < CFG.push_onset + CFG.push_duration)
        assert on.sum() in (10, 11)  # 0.1 s at 100 Hz (the end tick is decided by rounding)
        np.testing.assert_allclose(traj["push"][on], [[0.0, 150.0, 0.0]] * on.sum(), atol=1e-9)
        assert np.all(traj["push"][~on] == 0)
    # The two scenarios differ measurably, so matching the wrong row would fail.
    (_, m0, _), (_, m1, _) = replays
    assert abs(m0["com_max_err_m"] - m1["com_max_err_m"]) > 1e-5


def check_rrd(path, traj):
    """The .rrd at ``path`` shows the trajectory ``traj`` (a run's records, (T, ...)): every entity at every tick,
    the meshes once, the base's pose, the push arrow while the push acts, the CoM error series."""
    times, static, batches = read_rrd(path)
    m = viz.visual_model()
    bodies = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b) for b in range(1, m.nbody)]
    expected = {f"/world/robot/{b}" for b in bodies} | {
        f"/{p}"
        for p in (
            "world/com",
            "world/com_ref",
            "world/com/trail",
            "world/com_ref/trail",
            "world/support_polygon",
            "world/contacts/f_meas",
            "world/contacts/f_cmd",
            "world/contacts/normals",
            "world/push",
            "plots/com_error_mm",
            "plots/Ldot_star",
            "plots/Ldot_meas",
            "plots/tau",
            "plots/f_cmd",
            "plots/f_meas",
            "plots/activation",
        )
    }
    assert expected <= set(times), sorted(expected - set(times))
    want = {int(round(t * 1e9)) for t in traj["t"]}
    for entity in expected:
        assert times[entity] == want, entity  # one row per controller tick, at the tick's time
    # Every mesh logged once (static), under its body.
    meshes = [p for p in static if "/geom_" in p]
    assert len(meshes) == int((m.geom_type == mujoco.mjtGeom.mjGEOM_MESH).sum()) == 39
    # The floating base's pose is the trajectory's base position (free joint: xpos = qpos[:3]).
    base = column_by_time(batches["/world/robot/root_link"], "Transform3D:translation")
    got = np.array([base[int(round(t * 1e9))][0] for t in traj["t"]])
    np.testing.assert_allclose(got, traj["qpos"][:, :3], atol=1e-5)
    # Push arrow only while the push acts, pointing along it (+y), scaled by FORCE_SCALE.
    push = column_by_time(batches["/world/push"], "Arrows3D:vectors")
    assert np.any(traj["push"] != 0)  # the arrow is checked where it shows, not only where it is empty
    for t, f in zip(traj["t"], traj["push"]):
        v = push[int(round(t * 1e9))] or []
        if np.any(f != 0):
            np.testing.assert_allclose(v[0], f * viz.FORCE_SCALE, rtol=1e-5)
        else:
            assert v == []
    # Series values: the CoM error is |com - com_ref| in mm.
    err = column_by_time(batches["/plots/com_error_mm"], "Scalars:scalars")
    np.testing.assert_allclose(
        [err[int(round(t * 1e9))][0] for t in traj["t"]],
        1e3 * np.linalg.norm(traj["com"] - traj["com_ref"], axis=1),
        rtol=1e-5,
    )


def test_rrd_of_a_balance_run_dir(balance_dir, tmp_path):
    """`wbc-jax view` of a balance run's folder: the .rrd shows its trajectory.npz, tick by tick."""
    out = tmp_path / "x" / "mine.rrd"
    assert cli.main(["view", str(balance_dir), "--out", str(out)]) == 0
    with np.load(balance_dir / "trajectory.npz") as data:
        traj = dict(data)
    assert traj["t"].shape == (100,)  # 1 s at 100 Hz
    on = np.any(traj["push"] != 0, axis=1)
    assert on.sum() in (10, 11)  # 0.1 s at 100 Hz (the end tick is decided by rounding)
    np.testing.assert_allclose(traj["push"][on], [[0.0, 40.0, 0.0]] * on.sum(), atol=1e-9)
    check_rrd(out, traj)


@pytest.mark.slow
def test_rrd_of_a_sweep_env(sweep_dir, replays, robot):
    """`wbc-jax view SWEEP --env 1`: the .rrd shows that env's replay."""
    assert cli.main(["view", str(sweep_dir), "--env", "1"]) == 0
    check_rrd(sweep_dir / "env_1.rrd", replays[1][0])


def _refused(argv, message, capsys):
    assert cli.main(argv) == 2, argv
    err = capsys.readouterr().err
    assert __import__("re").search(message, err), (argv, err)


def test_view_errors_name_the_problem(balance_dir, tmp_path, capsys):
    (tmp_path / "file.txt").write_text("x")
    for argv, message in [
        (["view", str(tmp_path / "nope")], "does not exist"),
        (["view", str(tmp_path / "file.txt")], "is a file"),
        (["view", str(tmp_path)], "neither a balance run"),
        (["view", str(balance_dir), "--env", "0"], "--env applies to sweeps only"),
    ]:
        _refused(argv, message, capsys)
    io.atomic_save_npz(tmp_path / "trajectory.npz", t=np.zeros(1))
    _refused(["view", str(tmp_path)], "trajectory lacks fields", capsys)
    (tmp_path / "trajectory.npz").write_bytes(b"PK\x03\x04 truncated")
    _refused(["view", str(tmp_path)], "trajectory.npz is unreadable", capsys)


@pytest.mark.slow
def test_view_of_a_sweep_names_its_envs(sweep_dir, capsys):
    for argv, message in [
        (["view", str(sweep_dir)], r"push sweep of 2 envs: choose one with --env I, I in 0..1"),
        (["view", str(sweep_dir), "--env", "2"], r"env 2 is out of range: this sweep has envs 0..1"),
        (["view", str(sweep_dir), "--env", "-1"], r"--env must be a whole number in \[0, "),
    ]:
        _refused(argv, message, capsys)
    assert sweep.load_sweep(sweep_dir)[0] == dataclasses.replace(CFG, out=str(sweep_dir))


def test_support_polygon_at_home_is_the_hull_of_both_soles(robot):
    from scipy.spatial import ConvexHull

    m = viz.visual_model()
    _, _, gpos = viz.body_poses(m, robot.home_qpos()[None])
    (poly,) = viz.support_polygons(m, gpos)
    assert np.array_equal(poly[0], poly[-1])  # closed
    x, y = poly[:, 0], poly[:, 1]
    area = 0.5 * abs(np.dot(x[:-1], y[1:]) - np.dot(x[1:], y[:-1]))
    names = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, g) or "" for g in range(m.ngeom)]
    soles = gpos[0, [g for g, n in enumerate(names) if "_foot_contact" in n]]
    assert len(soles) == 8
    assert area == pytest.approx(ConvexHull(soles[:, :2]).volume, rel=1e-9)
    # Both soles (0.195 m long, feet 0.14 m apart, ~0.096 m wide) span ~0.195 x 0.23 m.
    assert np.ptp(x) == pytest.approx(0.195, abs=0.01) and np.ptp(y) > 0.2
    # A lifted robot touches nothing.
    q = robot.home_qpos()
    q[2] += 0.05
    _, _, gpos = viz.body_poses(m, q[None])
    assert len(viz.support_polygons(m, gpos)[0]) == 0
