"""The table of results/limit: per pushed body and direction, the physical limit of push recovery
(``wbc-jax limit`` summaries), the feet-in-place LIP bound and the strict envelopes of controllers
(``wbc-jax envelope`` summaries), each as a fraction of the limit.

A body whose limit search has not been run (it needs a GPU in reasonable time) keeps its LIP
bound and envelopes, its limit columns are None and ``missing`` names the command that fills them.
"""

from __future__ import annotations

import pathlib

import numpy as np

from wbc_jax.core import io, loader, provenance
from wbc_jax.jobs import sweep_table
from wbc_jax.robot import bounds
from wbc_jax.robot import model as model_lib


def _read(path) -> dict:
    path = pathlib.Path(path)
    try:
        return loader.read_json(path, "limit table input")
    except OSError as err:
        raise ValueError(f"{path} is unreadable: {err}") from None


def _best(found: dict) -> tuple[float | None, list | None, str | None]:
    """(limit, bracket, optimiser) from {optimiser: {"limit_ns", "bracket_ns"}}: the largest limit (each is a
    trajectory replayed and passed in C MuJoCo), and the smallest impulse where every optimiser failed (the
    largest of their brackets' upper ends; None where one optimiser failed at none it tried)."""
    if not found:
        return None, None, None
    name = max(found, key=lambda k: found[k]["limit_ns"])
    uppers = [f["bracket_ns"][1] for f in found.values()]
    upper = None if None in uppers else max(uppers)
    return found[name]["limit_ns"], [found[name]["limit_ns"], upper], name


def ddp_label(ddp: dict) -> str:
    """The optimiser's name of one cross-check file: its ``optimiser`` where it names one (e.g. a
    controller's own trajectory, experiments/acceptance/controller_witness.py), else "crocoddyl", with its
    CoP rectangle's scale where the barrier's rectangle is not the controller's."""
    if ddp.get("optimiser"):
        return str(ddp["optimiser"])
    scale = ddp["config"].get("cop_scale", 1.0)
    return "crocoddyl" if scale == 1.0 else f"crocoddyl cop x{scale:g}"


def body_table(
    limit_summary: dict | None, envelopes: dict, azimuths, robot, body: str, ddps: list | tuple = ()
) -> dict:
    """{azimuth: row} of pushes on ``body``: ``limit_summary`` (a limit run's summary.json or None),
    ``envelopes`` {label: envelope summary.json dict} (gain set 0), the LIP and flywheel bounds
    (``wbc_jax.robot.bounds``) at ``azimuths``; ``ddps``: the crocoddyl cross-checks' results
    (experiments/acceptance/ddp_limit.py, each file an optimiser: :func:`ddp_label`) where they ran.
    The limit is the best optimiser's (``found_by``)."""
    lip = sweep_table.lip_bound(robot, azimuths)
    flywheel = bounds.flywheel_bound(robot, azimuths, body)
    rows = {}
    for az in azimuths:
        by = {}
        if limit_summary is not None and str(float(az)) in limit_summary["directions"]:
            by["mjx"] = limit_summary["directions"][str(float(az))]
        for ddp in ddps:
            if str(float(az)) in ddp["directions"]:
                by[ddp_label(ddp)] = ddp["directions"][str(float(az))]
        lim, bracket, found_by = _best(by)
        envs = {}
        for label, summary in envelopes.items():
            e = summary["envelope"].get("0", summary["envelope"].get(0))[str(float(az))]["impulse_ns"]
            envs[label] = {
                "impulse_ns": e,
                "fraction_of_lip": e / lip[az]["impulse_bound_ns"],
                "fraction_of_limit": e / lim if lim else None,
            }
        fly = flywheel[az]["impulse_bound_ns"]
        best_envelope = max((v["impulse_ns"] for v in envs.values()), default=None)
        alone = (by[found_by].get("limit_replayed_alone") or {}) if found_by else {}
        rows[float(az)] = {
            "lip_bound_ns": lip[az]["impulse_bound_ns"],
            "flywheel_bound_ns": fly,
            "limit_ns": lim,
            "fraction_of_lip": None if lim is None else lim / lip[az]["impulse_bound_ns"],
            "fraction_of_flywheel": None if lim is None else lim / fly,
            "lip_fraction_of_flywheel": lip[az]["impulse_bound_ns"] / fly,
            "bracket_ns": bracket,
            "found_by": found_by,
            "limit_by_optimiser_ns": {k: v["limit_ns"] for k, v in by.items()} or None,
            # the best optimiser's limit replayed again in a batch of its own (ddp_limit.py --recheck; None: not)
            "limit_replayed_alone": alone.get("verified") if alone.get("impulse_ns") == lim else None,
            "limit_over_best_envelope": None if lim is None or not best_envelope else lim / best_envelope,
            "limit_at_least_envelopes": None
            if lim is None
            else all(v["impulse_ns"] <= lim + 1e-9 for v in envs.values()),
            "envelopes": envs,
        }
    return rows


