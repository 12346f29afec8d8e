"""The ``wbc-jax tune`` job: one tuning pipeline, run in phases (``--phases``), each resumable in ``--out``.

    predict   prediction.json, survival_vs_loss.png   does the loss rank held-out survival
    train     gradient/                              gradient tuning (history, checkpoint, train_info.json)
    quality   quality.json                           the gradient against zeroth-order estimates
    profile   profile.json                           where a gradient step's time goes
    cmaes     cmaes/                                 CMA-ES (evosax) on --search-backend
    random    random/                                random search on --search-backend
    hybrid    hybrid/t<B>/                           the gradient refining CMA-ES's set at B/2 (with --budget-s)
    heldout   heldout/, heldout_raw.json             every gain set on the held-out evaluation
    report    heldout.json, race.json, summary.json, envelope_polar.png, learning_curves.png, race.png

timings.json holds each phase's wall seconds; a re-run of a finished phase leaves its time as it was
(:mod:`wbc_jax.tuning.orchestration.timings`).

Two budgets. Without ``--budget-s`` (the equal-steps comparison): the gradient runs ``--steps``, the
searches its simulated steps (and its wall time, ``--wall-budget``); the sets are ``gradient``, ``cmaes``,
``random`` (equal steps) and ``cmaes_wall``, ``random_wall`` (equal wall time). With ``--budget-s T`` (the
race): every method runs T seconds of wall time, compilation included, and its gain set at each of
``--snapshots-s`` and at T is kept (``gradient_t120``, ..., ``gradient`` at T): one run gives every
budget. Phase ``hybrid`` (:mod:`wbc_jax.tuning.algorithms.hybrid`) refines CMA-ES's set at half of each budget
with the gradient for the other half (``hybrid_t120``, ..., ``hybrid``). The tuned sets are written
once into ``gains/`` (:func:`wbc_jax.tuning.store.write_controls`), with their origin in
``gains/provenance.json``; the held-out evaluation adds ``HeldoutConfig.sets`` (the WBC defaults and
the hand-set row by default).
"""

from __future__ import annotations

import dataclasses
import json
import pathlib

import jax
import numpy as np

from wbc_jax.core import io, options, provenance
from wbc_jax.core.options import flat_dict
from wbc_jax.jobs import runs
from wbc_jax.report import tuning_plots
from wbc_jax.robot.robots import describe
from wbc_jax.sim import scenario
from wbc_jax.tuning import store
from wbc_jax.tuning.algorithms import baselines, hybrid
from wbc_jax.tuning.algorithms import gradient as tuning
from wbc_jax.tuning.algorithms import problem as tp
from wbc_jax.tuning.algorithms.loss import LossConfig
from wbc_jax.tuning.algorithms.params import nava_conditions
from wbc_jax.tuning.config import TuneConfig
from wbc_jax.tuning.heldout_config import HeldoutConfig, heldout_default_config
from wbc_jax.tuning.orchestration import heldout as tuning_eval
from wbc_jax.tuning.orchestration import heldout_report, prediction, race
from wbc_jax.tuning.orchestration.timings import PhaseTimings


def _search_times(tc: TuneConfig, kind: str) -> list:
    """The wall times a search keeps its sets at: the race's budgets, and for the hybrid's parent search (phase
    hybrid) also half of each (where the hybrid starts)."""
    times = race.budgets(tc)
    if kind == hybrid.PARENT and "hybrid" in tc.phases:
        times = sorted(set(times) | set(hybrid.halves(times)))
    return times


def _inputs(tc: TuneConfig, hc: HeldoutConfig | None = None) -> dict:
    """The run's input files by role (each recorded with its sha256 in every result the run writes)."""
    return {
        "init_gains": tc.init_gains,
        "envelope": tc.envelope,
        "tasks": tc.controller.tasks,
        **(tuning_eval.set_files(hc.sets, describe(tc.robot)) if hc is not None else {}),
    }


