"""Push sweeps: input checks, the sharded path on several (host) devices, NaN isolation, resume."""

import json
import os
import pathlib
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from wbc_jax.control.gains import default_gains
from wbc_jax.core import options
from wbc_jax.jobs import sweep, sweep_config, sweep_table
from wbc_jax.robot.icub import DESCRIPTION as ICUB
from wbc_jax.sim import runner, scenario


def test_controller_settings_of_a_sweep_and_a_held_out_evaluation_reach_the_loop():
    """--angular-weight-soft and --tasks travel into the closed loop's force QP and contact set (the
    held-out evaluation's and the tuning run's configs too), not only into the run's records."""
    from wbc_jax.tuning.orchestration import heldout as tuning_eval

    tasks = str(pathlib.Path(__file__).resolve().parent.parent / "experiments" / "tasks" / "feet_sole95.yaml")
    cfg = options.replace(sweep_config.SweepConfig(), angular_weight_soft=0.01, tasks=tasks, forces="qp")
    st = sweep.make_setup(cfg, default_gains(ICUB, scenario.float_dtype()))
    assert st.loop.controller.config.force_settings.angular_weight_soft == 0.01
    rects = [c.params.foot_size for c in st.loop.contact_set.contacts]
    assert rects[0] == ((-0.0635, 0.1255), (-0.0425, 0.0505)) and rects[1][1] == (-0.0505, 0.0425)
    hc = options.replace(tuning_eval.HeldoutConfig(), angular_weight_soft=0.1, tasks=tasks)
    assert tuning_eval._controller((1.0, 0.1), hc).angular_weight_soft == 0.1
    assert sweep.make_setup(sweep_config.SweepConfig()).loop.controller.config.angular_weight_soft == 1.0
    with pytest.raises(FileNotFoundError, match="--tasks file /nowhere.yaml does not exist"):
        options.replace(tuning_eval.HeldoutConfig(), tasks="/nowhere.yaml")


def test_bad_sweep_input_is_rejected_before_compiling(robot, tmp_path):
    with pytest.raises(ValueError, match="--magnitudes: give at least one value"):
        sweep_config.SweepConfig(magnitudes=()).check()
    with pytest.raises(ValueError, match=r"--magnitudes must be a number in \[0, 5000\] N, got -5"):
        sweep_config.SweepConfig(magnitudes=(-5.0,)).check()
    with pytest.raises(ValueError, match=r"--push-duration must be a number in \[0.001, 60\] s"):
        sweep_config.SweepConfig(push_duration=-0.1).check()
    with pytest.raises(ValueError, match=r"--body 'nose' is not a valid name here; valid: \['root_link'.*'chest'"):
        sweep.run_sweep(sweep_config.SweepConfig(body="nose", out=str(tmp_path / "s")), progress=False)
    with pytest.raises(ValueError, match=r"cannot push body 'world'"):  # the API below the configs refuses it too
        robot.index.pushable_body_id("world")
    with pytest.raises(ValueError, match=r"--queue must be a whole number in \[1, 1024\], got 0"):
        sweep_config.SweepConfig(queue=0).check()
    with pytest.raises(ValueError, match="needs an MJX backend: --backend jax or warp"):
        sweep.run_sweep(sweep_config.SweepConfig(queue=2, backend="mujoco", out=str(tmp_path / "s")), progress=False)
    with pytest.raises(ValueError, match="cannot record"):
        runner.check_queue(2, "jax", record=True)
    assert not (tmp_path / "s").exists()  # nothing written


def test_scenario_grid(robot):
    cfg = sweep_config.SweepConfig(magnitudes=(10.0, 20.0), directions=(0.0, 90.0), gain_sets=3, seed=4)
    scen, cols = sweep.build_scenarios(cfg, default_gains(ICUB), 23)
    assert scen.push.force.shape == (12, 1, 3) and scen.gains.kp_postural.shape == (12, 23)
    np.testing.assert_allclose(np.linalg.norm(scen.push.force[:, 0], axis=1), cols["magnitude_n"], rtol=1e-6)
    left = (cols["azimuth_deg"] == 90.0) & (cols["magnitude_n"] == 20.0)
    np.testing.assert_allclose(scen.push.force[left, 0], [[0, 20, 0]] * 3, atol=1e-5)
    # gain set 0 is the default; the others are seeded rescalings of it.
    assert np.allclose(scen.gains.kp_com[cols["gain_set"] == 0], [50, 50, 10])
    again, _ = sweep.build_scenarios(cfg, default_gains(ICUB), 23)
    np.testing.assert_array_equal(again.gains.kp_com, scen.gains.kp_com)


