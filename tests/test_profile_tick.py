"""benchmarks/profile_tick.py (issue 46): the profile's states are the ones the benchmark's closed loop
visits, its bad flags are refused in one line before anything compiles, and the postural projector's
certification it reports is the torque law's."""

import argparse

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import load_script, refused_in_one_line

from wbc_jax.control import torques
from wbc_jax.robot import contacts
from wbc_jax.sim import runner, scenario


@pytest.fixture(scope="module")
def profile_tick():
    return load_script("benchmarks/profile_tick.py")


@pytest.mark.parametrize(
    "argv, names",
    [
        (["--states", "random"], ("--states", "'loop'", "'synthetic'")),
        (["--ticks", "50"], ("--ticks", "0..49")),
        (["--batch", "0"], ("--batch", ">= 1")),
        (["--push-onset", "0.45"], ("--push-onset", "--horizon")),
        (["--qp-unrolled-steps", "26"], ("--qp-unrolled-steps", "0 to 25")),
        (["--qp-engine", "cuda"], ("--qp-engine", "'jax'", "'warp'")),
        (["--qp-engine", "warp", "--qp-unrolled-steps", "6"], ("--qp-engine warp", "--qp-unrolled-steps 0")),
    ],
)
def test_bad_flags_are_refused_in_one_line(profile_tick, capsys, argv, names):
    error = refused_in_one_line(profile_tick.main, [*argv, "--out", "/nonexistent/never_written"], capsys)
    assert all(name in error for name in names), error


def test_default_ticks_are_before_in_and_after_the_push(profile_tick):
    args = profile_tick.parse_args([])
    assert args.states == "loop"
    assert args.ticks == [15, 25, 40]  # push 0.2-0.3 s, 0.5 s horizon, 100 Hz


def test_projector_certification_is_the_torque_laws(robot):
    """Certified at the standing posture with the controller's tolerance (at most D directions cut,
    the Ritz start holds them); not with a tolerance that cuts more directions than the D the Ritz
    start spans (the whole eigh needed), as the full eigendecomposition says."""
    st = scenario.setup("stand", duration=0.1)
    loop, cfg = st.loop, st.loop.controller.config
    q = jnp.asarray(st.qpos0, st.dtype)

    @jax.jit
    def at_tolerance(pinv_tol):
        t = loop.terms(q, jnp.zeros(robot.index.nv, st.dtype))
        ct = contacts.contact_terms(loop.contact_set, t, 0.0, jnp.ones(2, st.dtype))
        certified = torques.projector_certified(t, ct.J, pinv_damping=cfg.pinv_damping, pinv_tol=pinv_tol)
        tt = torques.torque_terms(
            t, ct.J, ct.Jdot_nu, postural="stable", kp_postural=st.gains.kp_postural, kd_postural=st.gains.kd_postural,
            s_des=t.s, pinv_damping=cfg.pinv_damping, pinv_tol=pinv_tol,
        )  # fmt: skip
        A, threshold, _ = torques.projector_problem(tt.Lambda, tt.Mbar, cfg.pinv_damping, pinv_tol, None)
        return certified, jnp.sum(jnp.linalg.eigvalsh(A) > threshold)

    D = loop.contact_set.dim
    certified, cut = at_tolerance(cfg.pinv_tol)
    assert bool(certified) and 0 < int(cut) <= D
    certified, cut = at_tolerance(1.0)
    assert int(cut) > D and not bool(certified)


