"""Short-horizon gradients: windows of the closed loop started from states along forward rollouts.

Through a whole 2 s rollout, reverse mode multiplies 2,000 contact-step Jacobians: where the feet
tilt, slip or touch down the product is stiff and its gradient explodes or points the wrong way.
Short-horizon actor-critic (Xu et al., ICLR 2022, SHAC) differentiates short windows instead,
started from states visited by forward rollouts, and closes each window with a value of its last
state. Here (``--window-s``):

1. R forward rollouts of the training pushes run at the current gains on the fastest engine
   (``--search-backend``: Warp on a GPU), recording the state at every tick (:func:`recording_loop`);
2. each rollout gives K windows (``--windows``) starting at random ticks (uniform over the ticks
   from which a whole window fits): its physics state (qpos, qvel), the loop's state (controller
   memory, metrics, contact anchors) and the rollout's first-tick foot normals and sole corners, which
   tilt and slip are measured from;
3. each window runs W ticks on MJX-JAX and is differentiated (per window, as the whole-horizon
   step): its loss is the per-tick mean of the tuning loss's terms (the settling term, which asks
   for rest at the end of a rollout, left out) plus ``terminal_weight`` x a capturability cost at
   its last tick (:func:`wbc_jax.tuning.algorithms.loss.terminal_cost`: capture point in the support polygon,
   CoM at height), the analytic stand-in for SHAC's learned critic.

The solver of a window starts cold (MJX's warm start is not carried over), which moves the first
physics step of a window by the solver's tolerance. Shapes: R rollouts, K windows each, B = R K
windows (2 R K with antithetic pairs), W ticks per window, T ticks per rollout.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax.core.types import Array, pytree_dataclass
from wbc_jax.sim import loop as loop_lib
from wbc_jax.sim import metrics as metrics_lib
from wbc_jax.sim import mjx_loop, physics
from wbc_jax.sim.state import LoopState, Scenario
from wbc_jax.tuning.algorithms import loss as tuning_loss
from wbc_jax.tuning.algorithms import objectives
from wbc_jax.tuning.algorithms import problem as tp


@pytree_dataclass
class WindowStart:
    """Where each window starts (a leading axis of windows).

    Attributes:
      scen: the rollout's :class:`Scenario` (push, plant).
      qpos (nq,), qvel (nv,): the physics state at the window's first tick.
      state: the loop's :class:`LoopState` there.
      tick: () int32, the window's first tick.
      normal0 (2, 3), support0 (F, 2): the rollout's foot normals and sole corners at its first tick.
    """

    scen: Scenario
    qpos: Array
    qvel: Array
    state: LoopState
    tick: Array
    normal0: Array
    support0: Array


def record_start(record, new_state: LoopState, state: LoopState, qpos: Array, qvel: Array):
    """The recorder of :func:`recording_loop` (:data:`wbc_jax.sim.loop.Recorder`): the tick's record
    with the physics and loop state it started from."""
    return record, (qpos, qvel, state)


def recording_loop(loop: loop_lib.ClosedLoop) -> loop_lib.ClosedLoop:
    """A copy of a tuning loop whose per-tick record is (TuneTrace, (qpos, qvel, LoopState))."""
    return loop_lib.compose(loop, recorder=record_start)


def window_ticks(problem: tp.Problem) -> int:
    """W, the ticks of one window."""
    return max(1, int(round(problem.tc.window_s / problem.loop.cfg.control_dt)))


def sample_starts(rng: np.random.Generator, rollouts: int, windows: int, n_ticks: int, w: int) -> np.ndarray:
    """(R, K) first ticks of the windows: uniform over the ticks from which a whole window fits."""
    return rng.integers(0, n_ticks - w + 1, size=(rollouts, windows)).astype(np.int32)


def make_sampler(fwd: tp.Problem, rollouts: int, windows: int, mesh=None):
    """Forward rollouts that record the window starts, unjitted: ``fn(params, scen (R,), ticks (R, K)) ->
    (WindowStart (R K,), loss terms {name: (R,)}, Metrics (R,))`` on ``fwd``'s engine, data-parallel over
    the rollouts (R a multiple of the device count)."""
    loop = recording_loop(fwd.loop)
    st = fwd.setup
    qpos0 = jnp.asarray(st.qpos0, st.dtype)
    nominal = physics.device_model(st.robot.mj_model, loop.backend, loop.cfg.physics)
    per_device = rollouts // int(objectives.mesh_of(mesh).devices.size)

    def one(controls, reg, scen, ticks):
        plant = physics.plant_model(nominal, scen.friction, scen.mass_scale)
        qpos = loop.initial_qpos(qpos0, scen.joint_offset)
        metrics, (trace, (q, v, state)) = mjx_loop.rollout(
            loop, plant, qpos, controls, scen.push, controller_overrides=reg, batch=per_device
        )
        pick = lambda x: x[ticks]  # noqa: E731
        K = ticks.shape[0]
        start = WindowStart(
            scen=jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (K, *jnp.shape(x))), scen),
            qpos=pick(q),
            qvel=pick(v),
            state=jax.tree_util.tree_map(pick, state),
            tick=ticks,
            normal0=jnp.broadcast_to(trace.foot_normal[0], (K, *trace.foot_normal.shape[1:])),
            support0=jnp.broadcast_to(trace.base.support_xy[0], (K, *trace.base.support_xy.shape[1:])),
        )
        return start, tuning_loss.loss_terms(trace, fwd.lc, None, loop.cfg.control_dt), metrics

    def batch(scen, ticks, controls, reg):
        return jax.vmap(one, in_axes=(None, None, 0, 0))(controls, reg, scen, ticks)

    run = objectives.data_parallel(batch, mesh, replicated=2)

    def fn(params, scen, ticks):
        start, terms, metrics = run(scen, ticks, *tp.controls_cast(fwd, params))
        start = jax.tree_util.tree_map(lambda x: x.reshape((-1, *x.shape[2:])), start)
        return start, terms, metrics

    return fn


def make_window_grads(problem: tp.Problem, mesh=None):
    """Per-window value and gradient, unjitted: ``fn(params_b {group: (B, ...)}, starts WindowStart (B,))
    -> (values (B,), grads {group: (B, ...)}, terms {name: (B,)}, Metrics (B,))``, on MJX-JAX, data-parallel."""
    loop, st, lc, tc = problem.loop, problem.setup, problem.lc, problem.tc
    nominal = physics.device_model(st.robot.mj_model, "jax", loop.cfg.physics)
    W = window_ticks(problem)

    def objective(params, w: WindowStart):
        controls, reg = tp.controls_cast(problem, params)
        plant = physics.plant_model(nominal, w.scen.friction, w.scen.mass_scale)
        d = physics.device_data(st.robot.mj_model, "jax", loop.cfg.physics, w.qpos, st.dtype)
        state = w.state
        if reg:
            state = state.replace(controller=state.controller.replace(**reg))
        seed = w.scen.friction + sum(jnp.sum(x) for x in jax.tree_util.tree_leaves((controls, reg)))
        carry = mjx_loop.touch((d.replace(qvel=w.qvel.astype(d.qpos.dtype)), state, jnp.ones((), bool)), seed)
        (d, state, ok), trace = mjx_loop.chunk(loop, plant, controls, w.scen.push, carry, w.tick, W)
        terms = tuning_loss.loss_terms(trace, lc, None, loop.cfg.control_dt, reference=(w.normal0, w.support0))
        terms["terminal"] = tuning_loss.terminal_cost(trace, lc)
        total = terms["total"] - lc.w_settle * terms["settle"] + tc.terminal_weight * terms["terminal"]
        terms["total"] = total
        return tuning_loss.env_objective(total, lc), (terms, metrics_lib.final(state.metrics, ok))

    def fn(params_b, starts):
        with physics.gradient_solver(tc.solver_gradient, problem.iterations):
            per_env = jax.vmap(jax.value_and_grad(objective, has_aux=True))
            (values, (terms, metrics)), grads = per_env(params_b, starts)
        return values, grads, terms, metrics

    return objectives.data_parallel(fn, mesh)