def _write(out: pathlib.Path, problem: tp.Problem, name: str, controls, reg, origin: dict) -> None:
    store.write_controls(
        out / "gains",
        name,
        controls,
        reg,
        origin,
        regularisation=problem.tc.tune_regularisation,
        inputs=_inputs(problem.tc),
    )


def _gradient_sets(problem: tp.Problem, out: pathlib.Path, rows: list) -> None:
    tc = problem.tc
    folder = out / "gradient"
    if tc.budget_s > 0:
        for t in race.budgets(tc):
            i = tuning.at_time(rows, t)
            controls, reg = tuning.snapshot_controls(problem, folder, i)
            r = rows[i] if i >= 0 else {"sim_steps": 0, "wall_s": 0.0}
            name = store.set_name("gradient", None if t == tc.budget_s else t)
            _write(
                out,
                problem,
                name,
                controls,
                reg,
                {
                    "method": "gradient",
                    "budget_s": t,
                    "step": i,
                    "sim_steps": int(r["sim_steps"]),
                    "wall_s": float(r["wall_s"]),
                },
            )
    else:
        controls, reg = tuning.snapshot_controls(problem, folder, len(rows) - 1)
        _write(
            out,
            problem,
            "gradient",
            controls,
            reg,
            {
                "method": "gradient",
                "step": len(rows) - 1,
                "sim_steps": int(rows[-1]["sim_steps"]),
                "wall_s": float(rows[-1]["wall_s"]),
            },
        )


def _search_sets(problem: tp.Problem, out: pathlib.Path, kind: str, res: dict) -> None:
    tc = problem.tc
    if tc.budget_s > 0:
        picks = [
            (store.set_name(kind, None if t == tc.budget_s else t), res["at"][t], t) for t in _search_times(tc, kind)
        ]
    else:
        picks = [(kind, res["equal_steps"], None)]
        if res["equal_wall"]["reached"]:
            picks.append((f"{kind}_wall", res["equal_wall"], None))
    for name, e, t in picks:
        _write(
            out,
            problem,
            name,
            *e["controls"],
            {
                "method": kind,
                "budget_s": t,
                "generation": e["generation"],
                "sim_steps": e["sim_steps"],
                "wall_s": e["wall_s"],
            },
        )


def _gradient_budget(out: pathlib.Path) -> dict:
    path = out / "gradient" / "history.csv"
    if not path.exists():
        raise ValueError(
            "the searches at equal steps need the gradient run's budget: run --phases train first (or give --budget-s)"
        )
    rows = store.read_csv(path)
    return {"sim_steps": int(rows[-1]["sim_steps"]), "wall_s": float(rows[-1]["wall_s"])}


def tuned_sets(problem: tp.Problem, out: pathlib.Path) -> dict:
    """{name: (controls, regularisation (2,))} of the gain files in ``out/gains`` (read back, checked)."""
    from wbc_jax.tuning.algorithms import schedule as gain_schedule

    index_path = out / "gains" / "provenance.json"
    index = json.loads(index_path.read_text()) if index_path.exists() else {}
    sets = {}
    n, dtype = problem.robot.index.n, problem.setup.dtype
    for name in index:
        path = out / "gains" / f"{name}.json"
        if gain_schedule.is_schedule_file(path):
            controls = gain_schedule.load_schedule(path, dtype)
        else:
            controls = tuning_eval.load_gains(path, n, dtype)
        reg_path = out / "gains" / f"{name}_regularisation.json"
        reg = problem.reg0
        if reg_path.exists():
            d = json.loads(reg_path.read_text())
            reg = np.array([d["pinv_damping"], d["kp_postural_reg"]], float)
        sets[name] = (controls, reg)
    return sets


