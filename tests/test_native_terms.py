"""The compiled loop's physics call split at ``mj_step1`` with the controller's dynamics terms from
C MuJoCo (``native.step_terms``): equal to ``mj_step`` (HostBatch) bit for bit, contact slots and
divergences included, its terms those of the state it returns. The terms against MJX's
``dynamics.terms``: tests/test_dynamics.py (its compiled terms shared)."""

import jax
import mujoco
import numpy as np
import pytest
from conftest import stepping_inputs

from wbc_jax.robot import dynamics
from wbc_jax.sim import native, physics

pytestmark = pytest.mark.skipif(native.available() is not None, reason=f"native step: {native.available()}")


@pytest.fixture(scope="module")
def frames(robot):
    """The soles and a point off a forearm's origin (a motion task's frame)."""
    elbow = robot.index.body_id("l_elbow_1")
    return dynamics.sole_frames(robot.index) + dynamics.Frames((elbow,), ((0.03, -0.02, 0.11),))


def step_terms(robot, frames, ids, ctrl, xfrc, ok, slots, start=False):
    m, idx = robot.mj_model, robot.index
    sizes = dict(nq=m.nq, nv=m.nv, nbody=m.nbody, base_body=idx.base_body, frames=frames)
    return native.step_terms(ids, ctrl, xfrc, ok, slots, start=start, **sizes)


def no_slots(B: int, C: int = 0):
    return np.zeros((B, C, 3)), np.zeros((B, C, 3)), np.zeros((B, C, 2), np.int32)


def start_terms(robot, frames, ids, B: int, C: int = 0):
    """The loop's first call (nothing stepped: mj_step1 at the data's state)."""
    m = robot.mj_model
    zeros = np.zeros((B, m.nu)), np.zeros((B, 0, m.nbody, 6)), np.ones(B, bool), no_slots(B, C)
    return step_terms(robot, frames, ids, *zeros, start=True)


def test_split_step_equals_mj_step_bit_for_bit(robot, frames):
    """Torques and pushes of 30 ticks through HostBatch.step (mj_step) and through step_terms
    (mj_step2, then mj_step1 + mj_step2 per step, mj_step1 at the end), each on its own C data: the
    same states, divergence flags and contact slots bit for bit (an environment blown up and
    restored, one frozen before stepping by a NaN torque: its slots passed on); the terms are those
    of the state returned (the mass matrix and bias of mj_forward there, bit for bit)."""
    B, n_sub, ticks_run = 3, 10, 30
    m = physics.solver_mj_model(robot.mj_model, physics.PhysicsConfig())
    rng = np.random.default_rng(0)
    qpos = robot.home_qpos()[None].repeat(B, 0)
    qpos[:, robot.index.qpos_joints] += rng.normal(scale=0.05, size=(B, robot.index.n))
    python = physics.HostBatch(m, qpos, threads=1)
    split = physics.HostBatch(m, qpos, threads=1)  # its data stepped by step_terms only
    ids = native.handles(split.models, split.data)
    n_con = physics.max_contacts(m)
    step = jax.jit(lambda ctrl, xfrc, ok, slots: step_terms(robot, frames, ids, ctrl, xfrc, ok, slots))
    native.physics_cpu(reset=True)
    slots = start_terms(robot, frames, ids, B, n_con)[3]
    ok = np.ones(B, bool)
    chest = robot.index.body_id("chest")
    fresh = mujoco.MjData(m)
    M, M_ref = np.zeros((m.nv, m.nv)), np.zeros((m.nv, m.nv))
    for k in range(ticks_run):
        ctrl, xfrc = stepping_inputs(rng, k, m, B, n_sub, chest)
        python.step(ctrl, xfrc)
        q, v, ok, slots, engine = jax.device_get(step(ctrl, xfrc, ok, slots))
        q_py, v_py = python.state()
        np.testing.assert_array_equal(q, q_py)
        np.testing.assert_array_equal(v, v_py)
        np.testing.assert_array_equal(~ok, python.diverged)
        for a, b in zip(slots, python.contacts(n_con), strict=True):
            np.testing.assert_array_equal(a, b)
        for b in range(B):
            fresh.qpos[:], fresh.qvel[:] = q_py[b], v_py[b]
            mujoco.mj_forward(m, fresh)
            mujoco.mj_fullM(m, fresh, M_ref)
            np.testing.assert_array_equal(engine.M[b], M_ref)
            np.testing.assert_array_equal(engine.bias[b], fresh.qfrc_bias)
    # The accounting: every stepping call a tick of physics (the start is none), mj_step1 and
    # mj_step2 in the physics' CPU time, the terms' extraction apart (the controller's).
    physics_s, ticks = native.physics_cpu()
    assert ticks == ticks_run and 0 < native.terms_cpu() < physics_s
    assert ok.tolist() == [True, False, False]
    assert float(np.abs(q[0] - qpos[0]).max()) > 1e-3 and sum(int(d.ncon) for d in split.data) > 0
    del M


def test_step_terms_checks_its_arrays(robot, frames):
    m = robot.mj_model
    host = physics.HostBatch(m, robot.home_qpos()[None], threads=1)
    ids = native.handles(host.models, host.data)
    args = (np.zeros((1, m.nu + 1)), np.zeros((1, 1, m.nbody, 6)), np.ones(1, bool), no_slots(1))
    with pytest.raises(Exception, match="do not match the model's sizes"):
        step_terms(robot, frames, ids, *args)
    far = dynamics.Frames((m.nbody,), ((0.0, 0.0, 0.0),))
    with pytest.raises(Exception, match="frame body out of range"):
        step_terms(robot, far, ids, np.zeros((1, m.nu)), *args[1:])
