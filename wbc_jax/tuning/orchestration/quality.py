"""How good is the gradient? (phase ``quality`` of ``wbc-jax tune``, quality.json)

On N fixed held-out pushes of the training distribution (stream 6), at the start of the search theta,
with J(theta) the mean objective of the N rollouts (the training loss at the training horizon):

* first-order estimates from the training program (the whole horizon, or ``--window-s`` windows):
  per-rollout gradients at theta (``first-order``) and at antithetic perturbations theta +- sigma eps
  (``smoothed``, and with their values the ``interpolated`` mix: :mod:`wbc_jax.tuning.algorithms.estimators`),
  each over the N pushes in batches of the training batch;
* a zeroth-order estimate of the gradient of the smoothed loss E[J(theta + sigma eps)] from M antithetic
  directions on the same N pushes (common random numbers), g_ZO = mean_m (J(theta + sigma e_m) -
  J(theta - sigma e_m)) / (2 sigma) e_m, and its two halves (their cosine is the ceiling any estimate
  can reach against it with this M);
* for each estimate: its cosine with g_ZO (against the exact gradient of a smooth loss that cosine is
  about 1 / sqrt(1 + (D + 1) / M): ``exact_gradient_cosine``); the correlation of its directional
  derivatives e_m . g with the measured ones (J(theta + sigma e_m) - J(theta - sigma e_m)) / (2 sigma)
  and the slope between them (1: the right size); its consistency over batches (the mean cosine between
  one batch's estimate and the mean of the others; the signal-to-noise ratio |g|^2 / (tr Cov / n) of
  the per-rollout rows); and whether it descends: J(theta - h u) - J(theta) along its unit direction u
  for a few steps h, against the first-order prediction -h |g . u|.

Everything forward runs in one population program on ``--search-backend`` (Warp on a GPU); the
gradients in the training program (no other compilation). With ``--quality-directions 0`` the
zeroth-order estimate comes from the antithetic pairs of the training program instead (one push or
window per direction: noisier, and of the window objective in window mode) and nothing else is
compiled: what fits a short GPU call.
"""

from __future__ import annotations

import json
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from wbc_jax.core import io, provenance
from wbc_jax.tuning.algorithms import estimators, objectives
from wbc_jax.tuning.algorithms import gradient as tuning
from wbc_jax.tuning.algorithms import problem as tp
from wbc_jax.tuning.algorithms import windows as tw

STREAM = 6
LINE_STEPS = (0.02, 0.05, 0.1, 0.2)  # unconstrained units along a unit direction


# The population program evaluates at most this many rollouts at once: 2,048 pushes x 129 candidates in one
# program asked an H200 for 168 GiB (phase quality of the race, 2026-11-26); the searches' own programs stay
# within it too (--population 16 x --es-batch 60).
ENVS_PER_CALL = 16384