@pytest.mark.slow  # compiles the MJX closed loop twice (~75 CPU s each on the 2-core machine; tests/test_rollout.py)
def test_loop_states_are_the_ticks_the_loop_records(profile_tick):
    """The inputs profile_tick takes from benchmark.py's loop (4 pushes, 0.3 s) are those of the
    loop's own recorded run: the same postures at every tick, and the controller's tick on them gives
    the torques that run recorded, during the push too; the stages reproduce the tick's torques."""
    from loop_timing import make_setup, push_batch

    envs, onset, duration = 4, 0.1, 0.1
    st = make_setup("jax", 0.3, None)
    qpos, qvel, state = profile_tick.loop_run_inputs(st, envs, onset, duration)
    recorded = make_setup("jax", 0.3, None, record=True)
    records = runner.run(recorded, push_batch(recorded, envs, onset, duration)).records
    assert qpos.shape == records.qpos.shape == (envs, 30, st.robot.mj_model.nq)
    np.testing.assert_allclose(qpos, records.qpos, atol=1e-5)
    assert np.abs(qpos[:, -1] - qpos[:1, -1]).max() > 1e-4  # the pushes' azimuths differ, so do the states
    fns = profile_tick.stage_functions(st)
    for k in (5, 15, 25):  # before, in and after the push
        at_k = jax.tree_util.tree_map(lambda x, k=k: jnp.asarray(x[:, k]), state)
        args = (jnp.asarray(qpos[:, k]), jnp.asarray(qvel[:, k]), at_k, jnp.int32(k))
        tau = jax.jit(jax.vmap(fns["tick"], in_axes=(0, 0, 0, None)))(*args).tau
        np.testing.assert_allclose(tau, records.tau[:, k], atol=1e-3 * np.abs(records.tau[:, k]).max())
        diag = jax.jit(jax.vmap(fns["diagnostics"], in_axes=(0, 0, 0, None)))(*args)
        assert float(np.max(diag["tau_error"])) <= 1e-3 * np.abs(records.tau[:, k]).max()
    # --batch tiles the loop's environments: row i is environment i mod envs.
    ns = argparse.Namespace(
        states="loop", batch=6, loop_envs=envs, push_onset=onset, push_duration=duration, ticks=[15]
    )
    [group] = profile_tick.state_groups(st, ns)
    np.testing.assert_array_equal(np.asarray(group["qpos"]), qpos[np.arange(6) % envs, 15].astype(st.dtype))


def test_staged_programs_are_lowered_at_the_loops_matmul_precision(profile_tick):
    """profile_tick.staged, through which every stage is jitted, lowers at the loop's precision: each product is
    HIGHEST where jax.jit alone gives JAX's default (TF32 on a GPU). The torque law itself: the slow test below."""
    import types

    loop = types.SimpleNamespace(cfg=types.SimpleNamespace(matmul_precision="highest"))
    x = jnp.ones((2, 3, 3), jnp.float32)
    product = lambda a: a @ a.T  # noqa: E731
    for lowered, highest in (
        (profile_tick.staged(loop, product).lower(x), True),
        (jax.jit(jax.vmap(product)).lower(x), False),
    ):
        dots = [line for line in lowered.as_text().splitlines() if "dot_general" in line]
        assert dots and all(("HIGHEST" in line) == highest for line in dots), dots


@pytest.mark.slow  # 13 s on the 2-core machine, mostly tracing the loop's terms and init for their shapes
def test_stages_are_traced_at_the_loops_matmul_precision(profile_tick):
    """The stages run at the loop's matmul precision (``highest``), as the loop's programs: at JAX's
    default a GPU runs float32 products in TF32 (on an H100 every environment's postural projector then
    missed its certificate, another controller than the loop's). Lowered only, nothing compiles."""
    from loop_timing import make_setup

    st = make_setup("jax", 0.3, None)
    assert st.loop.cfg.matmul_precision == "highest"
    q = jax.ShapeDtypeStruct((2, *st.qpos0.shape), st.dtype)
    v = jax.ShapeDtypeStruct((2, st.robot.index.nv), st.dtype)
    t = jax.eval_shape(jax.vmap(st.loop.terms), q, v)
    state = jax.eval_shape(jax.vmap(st.loop.init), q)
    law = profile_tick.stage_functions(st)["torque_law"]
    text = profile_tick.staged(st.loop, law, (0, 0, None)).lower(t, state, jnp.int32(0)).as_text()
    dots = [line for line in text.splitlines() if "dot_general" in line]
    assert len(dots) > 10 and all("HIGHEST" in line for line in dots), dots[:3]
