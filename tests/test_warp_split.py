"""MuJoCo Warp's step in two phases (wbc_jax/sim/warp_split.py) and the controller's dynamics terms read off the first
(wbc_jax.robot.dynamics.terms_from_split), issue 46: step2(step1(d)) is mjx.step(d) bit for bit, and the terms are
those the controller computes in MJX-JAX (dynamics.terms) to float32 rounding, on tilted, moving states. Runs on
Warp's CPU backend where warp-lang is installed (the `cuda` extra)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

pytest.importorskip("warp", reason="MJX's Warp engine needs warp-lang (pip install 'wbc_jax[cuda]')")

from mujoco import mjx

from wbc_jax.core import mjx as mjx_device
from wbc_jax.robot import dynamics
from wbc_jax.robot.model import load_robot
from wbc_jax.sim import warp_split

BATCH = 4


@pytest.fixture(scope="module")
def split_run():
    robot = load_robot("icub")
    mj, idx = robot.mj_model, robot.index
    rng = np.random.default_rng(0)
    qpos = np.tile(robot.home_qpos(), (BATCH, 1)).astype(np.float32)
    qpos[:, idx.qpos_joints] += rng.normal(0.0, 0.1, (BATCH, len(idx.qpos_joints)))
    quat = np.array([0.98, 0.1, -0.1, 0.14])  # the base tilted and turned: the mixed representation's rotation matters
    qpos[:, 3:7] = quat / np.linalg.norm(quat)
    qvel = rng.normal(0.0, 0.5, (BATCH, mj.nv)).astype(np.float32)
    m = mjx.put_model(mj, impl="warp")
    d = mjx.make_data(mj, impl="warp", naconmax=16 * BATCH, njmax=200)
    step1, step2 = warp_split.phases()

    def phases(q, v):
        d1 = step1(m, d.replace(qpos=q, qvel=v))
        return d1, step2(m, d1)

    qs, vs = jnp.asarray(qpos), jnp.asarray(qvel)
    d1, d2 = jax.jit(jax.vmap(phases))(qs, vs)
    whole = jax.jit(jax.vmap(lambda q, v: mjx.step(m, d.replace(qpos=q, qvel=v))))(qs, vs)
    return robot, qs, vs, d1, d2, whole


def test_the_two_phases_are_mjx_step_bit_for_bit(split_run):
    _, _, _, d1, d2, whole = split_run
    for name in ("qpos", "qvel", "qacc", "qfrc_bias"):
        np.testing.assert_array_equal(getattr(d2, name), getattr(whole, name), err_msg=name)
    np.testing.assert_array_equal(d1.qfrc_bias, whole.qfrc_bias)  # the first phase computed it at the state
    assert float(jnp.max(jnp.abs(d2.qpos - d1.qpos))) > 1e-6  # and the second moved the robot


def test_the_terms_off_the_first_phase_are_the_controllers_own(split_run):
    """Each term within float32 rounding of its scale (measured: at most 2e-7 relative; h, of 3e2 N m, within 6e-5)."""
    robot, qs, vs, d1, _, _ = split_run
    idx, frames = robot.index, dynamics.sole_frames(robot.index)
    mx, dj = mjx_device.put_model(robot.mj_model), mjx_device.make_data(robot.mj_model)
    with jax.default_matmul_precision("highest"):  # as the loop traces both (SimConfig.matmul_precision); TF32 on a GPU
        got = jax.jit(jax.vmap(lambda dd: dynamics.terms_from_split(idx, robot.mj_model, dd, frames)))(d1)
        ref = jax.jit(jax.vmap(lambda q, v: dynamics.terms(mx, dj.replace(qpos=q, qvel=v), idx)))(qs, vs)
    for name in (
        "M",
        "h",
        "tau_passive",
        "J_frames",
        "Jdot_nu_frames",
        "A_G",
        "L_G",
        "Jdot_nu_CoM",
        "W_p_CoM",
        "W_p_frames",
        "W_R_frames",
        "W_R_B",
        "nu",
    ):
        a, b = np.asarray(getattr(got, name)), np.asarray(getattr(ref, name))
        scale = max(np.max(np.abs(b)), 1e-3)
        assert np.max(np.abs(a - b)) <= 2e-6 * scale, (name, np.max(np.abs(a - b)), scale)
    assert np.max(np.abs(np.asarray(ref.Jdot_nu_frames))) > 0.1  # the states move: the bias terms are not zeros


@pytest.mark.slow
def test_the_warp_loop_with_the_terms_off_step1_is_the_loop_with_its_own_terms(monkeypatch):
    """The stand task with a push, 0.3 s on the warp backend (Warp's CPU backend): the controller's terms read off
    step1 (PhysicsConfig.warp_terms 'step1') or computed in MJX-JAX give the same trajectory to float32 rounding
    (bounds about 10x the measured differences).
    Nightly: each loop compiles for about 80 s on the CPU."""
    from wbc_jax.sim import physics, runner, scenario
    from wbc_jax.sim.state import Push, SimConfig

    monkeypatch.setenv("WBC_JAX_WARP_ON_CPU", "1")
    out = {}
    with jax.enable_x64(False):  # the warp loop runs in float32, as on a GPU
        for terms in ("jax", "step1"):
            cfg = physics.PhysicsConfig(backend="warp", warp_graph_mode="none", warp_terms=terms)
            st = scenario.setup("stand", duration=0.3, sim=SimConfig(record=True, physics=cfg))
            push = Push(
                force=np.array([[0.0, 40.0, 0.0]]), onset=np.array([0.1]), duration=np.array([0.1]), body=np.array([-1])
            )
            out[terms] = runner.run(st, scenario.single(st, push=push)).records
    r_jax, r_split = out["jax"], out["step1"]
    com_jax, com_split = np.asarray(r_jax.com)[0], np.asarray(r_split.com)[0]  # (T, 3) of the one environment
    assert np.max(np.abs(com_jax - com_jax[0])) > 1e-3  # the push moved the CoM
    # measured: CoM 1.2e-7 m, torques 7.2e-5 N m of 5.8 (float32 rounding of the terms, carried over 30 ticks)
    np.testing.assert_allclose(com_split, com_jax, rtol=0, atol=1e-6)
    np.testing.assert_allclose(np.asarray(r_split.tau), np.asarray(r_jax.tau), rtol=0, atol=1e-3)


def test_step1_terms_on_another_backend_or_a_perturbed_plant_are_refused_in_one_line():
    from wbc_jax.sim import physics, scenario
    from wbc_jax.sim.state import SimConfig

    with pytest.raises(ValueError, match=r"warp_terms 'step1' .* needs the 'warp' backend .*valid here: \['jax'\]"):
        scenario.setup(
            "stand", duration=0.1, sim=SimConfig(physics=physics.PhysicsConfig(backend="jax", warp_terms="step1"))
        )
    with pytest.raises(ValueError, match=r"unknown warp_terms 'mjx'; valid: \['auto', 'jax', 'step1'\]"):
        physics.PhysicsConfig(warp_terms="mjx")