def test_lip_bound_is_omega_times_edge_distance(robot):
    b = sweep_table.lip_bound(robot, [0.0, 90.0])
    omega = np.sqrt(9.81 / 0.5496)
    # Forward: the toe spheres are ~0.13 m ahead of the sole origin, CoM ~0.014 m ahead of it.
    assert b[0.0]["edge_distance_m"] == pytest.approx(0.117, abs=0.005)
    assert b[90.0]["velocity_bound_mps"] == pytest.approx(omega * b[90.0]["edge_distance_m"], rel=1e-3)
    # A push at 60 deg elevation has half its impulse horizontal: twice the bound; a vertical one none.
    up = sweep_table.lip_bound(robot, [0.0, 90.0], elevation_deg=60.0)
    assert up[0.0]["impulse_bound_ns"] == pytest.approx(2 * b[0.0]["impulse_bound_ns"], rel=1e-9)
    assert sweep_table.lip_bound(robot, [0.0], elevation_deg=-90.0)[0.0]["impulse_bound_ns"] is None
    assert sweep_table.fraction(3.0, None) is None and sweep_table.fraction(3.0, 6.0) == 0.5


SHARDED = textwrap.dedent(
    """
    import json, pathlib, sys
    import jax, numpy as np
    from wbc_jax.control.gains import default_gains
    from wbc_jax.jobs import sweep, sweep_config
    from wbc_jax.robot.icub import DESCRIPTION as ICUB
    from wbc_jax.sim import metrics, runner, scenario
    backend = sys.argv[3]
    if backend == "jax":
        assert len(jax.devices()) == 2, jax.devices()
    out = pathlib.Path(sys.argv[1])
    # MJX, 8 per chunk (4: the sweep's size): sharded over the two host devices this deadlocked XLA:CPU (jax
    # 0.9.2); on the CPU the batch now runs on one device per process (runner.batch_devices).
    cfg = sweep_config.SweepConfig(magnitudes=(20.0, 400.0), directions=(90.0, 270.0), horizon=0.8, push_onset=0.1,
                            push_duration=0.1, chunk_size=8 if backend == "jax" else 2, backend=backend,
                            out=str(out))
    s = sweep.run_sweep(cfg, progress=False)
    if sys.argv[2] != "nan":
        print(json.dumps({"summary": {k: s[k] for k in ("n_envs", "n_devices")}}))
        raise SystemExit(0)
    # NaN isolation: the same setup and batch shape, one environment starts from NaN joints.
    st = sweep.make_setup(cfg, default_gains(ICUB, scenario.float_dtype()))
    scen, _ = sweep.build_scenarios(cfg, default_gains(ICUB), 23, scenario.float_dtype())
    scen = jax.tree_util.tree_map(lambda x: np.asarray(x)[:2], scen)
    scen = scen.replace(joint_offset=scen.joint_offset.copy())
    scen.joint_offset[1] = np.nan
    run = runner.run(st, scen, batch_size=cfg.batch_size)  # the sweep's compiled program
    again = runner.run(st, scen, batch_size=cfg.batch_size)
    m = run.metrics
    res = {"summary": {k: s[k] for k in ("n_envs", "upright_rate", "nan_envs", "n_devices", "backend")},
           "nan": np.asarray(m.nan).tolist(), "fell": np.asarray(m.fell).tolist(),
           "com_max": np.asarray(m.com_max_err).tolist(), "recompiled": again.compile_s > 0}
    if backend == "jax":
        # Two scenarios per batch slot: 1,600 N (falls), 20 N (survives), NaN joints (diverges), 10 N
        # (survives; it starts in the slot the fallen and the diverged robot left).
        four, _ = sweep.build_scenarios(cfg, default_gains(ICUB), 23, scenario.float_dtype())
        four = jax.tree_util.tree_map(lambda x: np.asarray(x)[[2, 0, 0, 0]].copy(), four)
        four.push.force[0] *= 4  # 1,600 N for 0.1 s: down well before the end
        four.joint_offset[2] = np.nan
        four.push.force[3] *= 0.5
        plain = runner.run(st, four, batch_size=cfg.batch_size).metrics
        queued = runner.run(st, four, batch_size=cfg.batch_size, queue=2).metrics
        cols = [metrics.summarize(x) for x in (plain, queued)]
        res["queue"] = {
            "outcomes": [[c[k].tolist() for k in ("survived", "upright", "fell", "nan")] for c in cols],
            "ticks": [np.asarray(x.ticks).tolist() for x in (plain, queued)],
            "survivors": [[float(c[k][i]) for i in (1, 3) for k in ("com_rmse_m", "max_abs_torque_nm")] for c in cols],
        }
    print(json.dumps(res))
    """
)


