"""C MuJoCo inside XLA (the compiled loop of one robot) and compiled programs kept on disk.

The native step against HostBatch (the Python loop's physics) bit for bit, a divergence restored
and flagged alike; the contact slots alike; a program loaded from disk in a new process gives the
outputs of the program compiled here; the driver's settings are checked before compiling. The
compiled closed loop itself is checked against the MJX closed loop and the Python loop in
tests/test_rollout.py (one compiled program shared)."""

import pathlib
import subprocess
import sys

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from conftest import stepping_inputs

from wbc_jax.sim import executables, host_loop, native, physics, scenario
from wbc_jax.sim.state import SimConfig

pytestmark = pytest.mark.skipif(native.available() is not None, reason=f"native step: {native.available()}")


def _batch(robot, B: int):
    """B environments at the home posture (joints offset per environment) in C MuJoCo."""
    m = physics.solver_mj_model(robot.mj_model, physics.PhysicsConfig())
    rng = np.random.default_rng(0)
    qpos = robot.home_qpos()[None].repeat(B, 0)
    qpos[:, robot.index.qpos_joints] += rng.normal(scale=0.05, size=(B, robot.index.n))
    return m, qpos


def test_native_step_equals_host_batch_bit_for_bit(robot):
    """Torques and pushes of 30 ticks through HostBatch.step and through the FFI step, each on
    its own C data: the same states and contact slots bit for bit; an environment driven to
    blow up is restored to its last sound state and flagged by both, then frozen."""
    B, n_sub, ticks = 3, 10, 30
    m, qpos = _batch(robot, B)
    python = physics.HostBatch(m, qpos, threads=1)
    compiled = physics.HostBatch(m, qpos, threads=1)  # its data stepped by the native step only
    ids = native.handles(compiled.models, compiled.data)
    n_con = physics.max_contacts(m)

    @jax.jit
    def tick(ctrl, xfrc, ok):
        q, v, ok = native.step(ids, ctrl, xfrc, ok, m.nq, m.nv)
        return q, v, ok, native.contacts(ids, q, n_con, q.dtype)

    rng = np.random.default_rng(1)
    ok = np.ones(B, bool)
    chest = robot.index.body_id("chest")
    for k in range(ticks):
        ctrl, xfrc = stepping_inputs(rng, k, m, B, n_sub, chest)
        python.step(ctrl, xfrc)
        q, v, ok, slots = jax.device_get(tick(ctrl, xfrc, ok))
        q_py, v_py = python.state()
        # The same C function (mj_step) on the same inputs through two callers: bit-equal (measured so with XLA held to AVX2).
        np.testing.assert_array_equal(q, q_py)
        np.testing.assert_array_equal(v, v_py)
        np.testing.assert_array_equal(~ok, python.diverged)
        for a, b in zip(slots, python.contacts(n_con), strict=True):
            np.testing.assert_array_equal(a, b)
    assert ok.tolist() == [True, False, False]
    assert np.isfinite(q[2]).all() and float(np.abs(q[0] - qpos[0]).max()) > 1e-3  # restored; env 0 moved
    assert sum(int(d.ncon) for d in compiled.data) > 0  # the slots held contacts


def test_native_step_checks_its_arrays(robot):
    m, qpos = _batch(robot, 1)
    host = physics.HostBatch(m, qpos, threads=1)
    ids = native.handles(host.models, host.data)
    with pytest.raises(Exception, match="do not match the model's sizes"):
        native.step(ids, jnp.zeros((1, m.nu + 1)), jnp.zeros((1, 10, m.nbody, 6)), jnp.ones(1, bool), m.nq, m.nv)


def test_host_loop_settings_are_checked_before_compiling(monkeypatch):
    with pytest.raises(ValueError, match="unknown host_loop 'fast'"):
        SimConfig(host_loop="fast")
    st = scenario.setup(
        "stand", duration=0.05, sim=SimConfig(host_loop="compiled", physics=physics.PhysicsConfig(backend="mujoco"))
    )
    assert host_loop.driver(st.loop) == "compiled"
    auto = scenario.setup("stand", duration=0.05, sim=SimConfig(physics=physics.PhysicsConfig(backend="mujoco")))
    assert host_loop.driver(auto.loop) == "compiled"  # any batch (tests/test_rollout.py runs one of two)
    monkeypatch.setattr(native, "available", lambda: "no C++ compiler found")
    with pytest.raises(ValueError, match="host_loop='compiled' cannot run here: no C\\+\\+ compiler found"):
        host_loop.driver(st.loop)
    assert host_loop.driver(auto.loop) == "python"  # auto falls back to the Python loop


_LOAD = """
import sys, jax, numpy as np
jax.config.update("jax_enable_x64", True)
from wbc_jax.sim import executables
a = np.arange(16.0).reshape(4, 4) + 10 * np.eye(4)
def lower():
    raise SystemExit("traced: the saved program was not loaded")
out = executables.compiled("solve", "test", (a, a[0]), lower, sys.argv[1])(a, a[0])
np.save(sys.argv[2], np.asarray(out))
"""


def test_a_saved_program_loads_in_a_new_process_with_the_same_outputs(tmp_path):
    """A linear solve (LAPACK's LU: the kernels a loaded program must not find unset) compiled
    and saved here, then loaded by a fresh process without tracing: the same output bit for bit.
    A second ``compiled`` call here loads it too; a damaged file is compiled again."""
    a = np.arange(16.0).reshape(4, 4) + 10 * np.eye(4)
    calls = []

    def lower():
        calls.append(1)
        return jax.jit(lambda m, b: jnp.linalg.solve(m, b)).lower(a, a[0])

    here = np.asarray(executables.compiled("solve", "test", (a, a[0]), lower, tmp_path)(a, a[0]))
    assert len(calls) == 1 and len(list(tmp_path.iterdir())) == 1
    np.testing.assert_allclose(a @ here, a[0], atol=1e-12)
    executables.compiled("solve", "test", (a, a[0]), lower, tmp_path)
    assert len(calls) == 1  # loaded, not compiled
    root = pathlib.Path(__file__).resolve().parent.parent
    proc = subprocess.run(
        [sys.executable, "-c", _LOAD, str(tmp_path), str(tmp_path / "out.npy")],
        cwd=root,
        capture_output=True,
        text=True,
        timeout=300,
        env={**__import__("os").environ, "PYTHONPATH": str(root), "JAX_PLATFORMS": "cpu"},
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    np.testing.assert_array_equal(np.load(tmp_path / "out.npy"), here)
    (saved,) = (p for p in tmp_path.iterdir() if p.name.startswith("solve"))
    saved.write_bytes(b"damaged")
    with pytest.warns(UserWarning, match="did not load"):
        again = executables.compiled("solve", "test", (a, a[0]), lower, tmp_path)
    assert len(calls) == 2
    np.testing.assert_array_equal(np.asarray(again(a, a[0])), here)


def test_program_keys_follow_shapes_and_settings():
    a = np.zeros((2, 3))
    key = executables.program_key("p", "k", (a,))
    assert key == executables.program_key("p", "k", (np.ones((2, 3)),))  # values do not matter
    assert key != executables.program_key("p", "k", (np.zeros((3, 3)),))
    assert key != executables.program_key("p", "k", (a.astype(np.float32),))
    assert key != executables.program_key("p", "other structure", (a,))
    assert mujoco.__version__ and executables.source_digest()  # versions and sources are in it
