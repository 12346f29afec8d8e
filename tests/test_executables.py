"""Saved programs (wbc_jax/sim/executables.py) on a machine of several devices: a program compiled
for one device loads onto that device, not onto all of them (the tune job's one-device gradient
program on a 2-GPU machine expected a shard per device when loaded: "Expected args to
execute_sharded_on_local_devices to have 2 shards"). Two host CPU devices, in subprocesses."""

import os
import pathlib
import subprocess
import sys

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parent.parent
_SOLVE_ON_DEVICE_1 = """
import sys, jax, jax.numpy as jnp, numpy as np
from wbc_jax.sim import executables
folder, mode, out = sys.argv[1:]
device = jax.devices()[1]
a = jax.device_put(np.arange(16.0, dtype=np.float32).reshape(4, 4) + 10 * np.eye(4, dtype=np.float32), device)
b = a[0]
def lower():
    if mode == "load":
        raise SystemExit("traced: the saved program was not loaded")
    return jax.jit(lambda m, v: jnp.linalg.solve(m, v)).lower(a, b)
x = executables.compiled("solve_on_1", "test", (a, b), lower, folder)(a, b)
assert x.devices() == {device}, x.devices()
np.save(out, np.asarray(x))
"""


def _run(tmp_path, mode: str) -> np.ndarray:
    env = {
        **os.environ,
        "PYTHONPATH": str(ROOT),
        "JAX_PLATFORMS": "cpu",
        "XLA_FLAGS": f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=2",
    }
    out = tmp_path / f"{mode}.npy"
    proc = subprocess.run(
        [sys.executable, "-c", _SOLVE_ON_DEVICE_1, str(tmp_path / "programs"), mode, str(out)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    return np.load(out)


def test_a_program_saved_for_the_second_of_two_devices_loads_and_runs_there(tmp_path):
    saved = _run(tmp_path, "save")
    loaded = _run(tmp_path, "load")
    np.testing.assert_array_equal(loaded, saved)
    a = np.arange(16.0, dtype=np.float32).reshape(4, 4) + 10 * np.eye(4, dtype=np.float32)
    np.testing.assert_allclose(a @ saved, a[0], rtol=1e-5)