def run(
    cfg: TuneConfig | None = None,
    hc: HeldoutConfig | None = None,
    *,
    lc: LossConfig | None = None,
    progress: bool = True,
    mesh=None,
    **overrides,
) -> dict:
    """The ``tune`` job (module docstring). ``overrides``: fields of :class:`TuneConfig`. Returns the
    summary of what ran (phase timings, and the held-out rows once reported)."""
    if jax.process_count() > 1:  # each device's share comes back to this process's host (objectives.DevicePrograms)
        raise ValueError(
            f"wbc-jax tune runs in one process on its local devices (every local GPU), not in "
            f"{jax.process_count()} processes: run it without --distributed"
        )
    tc = options.replace(tuning.default_config() if cfg is None else cfg, **overrides)
    hc = dataclasses.replace(heldout_default_config() if hc is None else hc, robot=tc.robot, controller=tc.controller)
    lc = LossConfig() if lc is None else lc
    out = pathlib.Path(tc.out)
    runs.check_output_dir(out, "tune")
    problem = tp.make_problem(tc, lc)
    reference = tuning_eval.load_sets(hc.sets, problem.robot.description, problem.setup.dtype)  # checked first
    files = _inputs(tc, hc)
    fp = runs.fingerprint(
        {
            "tune": {k: v for k, v in flat_dict(tc).items() if k not in ("out", "phases", *tc.PROCEDURE)},
            "heldout": {k: v for k, v in flat_dict(hc).items() if k != "out"},
            "loss": dataclasses.asdict(problem.lc),  # the torque scales resolved for the robot
            "dtype": str(scenario.float_dtype()),
        },
        list(files.values()),
        tc.robot,
    )
    runs.claim_output_dir(out, "tune", fp, resume=True)
    if "hybrid" in tc.phases and hybrid.PARENT not in tc.phases:  # its parents are there already, or an error now
        for t in race.budgets(tc):
            hybrid.parent(problem, out, t)
    io.atomic_write_json(
        out / "config.json",
        {
            "tune": flat_dict(tc),
            "heldout": flat_dict(hc),
            "loss": dataclasses.asdict(problem.lc),  # the torque scales resolved for the robot
            "provenance": provenance.record(files),
        },
    )
    timed = PhaseTimings(out, progress=progress).run  # timings.json (its module docstring)

    summary: dict = {"phases": list(tc.phases)}
    if "predict" in tc.phases:
        pred = timed(
            "predict",
            lambda: prediction.survival_prediction(problem, tc.eval_pushes, out=out),
            out / "prediction.json",
        )
        summary["predict"] = {k: pred[k] for k in ("n", "survival_rate", "spearman_train_horizon", "auc_train_horizon")}
    # One gradient program for training and the quality figures (compiled once).
    step = None
    if "train" in tc.phases or "quality" in tc.phases:
        step = tuning.GradientStep(problem, tuning.make_optimizer(tc.lr, tc.clip_norm), mesh)
    if "train" in tc.phases:
        _, _, rows, info = timed(
            "train", lambda: tuning.train(problem, out / "gradient", progress=progress, mesh=mesh, step_fn=step)
        )
        _gradient_sets(problem, out, rows)
        summary["train"] = {k: info.get(k) for k in ("compile_s", "step_s_median", "gradient_physics_steps_per_s")}
    if "quality" in tc.phases:
        from wbc_jax.tuning.orchestration import quality

        q = timed(
            "quality",
            lambda: quality.measure(problem, out, mesh=mesh, progress=progress, step=step),
            out / "quality.json",
        )
        summary["quality"] = {
            k: {m: e[m] for m in ("cosine_zeroth_order", "directional_correlation") if m in e}
            for k, e in q["estimates"].items()
        }
    if "profile" in tc.phases:
        from wbc_jax.tuning.orchestration import profile

        summary["profile"] = timed("profile", lambda: profile.measure(problem, out, mesh=mesh), out / "profile.json")[
            "summary"
        ]
    for kind in tc.searches:
        budget = {"sim_steps": 0, "wall_s": 0.0} if tc.budget_s > 0 else _gradient_budget(out)
        times = _search_times(tc, kind) if tc.budget_s else ()
        res = timed(
            kind,
            lambda k=kind, b=budget, t=times: baselines.search(
                problem, k, out / k, budget=b, times=t, progress=progress, mesh=mesh
            ),
        )
        _search_sets(problem, out, kind, res)
    if "hybrid" in tc.phases:
        refined = timed("hybrid", lambda: hybrid.run(problem, out, race.budgets(tc), progress=progress, mesh=mesh))
        for name, (controls, reg, origin) in refined.items():
            _write(out, problem, name, controls, reg, origin)
        summary["hybrid"] = {
            n: {k: o[k] for k in ("parent", "step", "gradient_wall_s", "sim_steps", "wall_s")}
            for n, (_, _, o) in refined.items()
        }
    if "heldout" in tc.phases:
        sets = {**reference, **tuned_sets(problem, out)}

        def held_out() -> None:
            io.atomic_write_json(
                out / "heldout_raw.json", tuning_eval.heldout(sets, hc, out / "heldout", progress=progress)
            )

        timed("heldout", held_out, out / "heldout_raw.json")
    if "report" in tc.phases:
        summary["heldout"] = report(problem, out, hc, reference)
    return summary


