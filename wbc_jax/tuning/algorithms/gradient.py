"""Gradient-based gain tuning through the differentiable closed loop (issues 5, 20, 35).

The pipeline (brax-APG shape)::

    params --(bounded, stable map: params / schedule)--> gains (+ regularisation)
           --vmap(closed loop with a TuneTrace over B rollouts: objectives)--> per-rollout values, grads
           --(estimator: robust mean, smoothed, alpha-order mix: estimators)--> gradient
           <--(adam, clipped, NaN-guarded)--

Differentiation: reverse mode through the closed loop's ``lax.scan``: MJX physics with the model's
contact solver (Newton, 4 iterations), differentiated implicitly at its solution
(:func:`wbc_jax.sim.physics.implicit_solver`; ``--solver-gradient unrolled``: through every iteration,
run as a fixed-length scan, :func:`~wbc_jax.sim.physics.fixed_iteration_solver`; the same gradient, the
implicit one 3.8x cheaper), 4 corner spheres per foot (foot boxes gave NaN gradients), the contact QP
through its implicit derivative, and ``jax.checkpoint`` on each 10 ms tick (``--checkpoint``). Each rollout has its own parameters and gradient (vmap of value_and_grad), so a
rollout that diverges is dropped from the step instead of poisoning it. The rollouts are whole
horizons from the sampled pushes, or (``--window-s``) short windows started from states along
forward rollouts (:mod:`wbc_jax.tuning.algorithms.windows`).

Each step draws a fresh batch (:func:`wbc_jax.tuning.algorithms.problem.sample_pushes`, reproducible by step);
the run is resumable (checkpoint.npz with every step's parameters, history.csv), and its history
counts simulated physics steps (the forward rollouts of the windows included) and wall time
(compilation included), against which the gradient-free searches get the same budgets. With
``--budget-s`` the run stops when its wall time is spent. The race's hybrid
(:mod:`wbc_jax.tuning.algorithms.hybrid`) runs this same loop from CMA-ES's set, with a wall budget of its own.
"""

from __future__ import annotations

import hashlib
import json
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.flatten_util import ravel_pytree

from wbc_jax.core import io, provenance
from wbc_jax.sim import runner
from wbc_jax.sim.per_device import PerDevice
from wbc_jax.tuning import store
from wbc_jax.tuning.algorithms import estimators, objectives
from wbc_jax.tuning.algorithms import problem as tp
from wbc_jax.tuning.algorithms import windows as tw
from wbc_jax.tuning.algorithms.estimators import ESTIMATOR_STATS, robust_mean_gradient  # noqa: F401
from wbc_jax.tuning.algorithms.loss import TERMS
from wbc_jax.tuning.algorithms.problem import Problem
from wbc_jax.tuning.config import TuneConfig, default_config  # noqa: F401  (the job's config)

HISTORY_COLUMNS = (
    "step",
    "loss",
    "rollout_loss",
    *TERMS,
    "survival_rate",
    "upright_rate",
    "qp_infeasible_rate",
    "grad_norm",
    "finite",
    "skipped_total",
    "step_s",
    "sim_steps",
    "grad_sim_steps",
    "wall_s",
    "rss_mb",
    *ESTIMATOR_STATS,
)


def make_optimizer(lr: float, clip_norm: float):
    """adam after global-norm clipping; non-finite gradients are skipped and counted.

    ``optax.apply_if_finite`` leaves params and adam state unchanged on a NaN/inf gradient and
    counts it (``notfinite_count``, ``total_notfinite``)."""
    return optax.apply_if_finite(
        optax.chain(optax.clip_by_global_norm(clip_norm), optax.adam(lr)), max_consecutive_errors=10**9
    )


def skipped_count(opt_state) -> int:
    """Total number of skipped (non-finite) gradients so far."""
    return int(opt_state.total_notfinite)


def training_batch(problem: Problem, k: int, size: int | None = None):
    """The pushes of gradient step k: (Scenario (size,), columns); ``size`` default: the step's
    distinct rollouts (whole-horizon mode) or forward rollouts (window mode)."""
    tc = problem.tc
    if size is None:
        size = tc.pushes_per_call
    return tp.sample_pushes(tc, problem.robot, problem.table, tp.batch_rng(tc.seed, 0, k), size, problem.setup.dtype)


def pair_rows(tree, pairs: bool):
    """Each row twice (rows 2j, 2j + 1 share it) for antithetic pairs."""
    return jax.tree_util.tree_map(lambda x: jnp.repeat(jnp.asarray(x), 2, axis=0), tree) if pairs else tree


