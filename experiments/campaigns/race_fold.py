"""Issue 35's GPU figures in one file, and into results/: what experiments/campaigns/race_gpu.sh ran.

    python experiments/campaigns/race_fold.py --from RUNS [--summary FILE] [--docs DIR]
    python experiments/campaigns/race_fold.py --from RUN --docs DIR --table results/tuning/race.json

The second form folds one race run folder of experiments/campaigns/race_piece.sh (its ``race_<param>.tgz``
unpacked): its results and gain files into DIR, its rows (one per method x budget) into the table.

``--from``: the folder of race_gpu.sh's run folders (``new/``, ``old/``, ``race/``), or the returned
``race_gpu.tgz``. ``summary.json`` (``--summary``, default ``DIR/summary.json``) holds

* ``throughput``: physics steps/s with gradient (each step's rollouts x physics steps over its median
  wall time, the first step left out as the train phase does) at the new settings (``new``) and the old
  (``old``; without it, results/tuning/train_info.json, the committed before), their ratio, and the
  issue's target (500,000) met or not;
* ``quality``: per estimate, its cosine with the zeroth-order estimate, the directional correlation
  and slope, the consistency over batches and the signal-to-noise ratio (quality.json);
* ``profile``: the per-tick parts, implicit against unrolled solver gradients (profile.json);
* ``race``: race.json's verdict, recommendation and per-method rows when the race ran;

with the provenance of each file read (sha256) and this command. ``--docs DIR`` also copies the run
files (train_info, history, quality, profile; race.json, race.png, heldout.json) into ``DIR`` under
flat names, and race.json beside ``DIR`` (results/tuning/race.json for ``--docs results/tuning/race_h100``).
Exits 1 when no figure was found.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import shutil
import statistics
import sys
import tarfile
import tempfile

ROOT = pathlib.Path(__file__).resolve().parents[2]
TARGET_STEPS_PER_S = 500_000.0  # issue 35
BEFORE = ROOT / "results" / "tuning" / "train_info.json"  # the committed H100 figure (unrolled solver, batch 1,024)
QUALITY_KEYS = ("cosine_zeroth_order", "directional_correlation", "directional_slope", "batch_consistency", "snr")


def _json(path: pathlib.Path):
    return json.loads(path.read_text()) if path.is_file() else None


def throughput(run: pathlib.Path) -> dict | None:
    """Gradient throughput of a train phase's folder ``run/gradient`` (None: no step finished)."""
    import csv

    info = _json(run / "gradient" / "train_info.json")
    hist = run / "gradient" / "history.csv"
    rows = list(csv.DictReader(open(hist))) if hist.is_file() else []
    if info is None or not rows:
        return None
    steady = [float(r["step_s"]) for r in rows[1:]] or [float(r["step_s"]) for r in rows]
    step_s = statistics.median(steady)
    keys = (
        "device",
        "batch",
        "horizon_s",
        "steps_per_rollout",
        "checkpoint",
        "estimator",
        "compile_s",
        "temp_mb",
        "argument_mb",
    )
    return {
        **{k: info.get(k) for k in keys},
        "solver_gradient": _solver_gradient(run),
        "steps": len(rows),
        "step_s": [float(r["step_s"]) for r in rows],
        "step_s_median": step_s,
        "gradient_physics_steps_per_s": float(rows[-1]["grad_sim_steps"]) / step_s,
    }


def _solver_gradient(run: pathlib.Path) -> str | None:
    cfg = _json(run / "config.json")
    return None if cfg is None else cfg["tune"].get("solver_gradient")


