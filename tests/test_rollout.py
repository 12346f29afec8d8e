"""The closed loop: the C MuJoCo backend against the MJX closed loop (float64, the benchmark
scenario), the pushes, the metrics' geometry, one set of metric names."""

import dataclasses
import os
import pathlib
import subprocess
import sys

import jax
import numpy as np
import pytest
from scipy.spatial import ConvexHull

from wbc_jax.control.controller import ControllerConfig
from wbc_jax.core import constants
from wbc_jax.sim import host_loop, mjx_loop, native, physics, runner, scenario
from wbc_jax.sim import metrics as metrics_lib
from wbc_jax.sim.state import SimConfig

ROOT = pathlib.Path(__file__).resolve().parent.parent
PUSH = ([0.0, 40.0, 0.0], 0.3, 0.1)  # the benchmark scenario: stand, 40 N lateral chest push, 1 s
# A compiled batch against its environments compiled alone (float64): measured up to 5.3e-14 relative and 2.4e-13
# absolute (2026-11-27, AMD EPYC); two code paths differed by up to 1.1e-9 relative on other x86 CPUs (issue 41).
# Any real difference (a tick's push, a sub-step) moves these metrics by > 1e-4.
RTOL_BATCH_ALONE, ATOL_BATCH_ALONE = 1e-7, 3e-9


def _run(backend: str):
    st = scenario.setup("stand", duration=1.0, sim=SimConfig(physics=physics.PhysicsConfig(backend=backend)))
    return st, runner.run(st, scenario.single(st, scenario.make_push(*PUSH, st.dtype)))


@pytest.fixture(scope="module")
def runs():
    """The benchmark scenario on C MuJoCo; tests/test_baseline_cpu.py and the balance runs of tests/test_tune.py
    and tests/test_wheel.py (SHARED_BALANCE) run the same program (one compile in the session)."""
    return {"mujoco": _run("mujoco")}


# Compiling the MJX closed loop costs ~75 CPU s on the 2-core machine: nightly (`slow`). The default suite keeps the
# MJX loop's traced chunk (test_closed_loop_products_run_in_full_float32), MJX physics' gradients
# (tests/test_mjx_physics.py) and the controller against the NumPy baseline on C MuJoCo (tests/test_baseline_cpu.py).
@pytest.mark.slow
def test_c_mujoco_backend_equals_the_mjx_closed_loop(runs):
    """Same controller code, two physics engines: the CoM stays within 1e-6 m over 1 s (float64)."""
    (_, mjx_run), (_, c_run) = _run("jax"), runs["mujoco"]
    com_mjx, com_c = mjx_run.records.com[0], c_run.records.com[0]
    assert com_mjx.shape == com_c.shape == (100, 3)
    assert np.abs(com_mjx - com_c).max() < 1e-6
    # The push moved the robot (the check is not of a robot standing still).
    assert np.linalg.norm(com_c - com_c[0], axis=1).max() > 0.01
    # The measured wrenches (each engine's own contact read) agree too.
    np.testing.assert_allclose(mjx_run.records.f_meas[0], c_run.records.f_meas[0], atol=1e-3)
    m_mjx = metrics_lib.summarize(jax.tree_util.tree_map(lambda x: x[0], mjx_run.metrics))
    m_c = metrics_lib.summarize(jax.tree_util.tree_map(lambda x: x[0], c_run.metrics))
    assert set(m_c) == set(constants.METRIC_NAMES)
    for name in ("com_rmse_m", "com_max_err_m", "max_abs_torque_nm", "max_foot_slip_m", "min_com_height_m"):
        assert m_c[name] == pytest.approx(m_mjx[name], rel=1e-5, abs=1e-9), name
    assert m_c["upright"] and not m_c["nan"]


