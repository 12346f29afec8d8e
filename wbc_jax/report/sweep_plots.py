"""Plots of push sweeps: survival map and recovery envelope against the LIP bound."""

from __future__ import annotations

import pathlib

# Figure objects render without pyplot: no global backend switch, so importing this module
# inside Jupyter leaves the inline backend alone.
import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from wbc_jax.core import io


def _tick_positions(values: np.ndarray, max_labels: int = 10) -> tuple[np.ndarray, list[str]]:
    """Positions (in cell units) and round labels for at most ``max_labels`` ticks on an axis
    whose cells hold the sorted ``values`` (linear interpolation between cells)."""
    values = np.asarray(values, float)
    if len(values) <= max_labels:
        return np.arange(len(values)), [f"{v:g}" for v in values]
    ticks = MaxNLocator(nbins=max_labels, steps=[1, 2, 2.5, 5, 10]).tick_values(values[0], values[-1])
    ticks = ticks[(ticks >= values[0]) & (ticks <= values[-1])]
    return np.interp(ticks, values, np.arange(len(values))), [f"{t:g}" for t in ticks]


def survival_map(table, path: pathlib.Path, envelope: dict | None = None, survived: str = "survived") -> None:
    """Survival rate over push magnitude x direction (mean over the other sweep axes), with the
    feet-in-place LIP bound (as a force for the sweep's push duration) drawn over it."""
    pivot = table.pivot_table(index="magnitude_n", columns="azimuth_deg", values=survived, aggfunc="mean")
    fig = Figure(figsize=(8, 5))
    ax = fig.subplots()
    im = ax.imshow(pivot.values, origin="lower", aspect="auto", cmap="RdYlGn", vmin=0, vmax=1)
    x, xl = _tick_positions(pivot.columns.to_numpy(), 12)
    y, yl = _tick_positions(pivot.index.to_numpy(), 10)
    ax.set_xticks(x, xl, fontsize=8)
    ax.set_yticks(y, yl, fontsize=8)
    if envelope and len(pivot.index) > 1:
        duration = float(np.median(table["impulse_ns"] / np.maximum(table["magnitude_n"], 1e-12)))
        az = pivot.columns.to_numpy()
        bound_force = np.array([envelope[float(a)]["bound_impulse_ns"] / duration for a in az])
        rows = np.interp(bound_force, pivot.index.to_numpy(), np.arange(len(pivot.index)), right=np.nan)
        ax.plot(np.arange(len(az)), rows, "k--", lw=1.5, label="LIP bound m ω d / push duration")
        ax.legend(loc="upper right", fontsize=8)
    ax.set_xlabel("push azimuth [deg] (0 = forward, 90 = left)")
    ax.set_ylabel("push force [N]")
    fig.colorbar(im, label=f"{survived} rate")
    ax.set_title(f"push recovery: {survived}")
    fig.tight_layout()
    io.atomic_save_figure(path, fig)


def envelope(table, env: dict, path: pathlib.Path, others: dict | None = None) -> None:
    """Polar plot: largest survived impulse per direction vs the LIP feet-in-place bound;
    ``others``: more envelopes to overlay, {label: {azimuth: impulse}}."""
    az = np.array(sorted(env))
    best = np.array([env[a]["largest_survived_impulse_ns"] for a in az])
    bound = np.array([env[a]["bound_impulse_ns"] for a in az])
    theta = np.deg2rad(np.append(az, az[0]))
    fig = Figure(figsize=(6, 6))
    ax = fig.add_subplot(projection="polar")
    ax.plot(theta, np.append(bound, bound[0]), "k--", label="LIP bound m ω d")
    ax.plot(theta, np.append(best, best[0]), "o-", label="largest survived impulse")
    for label, values in (others or {}).items():
        v = np.array([values[a] for a in az])
        ax.plot(theta, np.append(v, v[0]), ".-", label=label)
    ax.set_title("recovery envelope [N s]")
    ax.legend(loc="lower left", fontsize=8)
    fig.tight_layout()
    io.atomic_save_figure(path, fig)