def report(problem: tp.Problem, out: pathlib.Path, hc: HeldoutConfig, reference: dict) -> dict:
    """heldout.json, race.json (with --budget-s), summary.json and the figures, from what the run holds."""
    tc = problem.tc
    raw_path = out / "heldout_raw.json"
    if not raw_path.exists():
        raise ValueError("no held-out results yet: run --phases heldout first")
    results = json.loads(raw_path.read_text())
    index_path = out / "gains" / "provenance.json"
    index = json.loads(index_path.read_text()) if index_path.exists() else {}
    sets = {**reference, **tuned_sets(problem, out)}
    files = {
        **tuning_eval.set_files(hc.sets, problem.robot.description),
        **{n: str(out / "gains" / f"{n}.json") for n in index},
    }
    budgets = {n: {"sim_steps": e.get("sim_steps", 0), "wall_s": e.get("wall_s", 0.0)} for n, e in index.items()}
    extra = {
        "config": {"tune": flat_dict(tc), "heldout": flat_dict(hc)},
        "nava_2016": {n: nava_conditions(c, r) for n, (c, r) in sets.items() if hasattr(c, "kp_com")},
    }
    for name in ("prediction", "quality"):
        if (out / f"{name}.json").exists():
            extra[name] = {
                k: v for k, v in json.loads((out / f"{name}.json").read_text()).items() if not isinstance(v, list)
            }
    rep = heldout_report.write_heldout(
        out / "heldout.json",
        results,
        budgets,
        extra=extra,
        inputs={**files, "tasks": tc.controller.tasks, "init_gains": tc.init_gains},
    )
    tuning_plots.envelope_polar({n: rep[n] for n in sets if n in rep and "_t" not in n}, out / "envelope_polar.png")
    histories = {
        k: store.read_csv(out / k / "history.csv")
        for k in ("gradient", *baselines.KINDS)
        if (out / k / "history.csv").exists()
    }
    histories.update(hybrid.histories(out, index))
    tuning_plots.learning_curves(histories, out / "learning_curves.png")
    line = {n: {k: rep[n][k] for k in heldout_report.SUMMARY_KEYS} for n in sets if n in rep}
    if tc.budget_s > 0:
        race_report = race.write(out, problem, rep, index, histories)
        line = {"sets": line, "race": race_report["verdict"], "recommended": race_report["recommended"]}
    io.atomic_write_json(
        out / "summary.json",
        {"sets": line, "targets": rep["targets"], "provenance": provenance.record(_inputs(tc, hc))},
    )
    return line