def test_a_robot_thrown_away_is_neither_upright_nor_survived(runs):
    """Issue 41, class 5: a chest push of 5000 N up and sideways for 0.1 s throws the robot metres
    away, upside down, its CoM never low and no body near the floor (the CoM and floor tests pass:
    they alone called it upright). The trunk's tilt makes it a fall; every boolean of the summary
    is checked, on the compiled C MuJoCo loop of ``runs`` (nothing compiles again)."""
    st, standing = runs["mujoco"]
    thrown = runner.run(st, scenario.single(st, scenario.make_push([0.0, 3000.0, 4000.0], 0.3, 0.1, st.dtype)))
    m = metrics_lib.summarize(jax.tree_util.tree_map(lambda x: x[0], thrown.metrics))
    com = thrown.records.com[0]
    assert np.linalg.norm(com[-1, :2] - com[0, :2]) > 2.0 and com[-1, 2] > 2.0  # metres away, in the air
    assert m["min_com_height_m"] > constants.FALL_COM_HEIGHT * com[0, 2]  # the CoM test never fired
    assert np.degrees(float(thrown.metrics.max_trunk_tilt[0])) > 120.0
    booleans = {k: bool(v) for k, v in m.items() if isinstance(v, (bool, np.bool_))}
    assert booleans == {"survived": False, "upright": False, "fell": True, "nan": False}
    assert np.isnan(m["time_to_recover_s"])
    # The 40 N benchmark push of the same loop: the trunk stays within a few degrees, upright.
    still = metrics_lib.summarize(jax.tree_util.tree_map(lambda x: x[0], standing.metrics))
    assert still["upright"] and not still["fell"] and not still["nan"]
    assert np.degrees(float(standing.metrics.max_trunk_tilt[0])) < 10.0


def _batch_against_alone(forces: str, driver: str = "python", rtol: float = 0.0, atol: float = 0.0):
    """A batch of two on C MuJoCo: each environment's metrics equal those of the same environment run alone
    (within rtol, atol), a diverged one (NaN joints) is flagged and poisons nothing. The Python loop runs an
    even batch without records as two halves in a pipeline (one half's controller beside the other half's
    physics); the compiled loop, one program over the batch. Returns (setup, the pushed environment's metrics
    run alone)."""
    st = scenario.setup(
        "stand",
        duration=1.0,
        sim=SimConfig(record=False, host_loop=driver, physics=physics.PhysicsConfig(backend="mujoco")),
        controller=ControllerConfig(forces=forces),
    )
    pushed = scenario.single(st, scenario.make_push(*PUSH, st.dtype))
    broken = pushed.replace(joint_offset=np.full_like(pushed.joint_offset, np.nan))
    both = jax.tree_util.tree_map(lambda a, b: np.concatenate([np.asarray(a), np.asarray(b)]), pushed, broken)
    together = runner.run(st, both).metrics
    alone = [runner.run(st, one).metrics for one in (pushed, broken)]
    for k in range(2):
        for name, value in vars(alone[k]).items():
            np.testing.assert_allclose(
                np.asarray(getattr(together, name))[k], np.asarray(value)[0], rtol=rtol, atol=atol, err_msg=name
            )
    assert not bool(together.nan[0]) and bool(together.nan[1]) and int(together.ticks[0]) == 100
    assert float(together.com_max_err[0]) > 1e-3  # the push moved the robot
    return st, alone[0]


def test_pipelined_host_batch_equals_environments_run_alone():
    """The Python loop of ticks (the C MuJoCo loop where the native step is not built), pipelined, on the analytic
    force distribution: its tick compiles in a fraction of the QP's (the QP's, and the compiled loop against it:
    the nightly test below)."""
    _batch_against_alone("analytic")


def test_compiled_batch_equals_environments_run_alone():
    """The compiled loop of a batch (``host_loop`` "auto" on any batch where the native step builds) against
    each environment compiled alone: one robot is traced without ``vmap``, so XLA may round differently."""
    if native.available() is not None:
        pytest.skip(f"native step: {native.available()}")
    _batch_against_alone("analytic", "compiled", rtol=RTOL_BATCH_ALONE, atol=ATOL_BATCH_ALONE)


# The Python loop's tick with the QP compiles in 50 CPU s on the 2-core machine: nightly (`slow`).
@pytest.mark.slow
def test_pipelined_qp_host_batch_equals_the_compiled_loop(runs):
    """The same on the QP (the benchmark scenario's controller); and the Python loop of ticks and the compiled loop
    (one program, C MuJoCo called from XLA) give the same metrics to float noise."""
    _, alone = _batch_against_alone("qp")
    compiled = runs["mujoco"][1]
    assert host_loop.driver(runs["mujoco"][0].loop) == ("compiled" if native.available() is None else "python")
    # Two code paths: their float64 rounding differs by CPU. Measured over the metrics: 1.1e-9 relative, 4.9e-11
    # absolute here, 3.8e-10 with XLA held to AVX2, 1.13e-9 on another 2-core x86 (issue 41); bars ~100x that. Any
    # real difference (a tick's push, a sub-step) moves these metrics by > 1e-4. The halves above run the program
    # of one environment alone on the same inputs: bit-equal (measured 0 here and with AVX2).
    for name, value in vars(alone).items():
        np.testing.assert_allclose(
            np.asarray(getattr(compiled.metrics, name), float),
            np.asarray(value, float),
            rtol=1e-7,
            atol=3e-9,
            err_msg=name,
        )


