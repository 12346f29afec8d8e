"""A diverged environment steps on from its last sound state (wbc_jax.sim.mjx_loop.keep_sound): a physics step reads
only ``STEP_STATE`` from the step before it, so restoring those fields alone gives the next step bit for bit what
restoring the whole ``mjx.Data`` gives, on MJX-JAX and (where warp-lang is installed, its CPU backend) MJX-Warp. The
entries a step writes are made NaN first (the ones it never writes, as ``cacc`` without sensors or the world
body's pose, keep their first value in every state): a field the step reads and ``STEP_STATE`` misses turns its output NaN.
The iCub on both engines is nightly (``slow``: compiling its MJX step costs about a minute on the 2-core CPU); the
default suite checks MJX-JAX on a small floating-base model with a joint, a motor and floor contacts."""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from wbc_jax.robot.model import load_robot
from wbc_jax.sim import mjx_loop

BATCH = 2


SMALL = """
<mujoco>
  <worldbody>
    <geom type="plane" size="2 2 0.1"/>
    <body pos="0 0 0.12">
      <freejoint/>
      <geom type="box" size="0.1 0.08 0.1"/>
      <body pos="0.1 0 0">
        <joint name="hinge" type="hinge" axis="0 1 0" damping="0.1"/>
        <geom type="capsule" fromto="0 0 0 0.2 0 -0.05" size="0.03"/>
      </body>
    </body>
  </worldbody>
  <actuator><motor joint="hinge" gear="1"/></actuator>
</mujoco>
"""


def _states(mj, qpos0, seed=0):
    """(qpos, qvel, ctrl), each (BATCH, .): ``qpos0`` with the joints (past the free joint's 7) offset, random speeds
    and controls."""
    rng = np.random.default_rng(seed)
    qpos = np.tile(qpos0, (BATCH, 1)).astype(np.float32)
    qpos[:, 7:] += rng.normal(0.0, 0.05, (BATCH, mj.nq - 7))
    qvel = rng.normal(0.0, 0.3, (BATCH, mj.nv)).astype(np.float32)
    ctrl = rng.normal(0.0, 2.0, (BATCH, mj.nu)).astype(np.float32)
    return jnp.asarray(qpos), jnp.asarray(qvel), jnp.asarray(ctrl)


def _poisoned(d, first, shared=()):
    """Every per-environment float entry of ``d`` (vmapped: leading axis BATCH) that a step wrote (it differs from
    ``first``'s, the data before any step) NaN; ``shared``: the names of a Warp Data's batch-shared buffers."""

    def one(path, x, x0):
        name = "__".join(p.name for p in path if isinstance(p, jax.tree_util.GetAttrKey) and p.name != "_impl")
        if name in shared or x.ndim == 0 or x.shape[0] != BATCH or not jnp.issubdtype(x.dtype, jnp.inexact):
            return x
        return jnp.where(x == x0, x, jnp.nan)

    return jax.jit(lambda d, first: jax.tree_util.tree_map_with_path(one, d, first))(d, first)


def _engine(model, impl):
    if model == "icub":
        robot = load_robot("icub")
        mj, qpos0 = robot.mj_model, robot.home_qpos()
    else:
        mj = mujoco.MjModel.from_xml_string(SMALL)
        qpos0 = mj.qpos0
    if impl == "warp":
        pytest.importorskip("warp", reason="MJX's Warp engine needs warp-lang (pip install 'wbc_jax[cuda]')")
        from mujoco.mjx.warp import types as warp_types

        m = mjx.put_model(mj, impl="warp")
        d = mjx.make_data(mj, impl="warp", naconmax=16 * BATCH, njmax=200)
        return mj, qpos0, m, d, warp_types.DATA_NON_VMAP
    return mj, qpos0, mjx.put_model(mj), mjx.make_data(mj), ()


@pytest.mark.parametrize(
    "model, impl",
    [
        ("small", "jax"),
        pytest.param("icub", "jax", marks=pytest.mark.slow),
        pytest.param("icub", "warp", marks=pytest.mark.slow),
    ],
)
def test_restoring_the_step_state_alone_is_restoring_everything(model, impl):
    mj, qpos0, m, d, shared = _engine(model, impl)
    qpos, qvel, ctrl = _states(mj, qpos0)

    step = jax.jit(jax.vmap(lambda dd: mjx.step(m, dd)))  # one program for every step here
    first = jax.vmap(lambda q, v, u: d.replace(qpos=q, qvel=v, ctrl=u))(qpos, qvel, ctrl)
    first = jax.device_put(first, jax.devices()[0])  # committed as the step's outputs are: one compiled step
    sound = step(first)  # derived fields computed, a warm start set
    new = step(sound)
    diverged = _poisoned(new, first, shared)
    assert np.isnan(np.asarray(diverged.qacc)).all() and np.isnan(np.asarray(diverged.qpos)).all()
    bad = jnp.zeros(BATCH, bool)

    def restored(whole):
        keep = jax.vmap(lambda n, s, o: mjx_loop.keep_sound(n, s, o, whole=whole))
        return jax.jit(keep)(diverged, bad, sound)

    want, got = step(restored(True)), step(restored(False))
    leaves = jax.tree_util.tree_leaves_with_path(want)
    for (path, a), b in zip(leaves, jax.tree_util.tree_leaves(got), strict=True):
        a, b, name = np.asarray(a), np.asarray(b), jax.tree_util.keystr(path)
        # MuJoCo Warp's constraint rows: those the step wrote
        if name.split(".")[-1].startswith("efc__") and a.ndim > 1:
            rows = np.arange(a.shape[1])[None, :] < np.asarray(want._impl.nefc)[:, None]
            if name.split(".")[-1] in mjx_loop.STALE_ROWS:  # zero beyond them, not the diverged step's NaN
                assert np.all(b[~rows] == 0), name
            a, b = a[rows], b[rows]
        np.testing.assert_array_equal(b, a, err_msg=name)
    assert np.all(np.isfinite(np.asarray(got.qpos))) and float(jnp.max(jnp.abs(got.qpos - sound.qpos))) > 1e-6
    # A sound environment keeps its new state whole.
    kept = jax.jit(jax.vmap(lambda n, o: mjx_loop.keep_sound(n, jnp.ones((), bool), o, whole=False)))(new, sound)
    for a, b in zip(jax.tree_util.tree_leaves(kept), jax.tree_util.tree_leaves(new), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
