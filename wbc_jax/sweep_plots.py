"""Plots of push sweeps: survival map and recovery envelope against the LIP bound."""

from __future__ import annotations

import pathlib

# Figure objects render without pyplot: no global backend switch, so importing this module
# inside Jupyter leaves the inline backend alone.
import numpy as np
from matplotlib.figure import Figure


def survival_map(table, path: pathlib.Path) -> None:
    """Survival rate over push magnitude x direction (mean over the other sweep axes)."""
    pivot = table.pivot_table(index="magnitude_n", columns="azimuth_deg", values="survived", aggfunc="mean")
    fig = Figure(figsize=(8, 5))
    ax = fig.subplots()
    im = ax.imshow(pivot.values, origin="lower", aspect="auto", cmap="RdYlGn", vmin=0, vmax=1)
    ax.set_xticks(range(len(pivot.columns)), [f"{c:g}" for c in pivot.columns], rotation=90 if len(pivot.columns) > 16 else 0, fontsize=7)
    ax.set_yticks(range(len(pivot.index)), [f"{m:g}" for m in pivot.index], fontsize=7)
    ax.set_xlabel("push azimuth [deg] (0 = forward, 90 = left)")
    ax.set_ylabel("push force [N]")
    fig.colorbar(im, label="survival rate")
    ax.set_title("push recovery: survival")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def envelope(table, env: dict, path: pathlib.Path) -> None:
    """Polar plot: largest survived impulse per direction vs the LIP feet-in-place bound."""
    az = np.array(sorted(env))
    best = np.array([env[a]["largest_survived_impulse_ns"] for a in az])
    bound = np.array([env[a]["bound_impulse_ns"] for a in az])
    theta = np.deg2rad(np.append(az, az[0]))
    fig = Figure(figsize=(6, 6))
    ax = fig.add_subplot(projection="polar")
    ax.plot(theta, np.append(bound, bound[0]), "k--", label="LIP bound m ω d")
    ax.plot(theta, np.append(best, best[0]), "o-", label="largest survived impulse")
    ax.set_title("recovery envelope [N s] (default gains)")
    ax.legend(loc="lower left", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