def test_a_rerun_with_new_gains_compiles_nothing(runs):
    """A notebook cell run again with other gains: the compiled loop of the same shape is reused
    (compile_s 0) and the new gains act (the CoM moves otherwise)."""
    st, first = runs["mujoco"]
    softer = jax.tree_util.tree_map(lambda g: np.asarray(g) * 0.5, st.gains)
    again = runner.run(st, scenario.single(st, scenario.make_push(*PUSH, st.dtype), gains=softer))
    assert again.compile_s == 0.0
    assert np.abs(again.records.com[0] - first.records.com[0]).max() > 1e-4


def test_recorded_push_and_host_wrenches(runs):
    st, run = runs["mujoco"]
    traj = run.records
    on = (traj.t[0] >= PUSH[1]) & (traj.t[0] < PUSH[1] + PUSH[2])
    assert on.sum() in (10, 11)
    np.testing.assert_allclose(traj.push[0][on], [PUSH[0]] * on.sum(), atol=1e-9)
    # The host scatters the tick's push forces onto their bodies as the traced physics does:
    # two pushes (one on the default body, one on the pelvis) over the push's first tick.
    two = jax.tree_util.tree_map(
        lambda a, b: np.concatenate([a, b]),
        scenario.make_push(*PUSH),
        scenario.make_push([5.0, 0.0, 0.0], 0.3, 0.05, body=st.robot.index.body_id("root_link")),
    )
    for k in (29, 30, 34, 35, 39, 40):
        traced = np.asarray(st.loop.xfrc(two, k))
        forces = np.asarray(st.loop.step_push_forces(two, k))[None]
        host = host_loop.host_xfrc(st.loop, forces, np.asarray(st.loop.push_bodies(two))[None])[0]
        np.testing.assert_allclose(host, traced, atol=1e-9)
    assert np.abs(np.asarray(st.loop.xfrc(two, 32))).sum() > 0


def test_polygon_margin_is_the_distance_to_the_hull():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-1, 1, size=(8, 2))
    hull = ConvexHull(pts)
    for p in rng.uniform(-1.5, 1.5, size=(20, 2)):
        inside = np.all(hull.equations[:, :2] @ p + hull.equations[:, 2] <= 0)
        margin = float(metrics_lib.polygon_margin(jax.numpy.asarray(pts), jax.numpy.asarray(p)))
        if inside:  # the distance to the nearest edge line
            assert margin == pytest.approx(-np.max(hull.equations[:, :2] @ p + hull.equations[:, 2]), abs=1e-9)
        else:
            assert margin < 0


def test_polygon_margin_in_float32_on_tilted_soles():
    """Sole corners in float32 (rounding puts collinear corners a hair apart): the margin is finite
    and equals the float64 one."""
    rng = np.random.default_rng(1)
    x0, x1, y0, y1 = -0.07, 0.12, -0.045, 0.045
    for _ in range(50):
        pts = []
        for foot in (-1, 1):
            c, s = np.cos(rng.uniform(-0.3, 0.3)), np.sin(rng.uniform(-0.3, 0.3))
            local = np.array([[x, y] for x in (x0, x1) for y in (y0, y1)]) @ np.array([[c, s], [-s, c]])
            pts.append(local * rng.uniform(0.95, 1.0) + np.array([0.01, foot * 0.07]) + rng.normal(scale=2e-3, size=2))
        pts = np.concatenate(pts) * 10 ** rng.uniform(-0.2, 0.4)
        p = rng.normal(scale=0.05, size=2)
        m32 = float(metrics_lib.polygon_margin(jax.numpy.asarray(pts, np.float32), jax.numpy.asarray(p, np.float32)))
        m64 = float(metrics_lib.polygon_margin(jax.numpy.asarray(pts, np.float64), jax.numpy.asarray(p, np.float64)))
        assert np.isfinite(m32) and abs(m32 - m64) < 1e-5, (m32, m64)


