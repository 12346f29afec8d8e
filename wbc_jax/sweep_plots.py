"""Plots of push sweeps: survival map and recovery envelope against the LIP bound."""

from __future__ import annotations

import pathlib

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def survival_map(table, path: pathlib.Path) -> None:
    """Survival rate over push magnitude x direction (mean over the other sweep axes)."""
    pivot = table.pivot_table(index="magnitude_n", columns="azimuth_deg", values="survived", aggfunc="mean")
    fig, ax = plt.subplots(figsize=(8, 5))
    im = ax.imshow(pivot.values, origin="lower", aspect="auto", cmap="RdYlGn", vmin=0, vmax=1)
    ax.set_xticks(range(len(pivot.columns)), [f"{c:g}" for c in pivot.columns], rotation=90 if len(pivot.columns) > 16 else 0, fontsize=7)
    ax.set_yticks(range(len(pivot.index)), [f"{m:g}" for m in pivot.index], fontsize=7)
    ax.set_xlabel("push azimuth [deg] (0 = forward, 90 = left)")
    ax.set_ylabel("push force [N]")
    fig.colorbar(im, label="survival rate")
    ax.set_title("push recovery: survival")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def envelope(table, env: dict, path: pathlib.Path) -> None:
    """Polar plot: largest survived impulse per direction vs the LIP feet-in-place bound."""
    az = np.array(sorted(env))
    best = np.array([env[a]["largest_survived_impulse_ns"] for a in az])
    bound = np.array([env[a]["bound_impulse_ns"] for a in az])
    theta = np.deg2rad(np.append(az, az[0]))
    fig = plt.figure(figsize=(6, 6))
    ax = fig.add_subplot(projection="polar")
    ax.plot(theta, np.append(bound, bound[0]), "k--", label="LIP bound m ω d")
    ax.plot(theta, np.append(best, best[0]), "o-", label="largest survived impulse")
    ax.set_title("recovery envelope [N s] (default gains)")
    ax.legend(loc="lower left", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
