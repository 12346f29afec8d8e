"""The race (issue 35): every method's held-out envelope at equal wall-time budgets; race.json, race.png.

A ``wbc-jax tune --budget-s T --snapshots-s t1 t2 ...`` run keeps each method's gain set at t1, t2, ...
and T (seconds of wall time on its fastest engine, compilation included); after the held-out phase this
reads them back with their simulated steps and writes:

* race.json: per method, per budget: the held-out envelope / LIP bound (median, min), grid survival,
  the 20 s sinusoid's CoM RMSE, simulated steps and wall time; the gradient's throughput; the verdict
  per budget for each gradient-based method (the gradient, and the hybrid: the gradient refining
  CMA-ES's set at half the budget, :mod:`wbc_jax.tuning.algorithms.hybrid`): its median minus CMA-ES's, its min
  against CMA-ES's, the sinusoid bound, and whether the issue's target is met (median >= CMA-ES +
  0.05, min >= CMA-ES's, sinusoid <= 1.5 mm; ``target_met``: by either method); and the set a user is
  told to pick (the best held-out median among the sets that keep the sinusoid within 1.5 mm);
* race.png: the held-out envelope against wall time and against simulated steps, every method.
"""

from __future__ import annotations

import json
import pathlib

from wbc_jax.core import constants, io, provenance
from wbc_jax.tuning.algorithms import problem as tp

METHODS = ("gradient", "cmaes", "random", "hybrid")
GRADIENT_BASED = ("gradient", "hybrid")  # the methods the verdict sets against CMA-ES
# A hybrid row's parts: its CMA-ES parent and the gradient's half (wbc_jax/tuning/algorithms/hybrid.py).
HYBRID_KEYS = (
    "parent",
    "parent_sha256",
    "parent_sim_steps",
    "parent_wall_s",
    "gradient_sim_steps",
    "gradient_wall_s",
    "gradient_compile_s",
)
MARGIN = 0.05  # the median the gradient must gain over CMA-ES (issue 35)


def budgets(tc) -> list:
    """The race's budgets [s] (a :class:`~wbc_jax.tuning.config.TuneConfig`'s): the snapshots within
    ``--budget-s``, then ``--budget-s``."""
    return sorted({float(t) for t in tc.snapshots_s if t < tc.budget_s} | {float(tc.budget_s)})


def points(rep: dict, index: dict) -> dict:
    """{method: [{budget_s, name, wall_s, sim_steps, envelope medians, survival, sinusoid}, ...]} by budget."""
    out: dict = {}
    for name, origin in index.items():
        method = origin.get("method")
        if method not in METHODS or origin.get("budget_s") is None or name not in rep:
            continue
        r = rep[name]
        out.setdefault(method, []).append(
            {
                "budget_s": float(origin["budget_s"]),
                "name": name,
                "wall_s": float(origin["wall_s"]),
                "sim_steps": int(origin["sim_steps"]),
                "envelope_fraction_median": r["envelope_fraction_median"],
                "envelope_fraction_min": r["envelope_fraction_min"],
                "survival_rate": r["survival_rate"],
                "sinusoid_com_rmse_m": r.get("sinusoid_com_rmse_m"),
                **{k: origin[k] for k in HYBRID_KEYS if k in origin},
            }
        )
    return {m: sorted(v, key=lambda p: p["budget_s"]) for m, v in out.items()}


def _sinusoid_ok(p: dict) -> bool:
    rmse = p.get("sinusoid_com_rmse_m")
    return rmse is not None and rmse <= constants.SINUSOID_MAX_COM_RMSE_M


def verdict(pts: dict) -> dict:
    """Per budget: each gradient-based method against CMA-ES (module docstring): ``<method>_minus_cmaes_median``,
    ``<method>_min_ge_cmaes_min``, ``<method>_sinusoid_ok``, ``<method>_target_met``; ``target_met`` and
    ``target_met_by``: whether, and by which, the issue's target is met."""
    out = {}
    cma = {p["budget_s"]: p for p in pts.get("cmaes", [])}
    for t in sorted(cma):
        c, row, met = cma[t], {}, []
        for method in GRADIENT_BASED:
            g = next((p for p in pts.get(method, []) if p["budget_s"] == t), None)
            if g is None:
                continue
            gain = g["envelope_fraction_median"] - c["envelope_fraction_median"]
            min_ok = g["envelope_fraction_min"] >= c["envelope_fraction_min"]
            row.update(
                {
                    f"{method}_minus_cmaes_median": gain,
                    f"{method}_min_ge_cmaes_min": min_ok,
                    f"{method}_sinusoid_ok": _sinusoid_ok(g),
                    f"{method}_target_met": bool(gain >= MARGIN and min_ok and _sinusoid_ok(g)),
                }
            )
            met += [method] if row[f"{method}_target_met"] else []
        if row:
            out[f"{t:g}"] = {**row, "target_met": bool(met), "target_met_by": met}
    return out


def recommended(rep: dict, names) -> str | None:
    """The best held-out median among the sets within the sinusoid bound (None: none is)."""
    ok = [n for n in names if n in rep and _sinusoid_ok(rep[n])]
    return max(ok, key=lambda n: (rep[n]["envelope_fraction_median"], rep[n]["envelope_fraction_min"]), default=None)


def write(out, problem: tp.Problem, rep: dict, index: dict, histories: dict) -> dict:
    """race.json and race.png in ``out`` (module docstring); returns race.json's dict."""
    from wbc_jax.report import tuning_plots

    out = pathlib.Path(out)
    tc = problem.tc
    pts = points(rep, index)
    info_path = out / "gradient" / "train_info.json"
    info = json.loads(info_path.read_text()) if info_path.exists() else {}
    from wbc_jax.tuning.algorithms.gradient import forward_backend

    search = forward_backend(tc)  # the engine the searches ran on (--search-backend auto resolved)
    engines = {"gradient": "jax", "cmaes": search, "random": search, "hybrid": f"{search}, then jax"}
    result = {
        "parameterisation": tc.parameterisation,
        "parameters": info.get("parameters"),
        "budget_s": tc.budget_s,
        "budgets_s": budgets(tc),  # the race's; CMA-ES also has rows at their halves with phase hybrid
        "methods": {m: {"engine": engines[m], "points": v} for m, v in pts.items()},
        "gradient": {
            k: info.get(k)
            for k in (
                "estimator",
                "window_s",
                "batch",
                "checkpoint",
                "compile_s",
                "step_s_median",
                "gradient_physics_steps_per_s",
                "physics_steps_per_s",
                "temp_mb",
                "device",
            )
        },
        "reference": {
            n: {
                k: rep[n][k]
                for k in ("envelope_fraction_median", "envelope_fraction_min", "survival_rate", "sinusoid_com_rmse_m")
            }
            for n in ("default", "critical")
            if n in rep
        },
        "verdict": verdict(pts),
        "recommended": recommended(
            rep, [n for n in rep if isinstance(rep[n], dict) and "envelope_fraction_median" in rep[n]]
        ),
        "provenance": provenance.record({"init_gains": tc.init_gains, "tasks": tc.controller.tasks}),
    }
    io.atomic_write_json(out / "race.json", result)
    tuning_plots.race_curves(pts, out / "race.png", reference=result["reference"])
    return result
