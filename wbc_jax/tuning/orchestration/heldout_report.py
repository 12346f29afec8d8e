"""heldout.json: the held-out evaluation's summary per gain set (:mod:`wbc_jax.tuning.orchestration.heldout`'s
results with the tuning runs' budgets), the issue's targets and the provenance."""

from __future__ import annotations

import pathlib

from wbc_jax.core import constants, io, provenance


def targets(summary: dict) -> dict:
    """The issue's targets for the gradient-tuned set against the default and the best hand-set row
    (``critical``), from a heldout.json-like summary {name: {...}}."""
    g, d = summary.get("gradient"), summary.get("default")
    if g is None or d is None:
        return {}
    gd, dd = g["grid_envelope"], d["grid_envelope"]
    below = [a for a in gd if gd[a]["fraction"] < dd[a]["fraction"] - 1e-9]
    out = {
        "median_fraction_ge_0.8": g["envelope_fraction_median"] >= 0.8,
        "min_fraction_ge_0.6": g["envelope_fraction_min"] >= 0.6,
        "no_direction_below_default": not below,
        "directions_below_default": below,
        "survival_ge_1.5x_default": g["survival_rate"] >= 1.5 * d["survival_rate"],
        "sinusoid_rmse_le_1.5mm": (
            g.get("sinusoid_com_rmse_m") is not None and g["sinusoid_com_rmse_m"] <= constants.SINUSOID_MAX_COM_RMSE_M
        ),
    }
    hand = [n for n in ("critical",) if n in summary]
    if hand:
        best = max(hand, key=lambda n: summary[n]["survival_rate"])
        out["survival_above_best_hand_set"] = g["survival_rate"] > summary[best]["survival_rate"]
    if "cmaes" in summary:
        out["envelope_median_ge_cmaes"] = g["envelope_fraction_median"] >= summary["cmaes"]["envelope_fraction_median"]
    return out


def write_heldout(path, results: dict, budgets: dict, *, extra: dict | None = None, inputs: dict | None = None) -> dict:
    """heldout.json: one object per gain set (envelope_fraction_median/_min, survival_rate,
    sinusoid_com_rmse_m, sim_steps, wall_s, device, the per-direction envelope, the unseen
    variations and the one-foot task), the targets, the survival criterion used and the provenance
    (``inputs``: {name: file} of the gain sets and other input files).
    ``budgets``: {name: {"sim_steps", "wall_s"}} of the tuning runs (0 for hand-set rows)."""
    device = provenance.device_label()
    summary = {}
    for name, r in results.items():
        if name.startswith("_"):
            continue
        grid = r["grid"]
        summary[name] = {
            "envelope_fraction_median": grid["envelope_fraction_median"],
            "envelope_fraction_min": grid["envelope_fraction_min"],
            "survival_rate": grid["survival_rate"],
            "sinusoid_com_rmse_m": r.get("sinusoid_com_rmse_m"),
            "sim_steps": int(budgets.get(name, {}).get("sim_steps", 0)),
            "wall_s": float(budgets.get(name, {}).get("wall_s", 0.0)),
            "device": device,
            "effort_peak_torque_nm_median": grid["peak_torque_nm_median"],
            "upright_rate": grid["upright_rate"],
            "envelope_fraction_monotone_median": grid["envelope_fraction_monotone_median"],
            "envelope_fraction_monotone_min": grid["envelope_fraction_monotone_min"],
            "grid_envelope": grid["envelope"],
            "unseen": {
                v: {k: e[k] for k in ("survival_rate", "envelope_fraction_median", "envelope_fraction_min")}
                for v, e in {**r["variations"], **({"one_foot": r["one_foot"]} if "one_foot" in r else {})}.items()
            },
        }
    report = {
        **summary,
        "targets": targets(summary),
        "survival_criterion": dict(constants.SURVIVAL_CRITERION),
        "timing": results.get("_timing", {}),
        **(extra or {}),
        "provenance": provenance.record(inputs),
    }
    io.atomic_write_json(pathlib.Path(path), report)
    return report


SUMMARY_KEYS = (
    "envelope_fraction_median",
    "envelope_fraction_min",
    "survival_rate",
    "sinusoid_com_rmse_m",
    "sim_steps",
    "wall_s",
)
