"""Gradient estimators of the tuning loss from a batch of per-rollout values and gradients.

A gradient step evaluates B rollouts, each at its own parameters ``theta_i`` (B, D), and returns each
rollout's objective ``v_i`` and reverse-mode gradient ``g_i``. The estimators (``--estimator``):

* ``first-order``: theta_i = theta; the robust mean of the g_i (:func:`robust_mean_gradient`: rollouts
  with a non-finite gradient left out, each clipped to ``env_clip`` x the median norm).
* ``smoothed``: antithetic pairs theta_{2j, 2j+1} = theta +- sigma eps_j on the same push; the robust
  mean of the g_i estimates the gradient of the Gaussian-smoothed loss E[L(theta + sigma eps)]
  (randomized smoothing: contact makes L piecewise smooth, its smoothed version is smooth).
* ``interpolated`` (the alpha-order estimator of Suh, Simchowitz, Zhang and Tedrake, ICML 2022): the
  same pairs give a zeroth-order estimate of the same smoothed gradient, z_j = (v_{2j} - v_{2j+1}) /
  (2 sigma) eps_j, unbiased but noisy; the first-order mean is low-variance but biased where contact
  makes the loss stiff or discontinuous. The step takes alpha g_FO + (1 - alpha) g_ZO with
  alpha = var_ZO / (var_FO + var_ZO) (the variance-minimising mix of two unbiased estimates, variances
  of the means), cut to alpha <= gamma / |g_FO - g_ZO| where the two means differ by more than
  gamma = ``bias_factor`` x the standard error of their difference (the first-order estimate is then
  biased beyond noise, and the mix stays within gamma of the unbiased one).

Shapes: B rollouts, n = B / 2 pairs, D parameters. Elementwise products and sums only (no matrix
products, which run in reduced precision on some GPUs).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree


def rows(tree) -> jax.Array:
    """(B, D) the leaves of a batched pytree (leading axis B), flattened in ravel_pytree's order."""
    leaves = jax.tree_util.tree_leaves(tree)
    B = leaves[0].shape[0]
    return jnp.concatenate([jnp.reshape(x, (B, -1)) for x in leaves], axis=1)


def robust_mean_gradient(grads, clip_factor: float):
    """The batch mean of per-rollout gradients, robust to rollouts that diverge.

    grads: a pytree whose leaves have a leading batch axis B (one gradient per rollout). A rollout
    whose gradient has a non-finite entry is left out; with ``clip_factor`` > 0 each remaining
    gradient is scaled down to at most ``clip_factor`` x the median norm of the remaining ones
    (a falling robot's gradient can be 1e14 times a standing one's and would otherwise set the
    direction of the whole batch's step).

    Returns (mean gradient (the leaves without the batch axis; NaN if no rollout is finite, so
    that the optimiser's guard skips the step), stats {"nonfinite_envs": (), "clipped_envs": (),
    "env_grad_norm_median": ()})."""
    mean, stats, _ = robust_rows(rows(grads), clip_factor)
    unravel = ravel_pytree(jax.tree_util.tree_map(lambda x: x[0], grads))[1]
    return unravel(mean), stats


def robust_rows(flat: jax.Array, clip_factor: float):
    """(mean (D,), stats, clipped finite rows (B, D) with zeros for the non-finite ones, finite (B,))."""
    B = flat.shape[0]
    finite = jnp.all(jnp.isfinite(flat), axis=1)  # (B,)
    safe = jnp.where(finite[:, None], flat, 0.0)
    norms = jnp.sqrt(jnp.sum(safe**2, axis=1))
    n_ok = jnp.sum(finite)
    median = jnp.nanmedian(jnp.where(finite, norms, jnp.nan))
    if clip_factor > 0:
        cap = clip_factor * median
        clipped = finite & (norms > cap)
        scale = jnp.where(clipped, cap / jnp.where(norms > 0, norms, 1.0), 1.0)
    else:
        clipped = jnp.zeros_like(finite)
        scale = jnp.ones_like(norms)
    kept = safe * scale[:, None].astype(flat.dtype)
    nan_if_none = jnp.where(n_ok > 0, 1.0, jnp.nan)
    mean = jnp.sum(kept, axis=0) / jnp.maximum(n_ok, 1) * nan_if_none
    stats = {"nonfinite_envs": B - n_ok, "clipped_envs": jnp.sum(clipped), "env_grad_norm_median": median}
    return mean, stats, (kept, finite)