def medians(rows: dict) -> dict:
    """Median (min) over directions of each envelope as a fraction of the LIP bound and of the
    limit, of the limit as a fraction of the LIP and flywheel bounds (None where not measured), and
    of the LIP bound as a fraction of the flywheel bound."""

    def stat(values):
        v = [x for x in values if x is not None]
        return None if len(v) < len(values) or not v else {"median": float(np.median(v)), "min": float(np.min(v))}

    labels = sorted({k for r in rows.values() for k in r["envelopes"]})
    out = {
        "limit": {
            k: stat([r[k] for r in rows.values()])
            for k in ("fraction_of_lip", "fraction_of_flywheel", "limit_over_best_envelope")
        },
        "lip_bound": {"fraction_of_flywheel": stat([r["lip_fraction_of_flywheel"] for r in rows.values()])},
    }
    for label in labels:
        out[label] = {
            k: stat([r["envelopes"][label][k] for r in rows.values()]) for k in ("fraction_of_lip", "fraction_of_limit")
        }
    return out


def _targets(rows: dict, summary: dict | None) -> dict:
    """Issues 37 and 43's targets for one body (None: its limit not measured): the limit at least
    every controller's envelope in every direction; every limit from a trajectory replayed in C
    MuJoCo; in the median over directions, the limit at least 1.1x the best controller's envelope,
    or within 10 % of the flywheel bound (issue 43 asks for either)."""
    if summary is None:
        return {
            "limit_at_least_every_envelope": None,
            "every_limit_replayed_in_c_mujoco": None,
            "limit_at_least_1p1x_best_envelope_median": None,
            "limit_within_10pct_of_flywheel_bound_median": None,
        }
    below = [az for az, r in rows.items() if r["limit_at_least_envelopes"] is False]
    measured = sum(r["limit_ns"] is not None for r in rows.values())
    of_flywheel = [r["fraction_of_flywheel"] for r in rows.values() if r["fraction_of_flywheel"] is not None]
    over_best = medians(rows)["limit"]["limit_over_best_envelope"]  # None unless every direction has both
    return {
        "limit_at_least_every_envelope": not below,
        "directions_below_an_envelope": below,
        "limit_over_best_envelope": over_best,
        "limit_at_least_1p1x_best_envelope_median": None if over_best is None else over_best["median"] >= 1.1,
        "limit_within_10pct_of_flywheel_bound_median": bool(of_flywheel) and float(np.median(of_flywheel)) >= 0.9,
        "directions_measured": f"{measured} of {len(rows)}",
        "every_limit_replayed_in_c_mujoco": summary["targets"]["every_limit_replayed_in_c_mujoco"],
        "time_cut": summary.get("time_cut"),
        "rounds_done": summary.get("rounds_done"),
        "devices": summary.get("devices"),
    }


def write(out_dir, bodies: dict, commands: dict, robot: str) -> dict:
    """results/limit/limit.json and limit.png from ``bodies`` {body: {"limit": summary path or None,
    "envelopes": {label: summary path}, "ddp": the crocoddyl cross-checks' files (optional)}}; ``commands`` {body: the command that fills in a missing
    body's limit}; ``robot``: the robot's name."""
    from wbc_jax.report import limit_plots

    robot = model_lib.load_robot(robot)
    tables, missing, inputs = {}, {}, {}
    for body, spec in bodies.items():
        envelopes = {label: _read(p) for label, p in spec["envelopes"].items()}
        inputs.update({f"{body}_envelope_{label}": p for label, p in spec["envelopes"].items()})
        summary = _read(spec["limit"]) if spec.get("limit") else None
        if summary is None:
            missing[body] = commands[body]
        else:
            inputs[f"{body}_limit"] = spec["limit"]
        azimuths = sorted({float(a) for s in envelopes.values() for a in s["envelope"]["0"]})
        ddps = [_read(p) for p in spec.get("ddp") or ()]
        labels = [ddp_label(d) for d in ddps]
        if len(set(labels)) < len(labels):
            raise ValueError(f"{body}'s crocoddyl files {spec['ddp']} repeat an optimiser ({labels}): one file each")
        inputs.update({f"{body}_ddp_{i}": p for i, p in enumerate(spec.get("ddp") or ())})
        tables[body] = body_table(summary, envelopes, azimuths, robot, body, ddps)
    result = {
        "what": "per pushed body and direction: the physical limit of push recovery (largest impulse with a torque "
        "trajectory within the model's torque limits that passes the strict criterion replayed in C MuJoCo, the best "
        "of the MJX search and the crocoddyl cross-check where it ran: found_by), the LIP bound "
        "m omega d, the LIP + flywheel bound (wbc_jax.robot.bounds, Pratt et al. 2006) and the strict envelopes of "
        "controllers, as fractions of the LIP bound and of the limit",
        "bodies": {body: {"medians": medians(rows), "directions": rows} for body, rows in tables.items()},
        "targets": {
            body: _targets(rows, _read(bodies[body]["limit"]) if bodies[body].get("limit") else None)
            for body, rows in tables.items()
        },
        "missing": missing or None,
        "provenance": provenance.record(inputs),
    }
    out_dir = pathlib.Path(out_dir)
    io.atomic_write_json(out_dir / "limit.json", result)
    limit_plots.polar_bodies(tables, out_dir / "limit.png")
    return result