def _aligned_soles(offset):
    """(8, 2) float32 corners of two parallel soles side by side (front and back edges collinear),
    shifted by ``offset``: the stand posture's support polygon."""
    x0, x1, y0, y1 = -0.07, 0.12, -0.045, 0.045
    feet = [np.array([[x, y] for x in (x0, x1) for y in (y0, y1)]) + [0.01, f * 0.07] for f in (-1, 1)]
    return (np.concatenate(feet) + offset).astype(np.float32)


def test_support_geometry_uses_no_matrix_products():
    """The support-polygon metrics compare against a 1e-6 m tolerance: a GPU may run float32 matrix
    products in TensorFloat-32 (1e-4 m here), which turned the stand posture's margin negative on
    an H200 (24 % of a 40 N benchmark batch counted as failed). No dot_general may appear in them."""
    pts, p = _aligned_soles([0.4, -0.3]), np.float32([0.42, -0.3])
    jaxpr = str(jax.make_jaxpr(metrics_lib.polygon_margin)(pts, p))
    assert "dot_general" not in jaxpr
    cset = scenario.setup("stand", duration=0.05).loop.contact_set
    K = len(cset.contacts)
    corners = jax.make_jaxpr(lambda pos, R: metrics_lib.support_corners(cset, pos, R))(
        np.zeros((K, 3), np.float32), np.tile(np.eye(3, dtype=np.float32), (K, 1, 1))
    )
    assert "dot_general" not in str(corners)


def _dot_precisions(sim: SimConfig) -> list[str]:
    """The precision of every matrix product in the start and one tick of the MJX closed loop
    (controller and physics), as traced."""
    st = scenario.setup("stand", duration=0.02, sim=sim)
    one = jax.tree_util.tree_map(lambda x: x[0], scenario.single(st, scenario.make_push(*PUSH, st.dtype)))
    loop = st.loop
    tick = lambda q: mjx_loop.chunk(loop, loop.mx, one.gains, one.push, mjx_loop.start(loop, q), 0, 1)  # noqa: E731
    jaxpr = str(jax.make_jaxpr(tick)(st.qpos0))
    return [
        line.split("precision=")[1].split(")")[0] if "precision=" in line else "None"
        for line in jaxpr.split("dot_general[")[1:]
    ]


@pytest.mark.slow  # traces the MJX loop twice (21 CPU s); the GPU set checks the float32 loop against float64
def test_closed_loop_products_run_in_full_float32():
    """A GPU may run float32 products in TensorFloat-32 (a 10-bit mantissa), which moved survival
    outcomes at the fall boundary of a push grid (BENCHMARKS.md): every product of the loop's
    programs is traced at HIGHEST precision, unless the config asks for XLA's default."""
    sim = SimConfig(physics=physics.PhysicsConfig(backend="jax"), record=False)
    highest = _dot_precisions(sim)
    assert len(highest) > 50 and all(p.startswith("(Precision.HIGHEST") for p in highest)
    # XLA's default where the code names none (MJX asks for HIGHEST in a few products itself).
    default = _dot_precisions(dataclasses.replace(sim, matmul_precision="default"))
    assert len(default) == len(highest) and default.count("(Precision.DEFAULT, Precision.DEFAULT") > 0.8 * len(default)
    with pytest.raises(ValueError, match=r"unknown matmul_precision 'tf32'; valid: \['highest', 'default'\]"):
        SimConfig(matmul_precision="tf32")


@pytest.mark.gpu
def test_polygon_margin_on_the_gpu_equals_float64():
    """On a CUDA GPU (skipped on the CPU): the float32 margin of the stand posture's soles, at
    offsets up to a few metres, equals the float64 one on the host to 1e-5 m."""
    rng = np.random.default_rng(2)
    fn = jax.jit(metrics_lib.polygon_margin)
    for _ in range(64):
        off = rng.uniform(-3, 3, 2)
        pts, p = _aligned_soles(off), (off + rng.normal(scale=0.05, size=2)).astype(np.float32)
        with jax.default_device(jax.devices("cpu")[0]), jax.enable_x64(True):
            m64 = float(metrics_lib.polygon_margin(np.float64(pts), np.float64(p)))
        m32 = float(fn(pts, p))
        assert abs(m32 - m64) < 1e-5, (off, m32, m64)