def summarize(runs: pathlib.Path) -> dict:
    from wbc_jax.core import provenance

    new, old = throughput(runs / "new"), throughput(runs / "old")
    before = old
    if before is None and BEFORE.is_file():
        b = _json(BEFORE)
        before = {
            "source": str(BEFORE.relative_to(ROOT)),
            "solver_gradient": "unrolled",
            **{k: b.get(k) for k in ("device", "batch", "horizon_s", "step_s_median", "gradient_physics_steps_per_s")},
        }
    out: dict = {"throughput": {"new": new, "old": before, "target_steps_per_s": TARGET_STEPS_PER_S}}
    if new is not None:
        rate = new["gradient_physics_steps_per_s"]
        out["throughput"]["target_met"] = rate >= TARGET_STEPS_PER_S
        if before is not None and before.get("gradient_physics_steps_per_s"):
            out["throughput"]["speedup"] = rate / before["gradient_physics_steps_per_s"]
            out["throughput"]["same_device"] = before.get("device") == new.get("device")
    q = _json(runs / "new" / "quality.json")
    if q is not None:
        out["quality"] = {
            "estimates": {name: {k: e[k] for k in QUALITY_KEYS if k in e} for name, e in q["estimates"].items()},
            **{k: q[k] for k in ("parameters", "pushes", "directions", "sigma", "exact_gradient_cosine") if k in q},
        }
    p = _json(runs / "new" / "profile.json")
    if p is not None:
        out["profile"] = p["summary"]
    r = _json(runs / "race" / "race.json")
    if r is not None:
        out["race"] = {k: r[k] for k in ("verdict", "recommended", "budgets_s", "methods") if k in r}
    files = {
        f"{run}/{rel}": runs / run / rel
        for run in ("new", "old", "race")
        for rel in (
            "gradient/train_info.json",
            "gradient/history.csv",
            "quality.json",
            "profile.json",
            "race.json",
            "heldout.json",
        )
        if (runs / run / rel).is_file()
    }
    out["provenance"] = provenance.record(files)
    return out


def fold(runs: pathlib.Path, docs: pathlib.Path) -> None:
    """Copy the run files into ``docs`` (flat names) and race.json beside it (``docs/../race.json``)."""
    docs.mkdir(parents=True, exist_ok=True)
    for run in ("new", "old", "race"):
        for rel in (
            "gradient/train_info.json",
            "gradient/history.csv",
            "quality.json",
            "profile.json",
            "race.json",
            "race.png",
            "heldout.json",
            "envelope_polar.png",
        ):
            src = runs / run / rel
            if src.is_file():
                shutil.copyfile(src, docs / f"{run}_{pathlib.Path(rel).name}")
    if (runs / "race" / "race.json").is_file():
        shutil.copyfile(runs / "race" / "race.json", docs.parent / "race.json")


PIECE_FILES = (
    "race.json",
    "race.png",
    "heldout.json",
    "summary.json",
    "timings.json",
    "learning_curves.png",
    "envelope_polar.png",
    "config.json",
    "gradient/train_info.json",
    "gradient/history.csv",
    "cmaes/history.csv",
    "random/history.csv",
    "hybrid/history.csv",
)


def race_rows(run: pathlib.Path) -> list[dict]:
    """One row per (method, parameterisation, budget_s) of a race run folder (race_piece.sh's ``RUNS/<param>``):
    engine, device, held-out median / min, survival, sinusoid RMSE, simulated steps, the gain file and its sha256."""
    race = _json(run / "race.json")
    gains = _json(run / "gains" / "provenance.json") or {}
    device = race["provenance"]["device"]["label"]
    rate = race["gradient"].get("gradient_physics_steps_per_s")
    rows = []
    for method, m in race["methods"].items():
        for pt in m["points"]:
            origin = gains.get(pt["name"], {})
            rows.append(
                {
                    "method": method,
                    "parameterisation": race["parameterisation"],
                    "budget_s": pt["budget_s"],
                    "engine": m["engine"],
                    "device": device,
                    "name": pt["name"],
                    "envelope_fraction_median": pt["envelope_fraction_median"],
                    "envelope_fraction_min": pt["envelope_fraction_min"],
                    "survival": pt["survival_rate"],
                    "sinusoid_com_rmse_m": pt["sinusoid_com_rmse_m"],
                    "physics_steps": pt["sim_steps"],
                    "wall_s": pt["wall_s"],
                    "gradient_physics_steps_per_s": None if method in ("cmaes", "random") else rate,
                    "gains_sha256": origin.get("sha256"),
                }
            )
    return rows


