"""Gradient-based gain tuning through the differentiable closed loop (issues 5, 20).

The pipeline (brax-APG shape)::

    params --(bounded, stable map: tuning_params)--> gains (+ regularisation)
           --vmap(closed loop with a TuneTrace over B sampled pushes: tuning_problem)--> loss
           <--(adam, clipped, NaN-guarded)-- grad                       (tuning_loss)

Differentiation: reverse mode (``jax.value_and_grad``) through the whole ``lax.scan`` of the
closed loop: MJX physics with the model's contact solver (Newton, 4 iterations), 4 corner spheres
per foot (foot boxes gave NaN gradients), the contact QP through its implicit
(custom_jvp, transposed) derivative, and ``jax.checkpoint`` on each 10 ms control tick
(``--checkpoint tick``), so memory grows with the horizon only by one carry per tick. Reverse
mode costs one backward pass for all 58 (60 with the regularisation) parameters.

MJX's Newton loop is a ``lax.while_loop`` (not reverse-differentiable) unless iterations == 1.
With iterations = 1 the closed loop is chaotic (float64, 0.35 s after a 50 N push: the loss
went 50.2 -> 1.2 when kp_com changed by 1e-6 relative), with 4 it is smooth. While the tuning
program is traced, :func:`wbc_jax.sim.physics.fixed_iteration_solver` swaps that one ``while_loop``
for MJX's own scan-based ``_while_loop_scan`` with the same bound: identical values (the scan
does no-ops once the loop condition is false), reverse-differentiable.

Each step draws a fresh batch of B pushes from the training distribution
(:func:`wbc_jax.tuning.problem.sample_pushes`); the loss (:mod:`wbc_jax.tuning.loss`) is a smooth
surrogate of strict survival. The run is resumable (checkpoint.npz, history.csv) and its
history counts the simulated physics steps and the wall time, against which the gradient-free
baselines (:mod:`wbc_jax.tuning.baselines`) get the same budget.
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax

from wbc_jax.control.gains import Gains, default_gains, gains_to_dict
from wbc_jax.core import io, provenance
from wbc_jax.jobs import runs
from wbc_jax.report import tuning_plots
from wbc_jax.sim import physics, runner, scenario
from wbc_jax.tuning import baselines
from wbc_jax.tuning import heldout as tuning_eval
from wbc_jax.tuning import problem as tp
from wbc_jax.tuning.config import TuneConfig, default_config
from wbc_jax.tuning.loss import TERMS, LossConfig
from wbc_jax.tuning.params import (
    nava_conditions,
)
from wbc_jax.tuning.problem import Problem, make_problem, sample_pushes

ENV_STATS = ("nonfinite_envs", "clipped_envs", "env_grad_norm_median")  # robust_mean_gradient's counts
HISTORY_COLUMNS = ("step", "loss", *TERMS, "survival_rate", "upright_rate", "qp_infeasible_rate", "grad_norm",
                   "finite", "skipped_total", "step_s", "sim_steps", "wall_s", "rss_mb", *ENV_STATS)  # fmt: skip


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


def robust_mean_gradient(grads, clip_factor: float):
    """The batch mean of per-rollout gradients, robust to rollouts that diverge.

    grads: a pytree whose leaves have a leading batch axis B (one gradient per rollout). A rollout
    whose gradient has a non-finite entry is left out; with ``clip_factor`` > 0 each remaining
    gradient is scaled down to at most ``clip_factor`` x the median norm of the remaining ones
    (a falling robot's gradient can be 1e14 times a standing one's and would otherwise set the
    direction of the whole batch's step). Elementwise products only (no matrix products, which
    run in reduced precision on some GPUs).

    Returns (mean gradient (the leaves without the batch axis; NaN if no rollout is finite, so
    that the optimiser's guard skips the step), stats {"nonfinite_envs": (), "clipped_envs": (),
    "env_grad_norm_median": ()})."""
    leaves = jax.tree_util.tree_leaves(grads)
    B = leaves[0].shape[0]
    flat = jnp.concatenate([jnp.reshape(x, (B, -1)) for x in leaves], axis=1)
    finite = jnp.all(jnp.isfinite(flat), axis=1)  # (B,)
    norms = jnp.sqrt(jnp.sum(jnp.where(jnp.isfinite(flat), flat, 0.0) ** 2, axis=1))
    n_ok = jnp.sum(finite)
    median = jnp.nanmedian(jnp.where(finite, norms, jnp.nan))
    if clip_factor > 0:
        cap = clip_factor * median
        clipped = finite & (norms > cap)
        scale = jnp.where(clipped, cap / jnp.where(norms > 0, norms, 1.0), 1.0)
    else:
        clipped = jnp.zeros_like(finite)
        scale = jnp.ones_like(norms)
    weight = jnp.where(finite, scale, 0.0) / jnp.maximum(n_ok, 1) * jnp.where(n_ok > 0, 1.0, jnp.nan)

    def mean(x):
        x = jnp.where(jnp.reshape(finite, (B,) + (1,) * (x.ndim - 1)), x, 0.0)
        return jnp.sum(jnp.reshape(weight, (B,) + (1,) * (x.ndim - 1)).astype(x.dtype) * x, axis=0)

    stats = {"nonfinite_envs": B - n_ok, "clipped_envs": jnp.sum(clipped), "env_grad_norm_median": median}
    return jax.tree_util.tree_map(mean, grads), stats


def make_train_step(problem: Problem, optimizer):
    """One optimiser step, jitted: ``(params, opt_state, scen) -> (params, opt_state, loss (),
    terms {name: ()}, Metrics (B,), grad_norm (), finite (), env_stats {name: ()})``.

    Each push's gradient is taken on its own (vmap of value_and_grad: the same backward pass as
    the batch mean's) and combined by :func:`robust_mean_gradient` (``tc.env_clip``), so a
    rollout that diverges neither poisons nor steers the step; ``env_stats`` counts them."""
    env_objective = tp.make_env_objective(problem)
    clip_factor = float(problem.tc.env_clip)

    @jax.jit
    def step(params, opt_state, scen):
        with physics.fixed_iteration_solver(problem.iterations):
            per_env = jax.vmap(jax.value_and_grad(env_objective, has_aux=True), in_axes=(None, 0))
            (values, (terms, metrics)), grads = per_env(params, scen)
        grad, env_stats = robust_mean_gradient(grads, clip_factor)
        finite = jnp.all(jnp.asarray([jnp.all(jnp.isfinite(g)) for g in jax.tree_util.tree_leaves(grad)]))
        updates, opt_state = optimizer.update(grad, opt_state, params)
        params = optax.apply_updates(params, updates)
        terms = jax.tree_util.tree_map(jnp.mean, terms)
        return params, opt_state, jnp.mean(values), terms, metrics, optax.global_norm(grad), finite, env_stats

    return step


def training_batch(problem: Problem, k: int):
    """The pushes of gradient step k: (Scenario (B,), columns)."""
    tc = problem.tc
    return sample_pushes(tc, problem.robot, problem.table, tp.batch_rng(tc.seed, 0, k), tc.batch, problem.setup.dtype)


def train(problem: Problem, out, *, progress: bool = True, step_fn=None):
    """Gradient tuning into ``out``: checkpoint.npz (resumable), history.csv, train_info.json,
    tuned_gains.json (+ tuned_regularisation.json with ``tune_regularisation``).

    ``step_fn``: a step with :func:`make_train_step`'s signature (tests); default: compiled here,
    ahead of time (its compile time and XLA memory analysis go to train_info.json).
    Returns (tuned Gains, regularisation (2,), history rows, info dict)."""
    from tqdm.auto import tqdm

    tc = problem.tc
    out = pathlib.Path(out)
    optimizer = make_optimizer(tc.lr, tc.clip_norm)
    params = problem.init_params()
    state = (params, optimizer.init(params))
    ckpt, hist_path, info_path = out / "checkpoint.npz", out / "history.csv", out / "train_info.json"
    start, rows, info = 0, [], {}
    if ckpt.exists():
        state, start, _ = tp.load_checkpoint(ckpt, state, problem.key)
        rows = tp.read_csv(hist_path)[:start] if hist_path.exists() else []
        info = json.loads(info_path.read_text()) if info_path.exists() else {}
    if step_fn is None:
        step_fn = make_train_step(problem, optimizer)
    if start < tc.steps and hasattr(step_fn, "lower"):  # ahead of time: the compile timed apart
        t0 = time.perf_counter()
        step_fn = step_fn.lower(*state, tp.shard_batch(training_batch(problem, start)[0])).compile()
        compile_s = time.perf_counter() - t0
        info.setdefault("compile_s", round(compile_s, 2))  # the first compile counts in the wall budget
        info["last_compile_s"] = round(compile_s, 2)
        ma = step_fn.memory_analysis()
        if ma is not None:
            info.update(temp_mb=ma.temp_size_in_bytes / 2**20, argument_mb=ma.argument_size_in_bytes / 2**20)
        info.update(device=provenance.device_label(), n_devices=len(runner.batch_devices()), batch=tc.batch, horizon_s=tc.horizon,
                    steps_per_rollout=problem.steps_per_rollout)  # fmt: skip
        io.atomic_write_json(info_path, info)
    wall = float(rows[-1]["wall_s"]) if rows else float(info.get("compile_s", 0.0))
    per_step = tc.batch * problem.steps_per_rollout
    with tqdm(total=tc.steps, initial=start, unit="step", disable=not progress, desc="gradient") as bar:
        for k in range(start, tc.steps):
            scen = tp.shard_batch(training_batch(problem, k)[0])
            t0 = time.perf_counter()
            params, opt_state, loss, terms, metrics, gnorm, finite, env_stats = step_fn(*state, scen)
            jax.block_until_ready(params)
            dt = time.perf_counter() - t0
            wall += dt
            state = (params, opt_state)
            rows.append({"step": k, "loss": float(loss), **{n: float(terms[n]) for n in TERMS},
                         **tp.survival_stats(metrics), "grad_norm": float(gnorm), "finite": bool(finite),
                         "skipped_total": skipped_count(opt_state), "step_s": round(dt, 3),
                         "sim_steps": (k + 1) * per_step, "wall_s": round(wall, 3), "rss_mb": round(tp.rss_mb(), 1),
                         **{n: float(env_stats[n]) for n in ENV_STATS}})  # fmt: skip
            tp.save_checkpoint(ckpt, state, k + 1, problem.key)
            tp.write_csv(hist_path, rows, HISTORY_COLUMNS)
            bar.set_postfix(loss=f"{float(loss):.4g}", surv=f"{rows[-1]['survival_rate']:.2f}",
                            skipped=skipped_count(opt_state), dropped=int(env_stats["nonfinite_envs"]))  # fmt: skip
            bar.update(1)
    gains, reg = problem.controls(state[0])
    reg = problem.regularisation(reg)
    save_controls(out, "tuned", gains, reg, problem)
    steady = [float(r["step_s"]) for r in rows[1:]] or [float(r["step_s"]) for r in rows]
    if steady:
        info["step_s_median"] = float(np.median(steady))
        info["gradient_physics_steps_per_s"] = per_step / info["step_s_median"]
        io.atomic_write_json(info_path, info)
    return gains, reg, rows, info


def save_controls(out: pathlib.Path, name: str, gains: Gains, reg, problem: Problem) -> None:
    """``{name}_gains.json`` (a gains file) and, when the regularisation is tuned,
    ``{name}_regularisation.json``."""
    io.atomic_write_json(out / f"{name}_gains.json", gains_to_dict(gains))
    if problem.tc.tune_regularisation:
        io.atomic_write_json(
            out / f"{name}_regularisation.json",
            dict(zip(("pinv_damping", "kp_postural_reg"), np.asarray(reg, float).tolist())),
        )


# ---------------------------------------------------------------------------------------------
# The `wbc-jax tune` job


def run(cfg: TuneConfig | None = None, *, lc: LossConfig | None = None, progress: bool = True,
        robot_name: str = "icub", **overrides) -> dict:  # fmt: skip
    """The ``tune`` job: gradient training, the gradient-free baselines at equal simulated steps
    (``cfg.baselines``), and the held-out pushes (the training distribution, another seed,
    ``eval_horizon``): strict survival and loss per gain set. Writes into ``cfg.out``:
    tuned_gains.json, history.csv, {cmaes,random}_gains.json and _history.csv, learning.png,
    eval.json. Returns eval.json's dict. ``overrides``: fields of :class:`TuneConfig`."""
    tc = dataclasses.replace(default_config() if cfg is None else cfg, **overrides)
    lc = LossConfig() if lc is None else lc
    out = pathlib.Path(tc.out)
    runs.check_output_dir(out, "tune")
    problem = make_problem(tc, lc, robot_name=robot_name)
    runs.claim_output_dir(out, "tune", runs.fingerprint({"tune": dataclasses.asdict(tc), "loss": dataclasses.asdict(lc),
                                                         "dtype": str(scenario.float_dtype())}, [tc.init_gains, tc.envelope, tc.tasks]),
                          resume=True)  # fmt: skip
    gains, reg, rows, info = train(problem, out, progress=progress)
    sets = {"default": (default_gains(problem.robot.index.n), problem.reg0), "gradient": (gains, reg)}
    histories = {"gradient": rows}
    budget = {"sim_steps": int(rows[-1]["sim_steps"]), "wall_s": float(rows[-1]["wall_s"])}
    for kind in tc.baselines:
        res = baselines.search(problem, kind, out / kind, budget=budget, progress=progress)
        sets[kind] = res["equal_steps"]["controls"]
        histories[kind] = res["history"]
        save_controls(out, kind, *sets[kind], problem)
    tuning_plots.learning_curves(histories, out / "learning.png", budget)
    held = tuning_eval.evaluate_pushes(problem, sets, progress=progress)
    report = {"held_out": held, "budget": budget, "train": info, "config": dataclasses.asdict(tc),
              "loss": dataclasses.asdict(lc), "nava_2016": {k: nava_conditions(*v) for k, v in sets.items()},
              "survival_criterion": tp.constants_used(), "device": provenance.device_label(),
              "versions": {"jax": jax.__version__, "mujoco": __import__("mujoco").__version__}}  # fmt: skip
    io.atomic_write_json(out / "eval.json", report)
    return report


def report_line(report: dict) -> dict:
    """The one-line JSON summary of a tuning report (the CLI prints it)."""
    keys = ("objective", "survival_rate", "upright_rate", "com_rmse_m")
    return {name: {k: r.get(k) for k in keys} for name, r in report["held_out"].items()}