def test_fall_thresholds_are_70_percent_of_the_com_height_and_5_cm():
    """The fall (docs/usage.md, "Survival"): the CoM below 70 % of its initial height, or a body other than the feet
    and ankles below 5 cm; just above either threshold is no fall."""
    assert (constants.FALL_COM_HEIGHT, constants.BODY_FLOOR_HEIGHT) == (0.7, 0.05)
    z = jax.numpy.zeros(3)
    state = dict(
        com_ref=z,
        com_vel=z,
        tau=jax.numpy.zeros(23),
        violation=0.0,
        infeasible=jax.numpy.asarray(False),
        contact_pos=jax.numpy.zeros((2, 3)),
        normals=jax.numpy.tile(jax.numpy.eye(3)[2], (2, 1)),
        anchors=jax.numpy.zeros((2, 3)),
        anchor_normals=jax.numpy.tile(jax.numpy.eye(3)[2], (2, 1)),
        fully_active=jax.numpy.ones(2, bool),
        support=jax.numpy.asarray([[0, 0], [1, 0], [0, 1.0]]),
        com0_height=0.5,
        t_now=0.0,
        physics_ok=jax.numpy.asarray(True),
    )

    def fell(com_z, lowest_body, trunk_deg=0.0):
        met = metrics_lib.initial(jax.numpy.asarray(0.5), jax.numpy.float64)
        heights = jax.numpy.asarray([0.3, lowest_body, 0.9])
        trunk = jax.numpy.asarray([np.sin(np.radians(trunk_deg)), 0.0, np.cos(np.radians(trunk_deg))])
        return bool(
            metrics_lib.update(
                met, com=jax.numpy.asarray([0, 0, com_z]), body_heights=heights, trunk_z=trunk, **state
            ).fell
        )

    assert not fell(0.351, 0.051) and fell(0.349, 0.051) and fell(0.351, 0.049)
    # The trunk (issue 41): tilted past FALL_TRUNK_TILT_DEG is a fall, however high the CoM.
    tilt = constants.FALL_TRUNK_TILT_DEG
    assert not fell(0.5, 0.3, tilt - 0.1) and fell(0.5, 0.3, tilt + 0.1) and fell(3.0, 2.0, 170.0)
    # Which bodies count: every body but the world, the feet and the links above the soles (ankles).
    st = scenario.setup("stand", duration=0.02, sim=SimConfig(physics=physics.PhysicsConfig(backend="mujoco")))
    m = st.robot.mj_model
    names = {m.body(int(b)).name for b in st.loop.non_foot_bodies}
    assert "chest" in names and "root_link" in names and len(names) == m.nbody - 1 - 4
    assert not names & {"l_ankle_1", "l_ankle_2", "r_ankle_1", "r_ankle_2", "world"}, names


def test_blown_up_states_count_as_diverged():
    """Finite but unphysical speeds are a divergence (flagged and frozen), like NaN."""
    q, v = np.zeros(30), np.zeros(29)
    assert physics.state_ok(q, v) and bool(physics.state_ok(jax.numpy.asarray(q), jax.numpy.asarray(v)))
    for bad_v in (np.full(29, 2e4), np.where(np.arange(29) == 3, np.inf, 0.0)):
        assert not physics.state_ok(q, bad_v) and not bool(
            physics.state_ok(jax.numpy.asarray(q), jax.numpy.asarray(bad_v))
        )
    assert not physics.state_ok(np.full(30, np.nan), v)


def test_bad_settings_are_named():
    with pytest.raises(ValueError, match="duration must be a positive finite"):
        SimConfig(duration=float("inf"))
    with pytest.raises(ValueError, match="control_dt must be a positive"):
        SimConfig(control_dt=0.0)
    with pytest.raises(ValueError, match="unknown physics backend 'gpu'"):
        physics.PhysicsConfig(backend="gpu")
    with pytest.raises(ValueError, match="shorter than one control tick"):
        scenario.setup("stand", duration=0.001)
    with pytest.raises(ValueError, match="multiple of the physics timestep"):
        scenario.setup("stand", duration=1.0, sim=SimConfig(control_dt=0.0105))
    if not physics.has_cuda():
        with pytest.raises(ValueError, match="needs a CUDA GPU"):
            physics.resolve_backend("warp")
    with pytest.raises(ValueError, match="gradients need the 'jax' physics backend"):
        physics.resolve_backend("mujoco", differentiable=True)


