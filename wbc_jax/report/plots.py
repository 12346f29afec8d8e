"""Matplotlib figures of rollouts (host side, numpy in, PNG out)."""

from __future__ import annotations

import pathlib

# Figure objects render without pyplot: no global backend switch, so importing this module
# inside Jupyter leaves the inline backend alone.
import numpy as np
from matplotlib.figure import Figure

from wbc_jax.core import io


def com_tracking(traj: dict, path: pathlib.Path, title: str = "") -> None:
    """CoM vs reference, per axis, and the tracking error."""
    t = traj["t"]
    fig = Figure(figsize=(8, 8))
    axes = fig.subplots(4, 1, sharex=True)
    for k, name in enumerate("xyz"):
        axes[k].plot(t, traj["com_ref"][:, k], "k--", lw=1, label="reference")
        axes[k].plot(t, traj["com"][:, k], lw=1.2, label="CoM")
        axes[k].set_ylabel(f"{name} [m]")
    axes[0].legend(loc="upper right")
    err = np.linalg.norm(traj["com"] - traj["com_ref"], axis=1)
    axes[3].plot(t, 1e3 * err, color="tab:red")
    axes[3].set_ylabel("|error| [mm]")
    axes[3].set_xlabel("time [s]")
    fig.suptitle(title or "CoM tracking")
    fig.tight_layout()
    io.atomic_save_figure(path, fig)


def contact_forces(traj: dict, names: list[str], dims: list[int], path: pathlib.Path, title: str = "") -> None:
    """Commanded vs measured (simulator) force of each contact, world axes (one row per contact)."""
    t = traj["t"]
    fig = Figure(figsize=(10, 2.3 * len(names) + 1))
    axes = np.atleast_2d(fig.subplots(len(names), 3, sharex=True))
    start = 0
    for k, (name, dim) in enumerate(zip(names, dims, strict=True)):
        for c, comp in enumerate(("f_x", "f_y", "f_z")):
            ax = axes[k, c]
            ax.plot(t, traj["f_cmd"][:, start + c], "k--", lw=1, label="commanded")
            ax.plot(t, traj["f_meas"][:, start + c], lw=1, label="simulator")
            ax.set_ylabel(f"{name} {comp} [N]", fontsize=8)
        start += dim
    for c in range(3):
        axes[-1, c].set_xlabel("time [s]")
    axes[0, 0].legend(loc="upper right", fontsize=7)
    fig.suptitle(title or "contact forces")
    fig.tight_layout()
    io.atomic_save_figure(path, fig)


def joint_torques(traj: dict, joints: list[str], path: pathlib.Path, title: str = "") -> None:
    """Joint torques, grouped by limb."""
    t = traj["t"]
    groups = {"torso": (0, 3), "left arm": (3, 7), "right arm": (7, 11), "left leg": (11, 17), "right leg": (17, 23)}
    fig = Figure(figsize=(8, 10))
    axes = fig.subplots(len(groups), 1, sharex=True)
    for ax, (name, (a, b)) in zip(axes, groups.items()):
        for j in range(a, min(b, traj["tau"].shape[1])):
            ax.plot(t, traj["tau"][:, j], lw=1, label=joints[j])
        ax.set_ylabel(f"{name} [N m]")
        ax.legend(fontsize=6, ncol=3, loc="upper right")
    axes[-1].set_xlabel("time [s]")
    fig.suptitle(title or "joint torques")
    fig.tight_layout()
    io.atomic_save_figure(path, fig)
