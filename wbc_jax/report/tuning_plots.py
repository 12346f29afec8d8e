"""Figures of gain tuning: the held-out envelopes, the learning curves and the loss as a predictor
of survival (numpy/dicts in, PNG out)."""

from __future__ import annotations

import pathlib

import numpy as np

from wbc_jax.core import io

# The gain sets of a tuning comparison, in the order figures and tables show them.
SET_ORDER = ("default", "gradient", "cmaes", "random", "critical")


def _save(fig, path) -> None:
    fig.tight_layout()
    io.atomic_save_figure(pathlib.Path(path), fig)


def envelope_polar(summary: dict, path) -> None:
    """One polar plot: the LIP bound and each gain set's largest survived impulse per direction."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.5, 6.5))
    ax = fig.add_subplot(projection="polar")
    names = [n for n in SET_ORDER if n in summary] + [
        n for n in summary if n not in SET_ORDER and "grid_envelope" in summary.get(n, {})
    ]
    first = summary[names[0]]["grid_envelope"]
    az = sorted(first, key=float)
    theta = np.deg2rad(np.append([float(a) for a in az], float(az[0])))

    def closed(v):
        return np.append(v, v[0])

    ax.plot(theta, closed(np.array([first[a]["bound_impulse_ns"] for a in az])), "k--", label="LIP bound m ω d")
    for n in names:
        e = summary[n]["grid_envelope"]
        ax.plot(
            theta,
            closed(np.array([e[a]["impulse_ns"] for a in az])),
            ".-",
            label=f"{n} (median {summary[n]['envelope_fraction_median']:.2f})",
        )
    ax.set_title("largest survived trunk impulse [N s] (strict survival)")
    ax.legend(loc="lower left", fontsize=7, bbox_to_anchor=(-0.1, -0.12))
    _save(fig, path)


def learning_curves(histories: dict, path, budget: dict | None = None) -> None:
    """Loss of the current solution against simulated physics steps and against wall time, per
    method ({name: history rows with loss, sim_steps, wall_s}); ``budget`` {"sim_steps", "wall_s"}:
    the gradient run's, drawn as vertical lines."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 3.8))
    axes = fig.subplots(1, 2)
    for name, rows in histories.items():
        if not rows:
            continue
        loss = [float(r["loss"]) for r in rows]
        for ax, col in zip(axes, ("sim_steps", "wall_s"), strict=True):
            ax.plot([float(r[col]) for r in rows], loss, ".-", label=name)
    for ax, col in zip(axes, ("sim_steps", "wall_s"), strict=True):
        if budget:
            ax.axvline(float(budget[col]), color="gray", ls=":", lw=1, label="gradient's budget")
    for ax, label in zip(axes, ("simulated physics steps", "wall time [s] (compilation included)"), strict=True):
        ax.set_xlabel(label)
        ax.set_ylabel("loss of the current solution (its batch)")
        ax.set_yscale("log")
        ax.legend(fontsize=8)
    _save(fig, path)


def survival_vs_loss(loss, survived, stats: dict, path) -> None:
    """Per held-out push: strict survival (jittered 0/1) against the loss, and the survival rate in
    loss quantile bins."""
    from matplotlib.figure import Figure

    loss, survived = np.asarray(loss, float), np.asarray(survived, bool)
    fig = Figure(figsize=(6.5, 4))
    ax = fig.subplots()
    jitter = np.random.default_rng(0).uniform(-0.05, 0.05, loss.size)
    ax.scatter(loss, survived + jitter, s=12, c=np.where(survived, "C2", "C3"), alpha=0.7)
    edges = np.unique(np.quantile(loss, np.linspace(0, 1, min(9, max(2, loss.size // 6)))))
    if edges.size > 2:
        idx = np.clip(np.digitize(loss, edges[1:-1]), 0, edges.size - 2)
        centres = [np.median(loss[idx == i]) for i in range(edges.size - 1) if np.any(idx == i)]
        rates = [survived[idx == i].mean() for i in range(edges.size - 1) if np.any(idx == i)]
        ax.plot(centres, rates, "k-o", label="survival rate per loss bin")
        ax.legend(fontsize=8)
    ax.set_xscale("log")
    ax.set_xlabel(f"loss over the training horizon ({stats.get('train_horizon_s')} s)")
    ax.set_ylabel(f"strictly survived at {stats.get('horizon_s')} s")
    ax.set_title(
        f"held-out pushes: Spearman {stats.get('spearman_train_horizon', float('nan')):.2f}, "
        f"ROC area {stats.get('auc_train_horizon', float('nan')):.2f} (n = {loss.size})"
    )
    _save(fig, path)


def race_curves(points: dict, path, reference: dict | None = None) -> None:
    """The race: held-out envelope / LIP bound (median solid, min dashed) of each method's gain set at
    each budget, against wall time and against simulated physics steps ({method: [{wall_s, sim_steps,
    budget_s, envelope_fraction_median, envelope_fraction_min}, ...]}); ``reference`` rows
    ({name: {...}}, e.g. the default and hand-set gains) as horizontal lines."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 3.8))
    axes = fig.subplots(1, 2)
    for i, (method, pts) in enumerate(points.items()):
        if not pts:
            continue
        for ax, col in zip(axes, ("budget_s", "sim_steps"), strict=True):
            x = [float(p[col]) for p in pts]
            ax.plot(x, [p["envelope_fraction_median"] for p in pts], "o-", color=f"C{i}", label=f"{method} median")
            ax.plot(
                x, [p["envelope_fraction_min"] for p in pts], "x--", color=f"C{i}", alpha=0.6, label=f"{method} min"
            )
    for ax in axes:
        for name, r in (reference or {}).items():
            ax.axhline(r["envelope_fraction_median"], color="gray", ls=":", lw=1)
            ax.annotate(
                f"{name} median",
                (0.01, r["envelope_fraction_median"]),
                xycoords=("axes fraction", "data"),
                fontsize=7,
                color="gray",
            )
        ax.set_ylabel("held-out envelope / LIP bound")
        ax.legend(fontsize=7)
    axes[0].set_xlabel("wall-time budget [s] (compilation included)")
    axes[1].set_xlabel("simulated physics steps")
    axes[1].set_xscale("symlog", linthresh=1e5)  # a set held at the start has 0 simulated steps
    axes[1].set_xlim(left=0)  # no negative decades
    _save(fig, path)