# The MJX variant compiles the sweep's chunk program on MJX (minutes on the 2-core CPU): nightly (`slow`).
@pytest.mark.parametrize("backend", [pytest.param("jax", marks=pytest.mark.slow), "mujoco"])
def test_sweep_isolates_nan_and_resumes(tmp_path, backend):
    """MJX with two host devices present, and C MuJoCo: the run finishes (a chunk of 8 sharded over
    two CPU devices used to hang), one env from NaN joints is flagged, the other is not; a finished
    sweep resumes from its parts; a changed input is refused."""
    # Added to the inherited XLA_FLAGS: replacing them dropped conftest's compile-time flags (a slower compile).
    flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=2"
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "XLA_FLAGS": flags}
    out = tmp_path / "sweep"
    run = lambda mode: subprocess.run(  # noqa: E731
        [sys.executable, "-c", SHARDED, str(out), mode, backend],
        capture_output=True,
        text=True,
        timeout=600,
        env=env,  # a hang fails here (a normal run takes 1-3 minutes)
    )
    proc = run("nan")
    assert proc.returncode == 0, proc.stderr[-3000:]
    res = json.loads(proc.stdout.strip().splitlines()[-1])
    assert res["summary"]["n_devices"] == 1 and res["summary"]["n_envs"] == 4  # one CPU device per process
    assert res["summary"]["backend"] == backend
    # 20 N survives; 400 N for 0.1 s (40 N s, over twice the LIP bound) does not.
    table = __import__("pandas").read_parquet(out / "results.parquet")
    assert table.sort_values("magnitude_n")["upright"].tolist() == [True, True, False, False]
    assert res["nan"] == [False, True], "the NaN environment is flagged, the other is not"
    assert not res["fell"][0] and res["com_max"][0] < 0.05 and not res["recompiled"]
    if backend == "jax":  # a queue of 2 scenarios per slot: the fallen and the diverged robot retire early
        q = res["queue"]
        assert (
            q["outcomes"][0]
            == q["outcomes"][1]
            == [
                [False, True, False, True],
                [False, True, False, True],
                [True, False, False, False],
                [False, False, True, False],
            ]
        )
        assert q["ticks"][0] == [80] * 4  # 0.8 s at 100 Hz
        fall_ticks, survivor, nan_ticks, refilled = q["ticks"][1]
        assert fall_ticks < 80 and fall_ticks % 20 == 0 and nan_ticks == 20  # decided at a check (every 20 ticks)
        assert survivor == refilled == 80  # the refilled slot runs its new scenario's whole horizon
        # float32 in this subprocess: the two programs round differently (measured 2.5e-6 relative).
        np.testing.assert_allclose(q["survivors"][1], q["survivors"][0], rtol=1e-4)
    assert (out / "survival.png").exists() and (out / "envelope.png").exists()
    # Resume: a complete sweep is read back from its parts without recomputing.
    before = (out / "parts" / "part-00000.parquet").stat().st_mtime
    proc = run("resume")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (out / "parts" / "part-00000.parquet").stat().st_mtime == before


def test_host_loop_is_refused_on_an_mjx_backend_in_one_line(tmp_path, capsys):
    """--host-loop sets how the C MuJoCo engine runs: with an MJX backend it would change nothing, so it is refused
    before anything compiles; an unknown value names the valid ones."""
    from wbc_jax import cli

    out = tmp_path / "sw"
    assert cli.main(["push-sweep", "--backend", "jax", "--host-loop", "python", "--out", str(out)]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert err == [
        "wbc-jax push-sweep: error: --host-loop python sets how the C MuJoCo engine runs the ticks: it needs "
        "--backend mujoco (--backend jax runs jax here)"
    ]
    proc = subprocess.run(
        [sys.executable, "-m", "wbc_jax.cli", "push-sweep", "--host-loop", "fast", "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    lines = [line for line in proc.stderr.splitlines() if "error:" in line]
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr[-2000:]
    assert "argument --host-loop: invalid choice: 'fast' (choose from 'auto', 'compiled', 'python')" in lines[0]
    assert not out.exists()