def fold_piece(run: pathlib.Path, docs: pathlib.Path, table: pathlib.Path) -> dict:
    """Copy a race run folder's results and gain files into ``docs`` and merge its rows into ``table``
    (results/tuning/race.json: the rows of every parameterisation raced so far, one GPU kind)."""
    from wbc_jax.core import io

    for rel in PIECE_FILES:
        if (run / rel).is_file():
            (docs / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(run / rel, docs / rel)
    for budget in sorted((run / "hybrid").glob("t*/")):  # one gradient run per hybrid budget (a run whose compile
        (docs / "hybrid" / budget.name).mkdir(parents=True, exist_ok=True)  # spent its half has no history)
        for name in ("history.csv", "train_info.json"):
            if (budget / name).is_file():
                shutil.copyfile(budget / name, docs / "hybrid" / budget.name / name)
    if (run / "gains").is_dir():
        shutil.copytree(run / "gains", docs / "gains", dirs_exist_ok=True)
    rows = race_rows(run)
    old = _json(table) or {"rows": []}
    param = rows[0]["parameterisation"]
    kept = [r for r in old["rows"] if r["parameterisation"] != param]
    devices = sorted({r["device"] for r in kept + rows})
    out = {
        "rows": kept + rows,
        "devices": devices,
        "one_gpu_kind": len(devices) == 1,
        "folders": {**old.get("folders", {}), param: str(docs)},
        "verdict": {**old.get("verdict", {}), param: _json(run / "race.json")["verdict"]},
    }
    io.atomic_write_json(table, out)
    table_plot(out["rows"], table.with_suffix(".png"))
    return out


def table_plot(rows: list[dict], path: pathlib.Path) -> None:
    """race.png beside the table: per parameterisation, each method's held-out envelope / LIP bound (median solid,
    min dashed) against its wall-time budget."""
    from matplotlib.figure import Figure

    params = sorted({r["parameterisation"] for r in rows})
    fig = Figure(figsize=(5 * len(params), 3.8))
    axes = fig.subplots(1, len(params), squeeze=False)[0]
    for ax, param in zip(axes, params, strict=True):
        methods = sorted({r["method"] for r in rows if r["parameterisation"] == param})
        for method in methods:
            color = f"C{('gradient', 'cmaes', 'random', 'hybrid').index(method)}"  # one colour per method
            pts = sorted(
                (r for r in rows if r["parameterisation"] == param and r["method"] == method),
                key=lambda r: r["budget_s"],
            )
            x = [r["budget_s"] for r in pts]
            ax.plot(x, [r["envelope_fraction_median"] for r in pts], "o-", color=color, label=f"{method} median")
            ax.plot(x, [r["envelope_fraction_min"] for r in pts], "x--", color=color, alpha=0.6)
        ax.set_title(f"{param} ({pts[0]['device']})", fontsize=9)
        ax.set_xlabel("wall-time budget [s] (compilation included)")
        ax.set_ylabel("held-out envelope / LIP bound (min dashed)")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--from", dest="src", required=True, help="race_gpu.sh's run folder or race_gpu.tgz")
    p.add_argument("--summary", default=None, help="summary.json to write (default: DOCS/summary.json)")
    p.add_argument("--docs", default=None, help="results folder to fold the files into, e.g. results/tuning/race_h100")
    p.add_argument(
        "--table",
        default=None,
        help="with --docs: --from is a race run folder of race_piece.sh "
        "(RUNS/<param>); fold it into DOCS and merge its rows into TABLE (results/tuning/race.json)",
    )
    args = p.parse_args(argv)
    from wbc_jax.core import io

    if args.table:
        out = fold_piece(pathlib.Path(args.src), pathlib.Path(args.docs), pathlib.Path(args.table))
        print(json.dumps({"table": args.table, "rows": len(out["rows"]), "devices": out["devices"]}))
        return 0

    src = pathlib.Path(args.src)
    if not src.exists():
        raise SystemExit(f"error: --from {src} does not exist")
    if args.summary is None and args.docs is None:
        raise SystemExit("error: give --summary FILE or --docs DIR")
    with tempfile.TemporaryDirectory() as tmp:
        runs = src
        if src.is_file():
            with tarfile.open(src) as tar:
                tar.extractall(tmp, filter="data")
            inner = [d for d in pathlib.Path(tmp).iterdir() if d.is_dir()]
            runs = inner[0] if len(inner) == 1 else pathlib.Path(tmp)
        summary = summarize(runs)
        target = pathlib.Path(args.summary) if args.summary else pathlib.Path(args.docs) / "summary.json"
        target.parent.mkdir(parents=True, exist_ok=True)
        io.atomic_write_json(target, summary)
        if args.docs:
            fold(runs, pathlib.Path(args.docs))
    found = [k for k in ("quality", "profile", "race") if k in summary] + (
        ["throughput"] if summary["throughput"]["new"] else []
    )
    print(json.dumps({"summary": str(target), "found": found}))
    return 0 if found else 1


if __name__ == "__main__":
    sys.exit(main())