def test_a_differentiated_loop_is_composed_with_its_trace_and_remat():
    """A loop's per-tick trace and rematerialisation are values (issue 44: no tuning settings in
    SimConfig): each composition has its own programs' key, a trace excludes SimConfig.record, and a
    policy that JAX lacks is named. No compile."""
    from wbc_jax.sim import loop as loop_lib

    plain = scenario.setup("stand", duration=0.1, sim=SimConfig(record=False)).loop
    traced = loop_lib.compose(plain, trace=loop_lib.smooth_trace)
    remat = loop_lib.compose(traced, remat="checkpoint_dots")
    recorded = loop_lib.compose(plain, recorder=loop_lib.smooth_trace)  # a recorder alone: no gains function
    assert (traced.trace, traced.remat, remat.trace, remat.remat) == (
        loop_lib.smooth_trace,
        False,
        loop_lib.smooth_trace,
        "checkpoint_dots",
    )
    assert len({loop.structure_key for loop in (plain, traced, remat, recorded)}) == 4
    recording = scenario.setup("stand", duration=0.1, sim=SimConfig(record=True)).loop
    with pytest.raises(ValueError, match="a trace and SimConfig.record are exclusive"):
        loop_lib.compose(recording, trace=loop_lib.smooth_trace)
    with pytest.raises(ValueError, match="remat 'every_other' is not a policy of jax.checkpoint_policies"):
        loop_lib.compose(plain, remat="every_other")


def _float32_com(backend: str, platforms: str, out: pathlib.Path) -> np.ndarray:
    """The benchmark scenario's CoM (T, 3) in float32 on ``backend``, in a process of its own: a
    float32 program traced in this float64 session mixes int64 index constants with int32 sizes,
    which JAX 0.11 refuses (results/nightly/gpu_before_fix.log)."""
    code = (
        "import numpy as np, sys; from tests.test_rollout import _run; "  # `python -c` puts its cwd first on sys.path
        "np.save(sys.argv[2], np.asarray(_run(sys.argv[1])[1].records.com[0], np.float64))"
    )
    env = {**os.environ, "JAX_ENABLE_X64": "0", "JAX_PLATFORMS": platforms}
    subprocess.run([sys.executable, "-c", code, backend, str(out)], cwd=ROOT, env=env, check=True, timeout=900)
    return np.load(out)


@pytest.fixture(scope="module")
def cpu_float32_com(tmp_path_factory):
    return _float32_com("jax", "cpu", tmp_path_factory.mktemp("cpu32") / "com.npy")


@pytest.mark.gpu
@pytest.mark.parametrize("backend", ["warp", "jax"])
def test_gpu_backends_follow_c_mujoco(runs, cpu_float32_com, backend, tmp_path):
    """On a CUDA GPU (skipped on the CPU): the MJX closed loop (Warp, JAX) in float32 on the GPU
    follows the same loop in float32 on the CPU within 2e-5 m of CoM over the benchmark scenario
    (the README's 4.0e-6 m between the float32 backends on an H200, results/gpu_h200/check, with room),
    and the float64 C MuJoCo loop within 2.5e-4 m: float32 itself moves the pushed robot's CoM by
    1.14e-4 m from float64 on the CPU (measured: MJX-JAX float32 against C MuJoCo float64), and by
    the same on the GPU (results/nightly/gpu.log)."""
    if backend == "warp" and not physics.has_warp():
        pytest.skip("warp-lang is not installed (pip install -e '.[gpu]')")
    com_gpu, com_c = _float32_com(backend, "cuda,cpu", tmp_path / "com.npy"), runs["mujoco"][1].records.com[0]
    assert com_gpu.shape == com_c.shape == cpu_float32_com.shape
    gpu_cpu, gpu_c64 = np.abs(com_gpu - cpu_float32_com).max(), np.abs(com_gpu - com_c).max()
    cpu_c64 = np.abs(cpu_float32_com - com_c).max()
    assert gpu_cpu < 2e-5, (gpu_cpu, gpu_c64, cpu_c64)
    assert gpu_c64 < 2.5e-4 and cpu_c64 < 2.5e-4, (gpu_cpu, gpu_c64, cpu_c64)
    assert np.linalg.norm(com_c - com_c[0], axis=1).max() > 0.01  # the push moved the robot
