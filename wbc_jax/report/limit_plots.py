"""Plots of the physical limit of push recovery (``wbc-jax limit``): the limit per direction
against the LIP and flywheel bounds and the controllers' strict envelopes."""

from __future__ import annotations

import pathlib

import numpy as np
from matplotlib.figure import Figure

from wbc_jax.core import io


def _closed(az: np.ndarray, values) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(values, float)
    return np.deg2rad(np.append(az, az[0])), np.append(v, v[0])


def _panel(ax, directions: dict, title: str) -> None:
    """One polar panel of a {azimuth: row} table (rows of ``limit_rounds.summarize``; a row's
    ``limit_ns`` may be None: not measured)."""
    az = np.array(sorted(float(a) for a in directions))
    rows = [directions[a] if a in directions else directions[str(a)] for a in az]
    ax.plot(*_closed(az, [r["lip_bound_ns"] for r in rows]), "k--", label="LIP bound m ω d")
    if all(r.get("flywheel_bound_ns") is not None for r in rows):
        ax.plot(*_closed(az, [r["flywheel_bound_ns"] for r in rows]), "k:", label="LIP + flywheel bound")
    if all(r.get("limit_ns") is not None for r in rows):
        ax.plot(*_closed(az, [r["limit_ns"] for r in rows]), "o-", lw=2, label="physical limit (trajectory opt.)")
        by_ddp = [(r.get("found_by") or "").startswith("crocoddyl") for r in rows]
        if any(by_ddp):
            ax.plot(
                np.deg2rad(az[by_ddp]),
                [r["limit_ns"] for r, d in zip(rows, by_ddp, strict=True) if d],
                "r*",
                ms=10,
                label="limit found by crocoddyl",
            )
    labels = sorted({k for r in rows for k in r.get("envelopes", {})})
    for label in labels:
        ax.plot(*_closed(az, [r["envelopes"][label]["impulse_ns"] for r in rows]), ".-", label=label)
    ax.set_title(title, fontsize=10)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.06), ncol=2, fontsize=8)


def polar(summary: dict, path: pathlib.Path) -> None:
    """Polar plot of one search's summary: limit, LIP bound and envelopes [N s] per direction."""
    fig = Figure(figsize=(6, 7.5))
    ax = fig.add_subplot(projection="polar")
    _panel(ax, summary["directions"], f"push recovery limit, {summary['config']['body']} [N s]")
    fig.tight_layout()
    io.atomic_save_figure(path, fig)


def bodies_figure(tables: dict) -> Figure:
    """One polar panel per pushed body: ``tables`` {body: {azimuth: row}} (limit.json's directions)."""
    fig = Figure(figsize=(6 * len(tables), 7.5))
    for i, (body, directions) in enumerate(tables.items()):
        _panel(fig.add_subplot(1, len(tables), i + 1, projection="polar"), directions, f"{body} push [N s]")
    fig.tight_layout()
    return fig


def polar_bodies(tables: dict, path: pathlib.Path) -> None:
    """:func:`bodies_figure` saved to ``path``."""
    io.atomic_save_figure(path, bodies_figure(tables))
