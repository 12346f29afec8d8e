"""Does the tuning loss predict survival? (the phase ``predict`` of ``wbc-jax tune``): held-out pushes of the
training distribution rolled out past the training horizon, their loss against strict survival."""

from __future__ import annotations

import pathlib
import time

import jax
import numpy as np

from wbc_jax.core import io, provenance
from wbc_jax.report.tuning_plots import survival_vs_loss
from wbc_jax.sim import metrics as metrics_lib
from wbc_jax.sim import mjx_loop, physics
from wbc_jax.tuning.algorithms import loss as tuning_loss
from wbc_jax.tuning.algorithms import problem as tp


def survival_prediction(problem: tp.Problem, n: int, *, gains=None, reg=None, out=None) -> dict:
    """Does the loss predict strict survival? ``n`` held-out pushes of the training distribution
    (stream 4), rolled out for ``eval_horizon`` s with the given gains (default: the start of the
    search); strict survival at the end against the loss of the training horizon (the trace's
    first ticks) and of the whole rollout: Spearman correlation, ROC area, per-push values;
    survival_vs_loss.png and prediction.json in ``out``."""
    tc = problem.tc
    ev = tp.make_problem(tc, problem.lc, horizon=tc.eval_horizon, checkpoint=False)
    scen, cols = tp.sample_pushes(tc, ev.robot, ev.table, tp.batch_rng(tc.seed, 4, 0), n, ev.setup.dtype)
    if gains is None:  # the start of the search (a schedule's at W = 0 with --parameterisation scheduled)
        gains = ev.controls(ev.init_params())[0]
    regd = dict(zip(("pinv_damping", "kp_postural_reg"), np.asarray(problem.reg0 if reg is None else reg, float)))
    n_train = problem.loop.n_ticks

    def both(g, r, s):
        metrics, trace = mjx_loop.rollout(ev.loop, *_env_args(ev, s), g, s.push, controller_overrides=r)
        return tuning_loss.loss_terms(trace, ev.lc, n_train), tuning_loss.loss_terms(trace, ev.lc), metrics

    t0 = time.perf_counter()
    terms, full_terms, metrics = jax.jit(jax.vmap(both, in_axes=(None, None, 0)))(gains, regd, scen)
    wall = time.perf_counter() - t0
    outcome = metrics_lib.summarize(metrics)
    survived = np.asarray(outcome["survived"])
    train_loss, full_loss = np.asarray(terms["total"]), np.asarray(full_terms["total"])
    per_term = {
        k: {"spearman": tuning_loss.spearman(np.asarray(v), survived), "auc": tuning_loss.auc(np.asarray(v), survived)}
        for k, v in terms.items()
        if k != "total"
    }
    rel = cols["impulse_ns"] / tp.interp_periodic(*problem.table, cols["azimuth_deg"])
    edges = np.linspace(*tc.magnitude_range, 5)
    bins = np.clip(np.searchsorted(edges, rel, side="right") - 1, 0, 3)
    by_size = [
        {
            "impulse_fraction": [float(edges[i]), float(edges[i + 1])],
            "n": int(np.sum(bins == i)),
            "survival_rate": float(survived[bins == i].mean()) if np.any(bins == i) else None,
        }
        for i in range(4)
    ]
    res = {
        "n": n,
        "survival_rate": float(survived.mean()),
        "horizon_s": tc.eval_horizon,
        "train_horizon_s": tc.horizon,
        "spearman_train_horizon": tuning_loss.spearman(train_loss, survived),
        "spearman_full": tuning_loss.spearman(full_loss, survived),
        "auc_train_horizon": tuning_loss.auc(train_loss, survived),
        "auc_full": tuning_loss.auc(full_loss, survived),
        "spearman_impulse_fraction": tuning_loss.spearman(rel, survived),
        "auc_impulse_fraction": tuning_loss.auc(rel, survived),
        "wall_s": round(wall, 1),
        "loss_train_horizon": train_loss.tolist(),
        "loss_full": full_loss.tolist(),
        "survived": survived.tolist(),
        "impulse_fraction_of_envelope": rel.tolist(),
        "per_term_train_horizon": per_term,
        "device": provenance.device_label(),
        "terms_train_horizon": {k: np.asarray(v).tolist() for k, v in terms.items()},
        "terms_full": {k: np.asarray(v).tolist() for k, v in full_terms.items()},
        "outcome": {k: np.asarray(v, float).tolist() for k, v in outcome.items()},
        "survival_by_impulse_fraction": by_size,
        "failure_rates": {k: float(np.mean(v)) for k, v in metrics_lib.failed_tests(outcome).items()},
    }
    if out is not None:
        out = pathlib.Path(out)
        res["provenance"] = provenance.record(tc.input_files)
        io.atomic_write_json(out / "prediction.json", res)
        survival_vs_loss(train_loss, survived, res, out / "survival_vs_loss.png")
    return res


def _env_args(problem: tp.Problem, s):
    st, loop = problem.setup, problem.loop
    nominal = physics.device_model(st.robot.mj_model, "jax", loop.cfg.physics)
    return physics.plant_model(nominal, s.friction, s.mass_scale), loop.initial_qpos(
        jax.numpy.asarray(st.qpos0, st.dtype), s.joint_offset
    )