def antithetic(params, key, n_pairs: int, sigma: float):
    """Per-rollout parameters of antithetic pairs: (params_b {group: (2 n, ...)} with rows 2j, 2j + 1 =
    params +- sigma eps_j, eps (n, D) standard normal)."""
    flat, unravel = ravel_pytree(params)
    eps = jax.random.normal(key, (n_pairs, flat.size), flat.dtype)
    signed = jnp.stack([eps, -eps], axis=1).reshape(2 * n_pairs, flat.size)
    return jax.vmap(unravel)(flat[None] + sigma * signed), eps


def repeated(params, n: int):
    """Per-rollout parameters all equal to ``params``: {group: (n, ...)}."""
    return jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (n, *jnp.shape(x))), params)


def zeroth_order_rows(values: jax.Array, eps: jax.Array, sigma: float):
    """(per-pair estimates (n, D), finite (n,)) of the smoothed gradient from antithetic values (2 n,)."""
    plus, minus = values[0::2], values[1::2]
    diff = (plus - minus) / (2.0 * sigma)
    finite = jnp.isfinite(diff)
    return jnp.where(finite, diff, 0.0)[:, None] * eps, finite


def _mean_var(x: jax.Array, ok: jax.Array):
    """Mean (D,) of the rows ``ok`` of x (n, D) and the variance of that mean (sum over entries)."""
    n = jnp.maximum(jnp.sum(ok), 1)
    mean = jnp.sum(jnp.where(ok[:, None], x, 0.0), axis=0) / n
    dev = jnp.where(ok[:, None], x - mean, 0.0)
    var = jnp.sum(dev**2) / jnp.maximum(n - 1, 1) / n
    return mean, var


def interpolate(fo_rows: jax.Array, fo_ok: jax.Array, zo_rows: jax.Array, zo_ok: jax.Array, bias_factor: float):
    """The alpha-order mix (module docstring): (gradient (D,), stats {alpha, fo_var, zo_var, bias_norm})."""
    g1, v1 = _mean_var(fo_rows, fo_ok)
    g0, v0 = _mean_var(zo_rows, zo_ok)
    alpha = v0 / jnp.maximum(v0 + v1, 1e-30)
    bias = jnp.sqrt(jnp.sum((g1 - g0) ** 2))
    gamma = bias_factor * jnp.sqrt(v0 + v1)
    alpha = jnp.where(bias > gamma, jnp.minimum(alpha, gamma / jnp.maximum(bias, 1e-30)), alpha)
    alpha = jnp.where(jnp.any(fo_ok), alpha, 0.0)
    return alpha * g1 + (1.0 - alpha) * g0, {"alpha": alpha, "fo_var": v1, "zo_var": v0, "bias_norm": bias}


def combine(kind: str, values: jax.Array, grads, eps, *, sigma: float, clip_factor: float, bias_factor: float):
    """The step's gradient (a pytree like one row of ``grads``) and its stats, by estimator ``kind``."""
    unravel = ravel_pytree(jax.tree_util.tree_map(lambda x: x[0], grads))[1]
    mean, stats, (kept, finite) = robust_rows(rows(grads), clip_factor)
    stats = {
        **stats,
        "alpha": jnp.ones(()),
        "fo_var": jnp.zeros(()),
        "zo_var": jnp.zeros(()),
        "bias_norm": jnp.zeros(()),
    }
    if kind == "interpolated":
        zo, zo_ok = zeroth_order_rows(values, eps, sigma)
        mean, mix = interpolate(kept, finite, zo, zo_ok, bias_factor)
        mean = jnp.where(jnp.any(finite) | jnp.any(zo_ok), mean, jnp.nan)
        stats.update(mix)
    elif kind not in ("first-order", "smoothed"):
        raise ValueError(f"unknown estimator {kind!r}; valid: first-order, smoothed, interpolated")
    return unravel(mean), stats


ESTIMATOR_STATS = ("nonfinite_envs", "clipped_envs", "env_grad_norm_median", "alpha", "fo_var", "zo_var", "bias_norm")
