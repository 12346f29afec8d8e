"""The results of a push sweep: the feet-in-place LIP bound per direction, each direction's
envelope (largest surviving impulse) and the summary of a results table."""

from __future__ import annotations

import math

from wbc_jax.core import constants
from wbc_jax.jobs.sweep_config import SUPPORTS, SweepConfig
from wbc_jax.robot import bounds
from wbc_jax.robot import model as model_lib


def lip_bound(robot: model_lib.Robot, directions_deg, support: str = "two-feet", elevation_deg: float = 0.0) -> dict:
    """Feet-in-place bound per direction: the LIP with the CoP at the support-polygon edge
    survives a horizontal CoM velocity up to omega d (omega = sqrt(g / z_CoM)); as a horizontal
    impulse: m omega d. A push at ``elevation_deg`` has the horizontal part cos(elevation) of its
    impulse: its bound is m omega d / cos(elevation), none (None) for a vertical push.

    support: "two-feet" (home posture, CoM between the feet) or "left-foot" (the single-support
    phase of the one-foot task: the left sole's contact points, CoM over the left sole)."""
    if support not in SUPPORTS:
        raise ValueError(f"unknown support {support!r}; valid: {list(SUPPORTS)}")
    pts, com, d = bounds.standing_support(robot, support)
    if support == "left-foot":  # references.make_schedule("one-foot"): CoM y over the left sole
        com[1] = d.site_xpos[robot.index.foot_sites[0], 1]
    omega = math.sqrt(constants.GRAVITY / com[2])
    horizontal = math.cos(math.radians(elevation_deg))
    out = {}
    for az in directions_deg:
        dist = bounds.ray_distance(pts, com[:2], az)
        bound = None if abs(elevation_deg) >= 90.0 else robot.index.mass * omega * dist / horizontal
        out[float(az)] = {"edge_distance_m": dist, "velocity_bound_mps": omega * dist, "impulse_bound_ns": bound}
    return out


def fraction(impulse: float, bound: float | None) -> float | None:
    """``impulse`` as a fraction of its LIP bound (None where there is none: vertical pushes)."""
    return None if bound is None else impulse / bound


def envelope_of(group, survived: str = "survived") -> tuple[float, float, int]:
    """(largest survived impulse, largest impulse below the first failure, survival islands above
    it) of one direction's rows."""
    alive = group[group[survived]]
    best = float(alive["impulse_ns"].max()) if len(alive) else 0.0
    by_mag = group.groupby("magnitude_n")[survived].mean().sort_index()
    failed = by_mag[by_mag < 1.0]
    islands = int((by_mag[by_mag.index > failed.index.min()] > 0).sum()) if len(failed) else 0
    # Islands: outcomes near the fall boundary that flip with float32/float64 or the solver's
    # iterations (experiments/checks/island_check.py); the monotone envelope excludes them.
    below = group[group["magnitude_n"] < failed.index.min()] if len(failed) else group
    monotone = float(below["impulse_ns"].max()) if len(below) else 0.0
    return best, monotone, islands


def summarize_table(table, cfg: SweepConfig, robot: model_lib.Robot) -> dict:
    """Survival rate (strict, and the lax ``upright`` count), envelope (largest survived impulse
    per direction) and its feet-in-place LIP bound."""
    support = "left-foot" if cfg.task == "one-foot" else "two-feet"
    bound = lip_bound(robot, sorted(set(table["azimuth_deg"])), support, cfg.elevation)
    envelope = {}
    default = table[table["gain_set"] == 0]
    for az, group in default.groupby("azimuth_deg"):
        best, monotone, islands = envelope_of(group)
        best_upright, _, _ = envelope_of(group, "upright")
        b = bound[float(az)]["impulse_bound_ns"]
        envelope[float(az)] = {
            "largest_survived_impulse_ns": best,
            "bound_impulse_ns": b,
            "fraction_of_bound": fraction(best, b),
            "survival_islands": islands,
            "monotone_impulse_ns": monotone,
            "fraction_of_bound_monotone": fraction(monotone, b),
            "largest_upright_impulse_ns": best_upright,
        }
    return {
        "support": support,
        "n_envs": int(len(table)),
        "survival_rate": float(table["survived"].mean()),
        "upright_rate": float(table["upright"].mean()),
        "nan_envs": int(table["nan"].sum()),
        "qp_infeasible_envs": int((table["qp_infeasible_ticks"] > 0).sum()),
        "envelope": envelope,
    }


# ---------------------------------------------------------------------------------------------
# Replays of one environment