def candidates_per_call(candidates: int, pushes: int) -> int:
    """Candidates per population-program call: all ``candidates`` when their ``pushes`` rollouts each fit
    :data:`ENVS_PER_CALL`, else as many as fit (at least one)."""
    return max(1, min(candidates, ENVS_PER_CALL // max(pushes, 1)))


def evaluate(pop, per_call: int, unravel, points: np.ndarray, filler: np.ndarray, scen) -> np.ndarray:
    """The objective (K,) of the flat parameter ``points`` (K, D) through the population program ``pop`` of
    ``per_call`` candidates, in calls of ``per_call`` (the last padded with ``filler`` (D,), dropped)."""
    k = len(points)
    padded = np.concatenate([points, np.repeat(filler[None], -k % per_call, 0)]) if k % per_call else points
    values = []
    for i in range(0, len(padded), per_call):
        batch = jax.vmap(unravel)(jnp.asarray(padded[i : i + per_call], filler.dtype))
        values += np.asarray(pop(batch, scen)[0], float).tolist()
    return np.asarray(values[:k], float)


def cosine(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    return float(a @ b / (na * nb)) if na > 0 and nb > 0 and np.isfinite(na * nb) else float("nan")


def batch_consistency(means: np.ndarray) -> float:
    """Mean cosine of each batch's estimate (K, D) with the mean of the other batches."""
    K = means.shape[0]
    if K < 2:
        return float("nan")
    total = means.sum(0)
    return float(np.nanmean([cosine(means[k], (total - means[k]) / (K - 1)) for k in range(K)]))


def snr(rows: np.ndarray) -> float:
    """|mean|^2 / (tr Cov / n) of finite per-rollout rows (n, D): how far the mean stands out of its noise.
    In float64: float32 per-rollout gradients of a few diverging rollouts reach 1e20 and more, and their
    variance overflowed to inf (the race's quality phase reported 0.0 and NaN, 2026-11-26)."""
    rows = np.asarray(rows, np.float64)
    rows = rows[np.all(np.isfinite(rows), 1)]
    if len(rows) < 2:
        return float("nan")
    m = rows.mean(0)
    return float(m @ m / (np.sum(rows.var(0, ddof=1)) / len(rows)))


def measure(problem: tp.Problem, out, *, mesh=None, progress: bool = True, step=None) -> dict:
    """The gradient-quality figures (module docstring) at the start of the search; quality.json in ``out``.
    ``step``: the training's :class:`~wbc_jax.tuning.algorithms.gradient.GradientStep` (its compiled program is reused)."""
    tc = problem.tc
    out = pathlib.Path(out)
    t_start = time.perf_counter()
    params = problem.init_params()
    flat0, unravel = ravel_pytree(params)
    D, N, M, sigma = int(flat0.size), tc.quality_pushes, tc.quality_directions, tc.smoothing_sigma
    if step is None:
        step = tuning.GradientStep(problem, tuning.make_optimizer(tc.lr, tc.clip_norm), mesh)
    scen_all, _ = tp.sample_pushes(
        tc, problem.robot, problem.table, tp.batch_rng(tc.seed, STREAM, 0), N, problem.setup.dtype
    )
    scen_all = objectives.cast_batch(scen_all, problem.setup.dtype)
    key = jax.random.key(tc.seed * 1000 + 11)
    B, half = tc.batch, tc.batch // 2

    def call_rows(k: int, perturbed: bool):
        """Call k's per-rollout parameters, eps and rows: at theta (the configured layout) or at
        antithetic perturbations (pairs sharing their push or window)."""
        paired = perturbed or tc.pairs
        if perturbed:
            pb, eps = estimators.antithetic(params, jax.random.fold_in(key, k), half, sigma)
        else:
            pb, eps = estimators.repeated(params, B), None
        if step.windowed:
            n_p = step.rollouts
            scen = jax.tree_util.tree_map(lambda x: x[k * n_p : (k + 1) * n_p], scen_all)
            ticks = tw.sample_starts(
                tp.batch_rng(tc.seed, STREAM + 1, k), n_p, tc.windows, problem.loop.n_ticks, step.W
            )
            starts, _, _ = step.sampler(params, scen, ticks)
            rows_in = jax.tree_util.tree_map(lambda x: x[: half if paired else B], starts)
        else:
            n_p = half if paired else B
            rows_in = jax.tree_util.tree_map(lambda x: x[k * n_p : (k + 1) * n_p], scen_all)
        return pb, eps, tuning.pair_rows(rows_in, paired), n_p

    def program_rows(perturbed: bool):
        """Per-call (values (B,), gradient rows (B, D), eps) over the N pushes."""
        vals, grads, epss = [], [], []
        n_p = step.rollouts if step.windowed else (half if perturbed or tc.pairs else B)
        for k in range(N // n_p):
            pb, eps, rows_in, _ = call_rows(k, perturbed)
            v, g, _, _ = step.grads(pb, rows_in)
            vals.append(np.asarray(v))
            grads.append(np.asarray(estimators.rows(g)))
            epss.append(None if eps is None else np.asarray(eps))
        return vals, grads, epss

    if progress:
        print(json.dumps({"quality": "first-order rows"}), flush=True)
    t0 = time.perf_counter()
    step.compile(params, step.optimizer.init(params))
    compile_s = time.perf_counter() - t0
    v_fo, g_fo, _ = program_rows(perturbed=False)
    v_sm, g_sm, e_sm = program_rows(perturbed=True) if B % 2 == 0 else (None, None, None)

    estimates, per_batch_means = {}, {}
    fo_batches = [np.asarray(estimators.robust_rows(jnp.asarray(g), tc.env_clip)[0]) for g in g_fo]
    per_batch_means["first-order"] = np.stack(fo_batches)
    estimates["first-order"] = np.mean(fo_batches, 0)
    if g_sm is not None:
        sm_batches, ip_batches, alphas = [], [], []
        for v, g, e in zip(v_sm, g_sm, e_sm):
            sm, _, (kept, ok) = estimators.robust_rows(jnp.asarray(g), tc.env_clip)
            zo, zo_ok = estimators.zeroth_order_rows(jnp.asarray(v), jnp.asarray(e), sigma)
            mix, stats = estimators.interpolate(kept, ok, zo, zo_ok, tc.bias_factor)
            sm_batches.append(np.asarray(sm))
            ip_batches.append(np.asarray(mix))
            alphas.append(float(stats["alpha"]))
        per_batch_means["smoothed"], per_batch_means["interpolated"] = np.stack(sm_batches), np.stack(ip_batches)
        estimates["smoothed"], estimates["interpolated"] = np.mean(sm_batches, 0), np.mean(ip_batches, 0)

    if M > 0:  # zeroth order on the population program: theta, then theta +- sigma e_m, the same N pushes
        if progress:
            print(json.dumps({"quality": "zeroth-order", "candidates": 2 * M + 1, "pushes": N}), flush=True)
        P = candidates_per_call(2 * M + 1, N)
        fwd = tp.with_backend(problem, tuning.forward_backend(tc))
        pop = objectives.make_population_objective(fwd, P, N, mesh)
        e = np.asarray(jax.random.normal(jax.random.key(tc.seed * 1000 + 13), (M, D), flat0.dtype))
        cands = np.concatenate([np.asarray(flat0)[None], np.asarray(flat0) + sigma * e, np.asarray(flat0) - sigma * e])
        t0 = time.perf_counter()
        J = evaluate(pop, P, unravel, cands, np.asarray(flat0), scen_all)
        pop_s = time.perf_counter() - t0
        J0, Jp, Jm = J[0], J[1 : M + 1], J[M + 1 :]
        directional = (Jp - Jm) / (2 * sigma)  # (M,) the smoothed loss's derivative along each e_m
        zo_terms = directional[:, None] * e
    else:  # zeroth order from the antithetic pairs of the program's calls: one push (or window) per direction
        pop, pop_s, directional, e = None, 0.0, None, None
        J0 = float(np.nanmean(np.concatenate(v_fo)))
        zo_terms = np.concatenate(
            [
                np.asarray(estimators.zeroth_order_rows(jnp.asarray(v), jnp.asarray(e), sigma)[0])
                for v, e in zip(v_sm or [], e_sm or [])
            ]
            or [np.zeros((0, D))]
        )
    ok = np.isfinite(zo_terms).all(1) & np.any(zo_terms != 0, 1)
    g_zo = zo_terms[ok].mean(0) if ok.any() else np.full(D, np.nan)
    half = max(1, int(ok.sum()) // 2)
    zo_a, zo_b = zo_terms[ok][:half].mean(0), zo_terms[ok][half:].mean(0)

    # Descent along each unit direction: J(theta - h u) for the steps of LINE_STEPS (population program).
    dirs = {**estimates, "zeroth-order": g_zo}
    line = [(name, h) for name in dirs for h in LINE_STEPS]
    J_line = []
    if pop is not None:
        pts = [np.asarray(flat0) - h * dirs[name] / max(np.linalg.norm(dirs[name]), 1e-30) for name, h in line]
        J_line = evaluate(pop, P, unravel, np.stack(pts), np.asarray(flat0), scen_all).tolist()
    result = {
        "device": provenance.device_label(),
        "parameters": D,
        "pushes": N,
        "batch": tc.batch,
        "directions": M,
        "sigma": sigma,
        "estimator_program": "window" if step.windowed else "whole horizon",
        "window_s": tc.window_s,
        "horizon_s": tc.horizon,
        "objective": float(J0),
        "zeroth_order": {
            "norm": float(np.linalg.norm(g_zo)),
            "halves_cosine": cosine(zo_a, zo_b),
            "finite_directions": int(ok.sum()),
            # E cos(grad, g_ZO) for the exact gradient of a smooth loss, M Gaussian directions
            "exact_gradient_cosine": float(1 / np.sqrt(1 + (D + 1) / max(int(ok.sum()), 1))),
            "source": "population program" if M > 0 else "antithetic pairs of the program",
        },
        "estimates": {},
        "timing": {
            "grad_compile_s": round(compile_s, 1),
            "population_s": round(pop_s, 1),
            "total_s": round(time.perf_counter() - t_start, 1),
        },
    }
    fo_rows = np.concatenate(g_fo)
    for name, g in dirs.items():
        entry = {"norm": float(np.linalg.norm(g)), "cosine_zeroth_order": cosine(g, g_zo)}
        if directional is not None and name != "zeroth-order":  # the estimate's e_m . g against the measured ones
            pred, good = e @ g, np.isfinite(directional)
            if np.all(np.isfinite(pred)) and good.sum() > 2:
                entry["directional_correlation"] = float(np.corrcoef(pred[good], directional[good])[0, 1])
                entry["directional_slope"] = float(pred[good] @ directional[good] / max(pred[good] @ pred[good], 1e-30))
        if J_line:  # J(theta - h u) - J(theta), and what the zeroth-order gradient predicts: -h g_ZO . u
            u = g / max(np.linalg.norm(g), 1e-30)
            entry["descent"] = {f"{h:g}": float(J_line[line.index((name, h))] - J0) for h in LINE_STEPS}
            entry["predicted_by_zeroth_order"] = {f"{h:g}": float(-h * (g_zo @ u)) for h in LINE_STEPS}
        if name in per_batch_means:
            entry["batch_consistency"] = batch_consistency(per_batch_means[name])
        if name == "first-order":
            entry["snr"] = snr(fo_rows)
            entry["nonfinite_rollouts"] = int(np.sum(~np.all(np.isfinite(fo_rows), 1)))
        if name == "interpolated":
            entry["alpha_mean"] = float(np.mean(alphas))
        result["estimates"][name] = entry
    result["provenance"] = provenance.record(tc.input_files)
    io.atomic_write_json(out / "quality.json", result)
    return result