class GradientStep:
    """One optimiser step of gradient tuning: ``step(params, opt_state, k) -> (params, opt_state,
    row)``, ``row`` the step's history entries (loss, terms, survival, gradient statistics,
    simulated steps). :meth:`compile` builds its programs ahead of time (seconds returned)."""

    def __init__(self, problem: Problem, optimizer, mesh=None):
        tc = problem.tc
        self.problem, self.optimizer, self.mesh = problem, optimizer, mesh
        n_dev = int(objectives.mesh_of(mesh).devices.size)
        if tc.batch % n_dev:
            raise ValueError(f"--batch {tc.batch} must be a multiple of the {n_dev} devices")
        self.windowed = tc.window_s > 0
        if self.windowed:
            self.fwd = tp.with_backend(problem, forward_backend(tc))
            self.rollouts = tc.distinct_rollouts // tc.windows
            if self.rollouts % n_dev:
                raise ValueError(
                    f"window mode: {self.rollouts} forward rollouts per step must divide by {n_dev} devices"
                )
            self.sampler = tw.make_sampler(self.fwd, self.rollouts, tc.windows, mesh)
            self.grads = tw.make_window_grads(problem, mesh)
            self.W = tw.window_ticks(problem)
        else:
            self.grads = objectives.make_rollout_grads(problem, mesh)
        self.update = jax.jit(self._update)
        self.perturb = jax.jit(estimators.antithetic, static_argnums=(2, 3))
        self.compiled = False

    def _update(self, params, opt_state, values, grads, eps, terms):
        """The optimiser step and the step's summary {loss, term means, grad_norm, finite, skipped_total,
        estimator stats}: one program, one transfer to the host."""
        tc = self.problem.tc
        grad, stats = estimators.combine(
            tc.estimator,
            values,
            grads,
            eps,
            sigma=tc.smoothing_sigma,
            clip_factor=tc.env_clip,
            bias_factor=tc.bias_factor,
        )
        finite = jnp.all(jnp.asarray([jnp.all(jnp.isfinite(g)) for g in jax.tree_util.tree_leaves(grad)]))
        updates, opt_state = self.optimizer.update(grad, opt_state, params)
        summary = {
            "loss": jnp.nanmean(jnp.where(jnp.isfinite(values), values, jnp.nan)),
            **{n: jnp.mean(terms[n]) for n in TERMS},
            "grad_norm": optax.global_norm(grad),
            "finite": finite,
            "skipped_total": opt_state.total_notfinite,
            **stats,
        }
        return optax.apply_updates(params, updates), opt_state, summary

    def rows_of(self, params, k: int):
        """(per-rollout params (B, ...), eps (B / 2, D) or None, the step's rollouts (Scenario or
        WindowStart (B,)), forward terms and metrics or None, simulated forward steps)."""
        tc, problem = self.problem.tc, self.problem
        if tc.pairs:
            key = jax.random.fold_in(jax.random.key(tc.seed * 1000 + 7), k)
            params_b, eps = self.perturb(params, key, tc.batch // 2, tc.smoothing_sigma)
        else:
            params_b, eps = estimators.repeated(params, tc.batch), None
        scen = objectives.cast_batch(training_batch(problem, k)[0], problem.setup.dtype)
        if not self.windowed:
            return params_b, eps, pair_rows(scen, tc.pairs), None, 0
        starts, terms, metrics = self.sampler(*self._sampler_args(params, k, scen))
        fwd_steps = self.rollouts * problem.steps_per_rollout
        return params_b, eps, pair_rows(starts, tc.pairs), (terms, metrics), fwd_steps

    def _sampler_args(self, params, k: int, scen=None) -> tuple:
        """The window sampler's arguments of step ``k``: (params, the step's pushes, window start ticks)."""
        tc, problem = self.problem.tc, self.problem
        if scen is None:
            scen = objectives.cast_batch(training_batch(problem, k)[0], problem.setup.dtype)
        ticks = tw.sample_starts(tp.batch_rng(tc.seed, 5, k), self.rollouts, tc.windows, problem.loop.n_ticks, self.W)
        return params, scen, ticks

    def compile(self, params, opt_state) -> float:
        """Build the step's programs ahead of time; returns the seconds spent (0 when already built).

        On one device the gradient and window programs load when an earlier phase or process compiled
        them (:meth:`~wbc_jax.tuning.algorithms.problem.Problem.program_identity` keys them): the race's
        hybrid builds its step once per budget, and a separate quality phase builds it again."""
        if self.compiled:
            return 0.0
        self.compiled = True
        t0 = time.perf_counter()
        identity = self.problem.program_identity(objectives.mesh_of(self.mesh))
        if self.windowed:
            self.sampler.compile(*self._sampler_args(params, 0), saved_as=("tune_window_sampler", identity))
        params_b, eps, rollouts, _, _ = self.rows_of(params, 0)
        self.grads.compile(params_b, rollouts, saved_as=("tune_gradient", identity))
        out = self.grads.eval_shape(params_b, rollouts)  # the compiled program's own shapes on one device
        self.update = runner.compile_ahead(self.update, params, opt_state, out[0], out[1], eps, out[2])
        return time.perf_counter() - t0

    def memory_mb(self):
        program = self.grads.program  # several devices: each device's program is alike; the first one's
        program = next(iter(program.compiled.values()), None) if isinstance(program, PerDevice) else program
        ma = program.memory_analysis() if hasattr(program, "memory_analysis") else None
        return (
            None
            if ma is None
            else {"temp_mb": ma.temp_size_in_bytes / 2**20, "argument_mb": ma.argument_size_in_bytes / 2**20}
        )

    def __call__(self, params, opt_state, k: int):
        problem = self.problem
        params_b, eps, rollouts, forward, fwd_steps = self.rows_of(params, k)
        values, grads, terms, metrics = self.grads(params_b, rollouts)
        params, opt_state, summary = self.update(params, opt_state, values, grads, eps, terms)
        if forward is not None:  # the whole-horizon rollouts of the window starts: their loss and outcomes
            metrics = forward[1]
        summary, metrics, forward = jax.device_get((summary, metrics, forward))  # the step's one transfer
        grad_steps = problem.tc.batch * (self.W if self.windowed else problem.loop.n_ticks) * problem.loop.n_sub
        row = {
            k_: (bool(v) if k_ == "finite" else int(v) if k_ == "skipped_total" else float(v))
            for k_, v in summary.items()
        }
        total = np.asarray(forward[0]["total"]) if forward is not None else None
        row["rollout_loss"] = (
            row["loss"] if total is None else float(np.mean(np.log1p(total) if problem.lc.robust else total))
        )
        row.update(grad_sim_steps=grad_steps, sim_steps_delta=grad_steps + fwd_steps, **tp.survival_stats(metrics))
        return params, opt_state, row


def forward_backend(tc: TuneConfig) -> str:
    """The engine of forward rollouts: ``--search-backend`` resolved (auto: warp where available)."""
    from wbc_jax.sim import physics

    if tc.search_backend == "auto":
        return "warp" if physics.has_cuda() and physics.has_warp() else "jax"
    return physics.resolve_backend(tc.search_backend)


def at_time(rows: list, seconds: float) -> int:
    """Index of the last history row whose wall time is within ``seconds`` (-1: none: the start)."""
    idx = [i for i, r in enumerate(rows) if float(r["wall_s"]) <= seconds]
    return idx[-1] if idx else -1


def start_key(problem: Problem, params) -> str:
    """The checkpoint key of a training run from ``params`` (another start: another run)."""
    flat = np.asarray(ravel_pytree(params)[0], np.float64)
    return f"{problem.key}-start-{hashlib.sha256(flat.tobytes()).hexdigest()[:16]}"


def train(
    problem: Problem,
    out,
    *,
    progress: bool = True,
    step_fn=None,
    mesh=None,
    start_params=None,
    budget_s: float | None = None,
):
    """Gradient tuning into ``out``: checkpoint.npz (resumable; every step's parameters), history.csv,
    train_info.json. Stops after ``tc.steps`` steps, or when ``budget_s`` (default ``tc.budget_s``; > 0)
    of wall time is spent, compilation included.

    ``start_params``: the unconstrained parameters to start from (default: ``problem.init_params()``, the
    --init-gains; the race's hybrid starts from CMA-ES's set); the checkpoint then also keeps them.
    ``step_fn``: a callable with :class:`GradientStep`'s signature (tests); default: a GradientStep,
    compiled here (its compile time, counted in the wall time, and memory go to train_info.json).
    Returns (tuned controls, regularisation (2,), history rows, info dict)."""
    from tqdm.auto import tqdm

    tc = problem.tc
    budget = tc.budget_s if budget_s is None else float(budget_s)
    out = pathlib.Path(out)
    out.mkdir(parents=True, exist_ok=True)
    optimizer = make_optimizer(tc.lr, tc.clip_norm)
    params = problem.init_params() if start_params is None else start_params
    key = problem.key if start_params is None else start_key(problem, params)
    flat0, unravel = ravel_pytree(params)
    kept = {} if start_params is None else {"start": np.asarray(flat0)}
    state = (params, optimizer.init(params))
    ckpt, hist_path, info_path = out / "checkpoint.npz", out / "history.csv", out / "train_info.json"
    start, rows, info, snapshots = 0, [], {}, np.zeros((0, flat0.size))
    if ckpt.exists():
        state, start, extra = store.load_checkpoint(ckpt, state, key)
        rows = store.read_csv(hist_path)[:start] if hist_path.exists() else []
        snapshots = extra.get("snapshots", snapshots)[:start]
    # A run stopped before its first step has its first compile on record: it counts, and may spend the budget.
    info = json.loads(info_path.read_text()) if info_path.exists() else {}
    wall = float(rows[-1]["wall_s"]) if rows else float(info.get("compile_s", 0.0))

    def spent(k: int) -> bool:
        return k >= tc.steps or (budget > 0 and wall >= budget)

    if not spent(start) and (step_fn is None or isinstance(step_fn, GradientStep)):
        step_fn = GradientStep(problem, optimizer, mesh) if step_fn is None else step_fn
        compile_s = step_fn.compile(*state)
        info.setdefault("compile_s", round(compile_s, 2))  # the first compile counts in the wall budget
        info.update(
            last_compile_s=round(compile_s, 2),
            device=provenance.device_label(),
            n_devices=step_fn.grads.n_devices,
            batch=tc.batch,
            horizon_s=tc.horizon,
            steps_per_rollout=problem.steps_per_rollout,
            estimator=tc.estimator,
            window_s=tc.window_s,
            checkpoint=tc.checkpoint,
            parameterisation=tc.parameterisation,
            budget_s=budget,
            parameters=int(flat0.size),
            **(step_fn.memory_mb() or {}),
        )
        info["provenance"] = provenance.record(tc.input_files)
        io.atomic_write_json(info_path, info)
    if not rows:
        wall = float(info.get("compile_s", 0.0))
    sim_steps = int(rows[-1]["sim_steps"]) if rows else 0
    k = start
    with tqdm(total=tc.steps, initial=start, unit="step", disable=not progress, desc="gradient") as bar:
        while not spent(k):
            t0 = time.perf_counter()
            params, opt_state, row = step_fn(*state, k)
            dt = time.perf_counter() - t0
            wall += dt
            sim_steps += int(row.pop("sim_steps_delta"))
            state = (params, opt_state)
            rows.append(
                {
                    "step": k,
                    **row,
                    "step_s": round(dt, 3),
                    "sim_steps": sim_steps,
                    "wall_s": round(wall, 3),
                    "rss_mb": round(store.rss_mb(), 1),
                }
            )
            snapshots = np.concatenate([snapshots, np.asarray(ravel_pytree(params)[0])[None]])
            k += 1
            store.save_checkpoint(ckpt, state, k, key, snapshots=snapshots, **kept)
            store.write_csv(hist_path, rows, HISTORY_COLUMNS)
            bar.set_postfix(
                loss=f"{row['loss']:.4g}",
                surv=f"{row['survival_rate']:.2f}",
                skipped=row["skipped_total"],
                dropped=int(row["nonfinite_envs"]),
            )
            bar.update(1)
    controls, reg = problem.controls(state[0])
    steady = [float(r["step_s"]) for r in rows[1:]] or [float(r["step_s"]) for r in rows]
    if steady and rows:
        info["step_s_median"] = float(np.median(steady))
        info["gradient_physics_steps_per_s"] = float(rows[-1]["grad_sim_steps"]) / info["step_s_median"]
        info["physics_steps_per_s"] = (int(rows[-1]["sim_steps"]) / len(rows)) / info["step_s_median"]
        if isinstance(step_fn, GradientStep) and step_fn.grads.ran_on:  # the devices the last step's rollouts ran on
            info["ran_on"] = step_fn.grads.ran_on
        io.atomic_write_json(info_path, info)
    return controls, problem.regularisation(reg), rows, info


def snapshot_controls(problem: Problem, out, index: int, start_params=None):
    """(controls, regularisation (2,)) after history row ``index`` of a training run in ``out`` (-1: the
    start, ``start_params`` or ``problem.init_params()``)."""
    params0 = problem.init_params() if start_params is None else start_params
    if index < 0:
        controls, reg = problem.controls(params0)
        return controls, problem.regularisation(reg)
    flat0, unravel = ravel_pytree(params0)
    with np.load(pathlib.Path(out) / "checkpoint.npz") as z:
        snap = z["extra_snapshots"][index]
    controls, reg = problem.controls(unravel(jnp.asarray(snap, flat0.dtype)))
    return controls, problem.regularisation(reg)
