"""Demonstrations 1-2 of the general task hierarchy: reaching while balancing, priority inversion.

    python experiments/demos/hierarchy_demos.py [--duration 20] [--out results/hierarchy] [--runs NAME ...]

Closed-loop runs of the ``stand`` task (two feet, constant CoM reference), each a
``wbc-jax balance`` run with a task file of experiments/tasks/:

- no_hand_task: the two-level law (force task, postural task);
- hand_above_posture (reach_circle.yaml): the right hand draws a 10 cm circle at 0.5 Hz in front
  of the chest, above the postural task;
- hand_below_posture (reach_below_posture.yaml): the same hand task below a posture task on every
  joint;
- hand_below_upper_body (reach_below_upper_body.yaml): the same hand task below a posture task on
  the torso and the right arm only (the hand may use the base and the legs).

``--runs`` runs a subset (e.g. one per process); demos.json is then built from every run's
metrics.json found under OUT (hand and posture-task RMSE, CoM RMSE and its change with the hand
task, falls). Plots of each run are under OUT/<run>/.
"""

from __future__ import annotations

import argparse
import json
import pathlib

from wbc_jax.core import io, provenance
from wbc_jax.jobs import balance

EXPERIMENTS = pathlib.Path(__file__).resolve().parents[1]
RUNS = {
    "no_hand_task": None,
    "hand_above_posture": EXPERIMENTS / "tasks" / "reach_circle.yaml",
    "hand_below_posture": EXPERIMENTS / "tasks" / "reach_below_posture.yaml",
    "hand_below_upper_body": EXPERIMENTS / "tasks" / "reach_below_upper_body.yaml",
}


def summarize(out: pathlib.Path, duration: float) -> dict:
    """demos.json's content from OUT/<run>/metrics.json (the runs present)."""
    runs = {}
    for name in RUNS:
        path = out / name / "metrics.json"
        if path.exists():
            runs[name] = {k: v for k, v in json.loads(path.read_text()).items() if k != "gains"}
    none = runs.get("no_hand_task")
    return {
        "duration_s": duration,
        "task_rmse_m": {k: {t: v["rmse"] for t, v in r.get("tasks", {}).items()} for k, r in runs.items()},
        "com_rmse_m": {k: r["com_rmse_m"] for k, r in runs.items()},
        "com_rmse_change_with_hand_task_m": {
            k: r["com_rmse_m"] - none["com_rmse_m"] for k, r in runs.items() if none and k != "no_hand_task"
        },
        "fell": {k: bool(r["fell"] or r["nan"]) for k, r in runs.items()},
        "runs": runs,
    }


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--duration", type=float, default=20.0)
    parser.add_argument("--out", default="results/hierarchy")
    parser.add_argument("--runs", nargs="+", default=list(RUNS), choices=list(RUNS))
    parser.add_argument("--quiet", action="store_true")
    args = parser.parse_args(argv)
    out = pathlib.Path(args.out)
    for name in args.runs:
        task_file = RUNS[name]
        result = balance.run(
            task="stand",
            duration=args.duration,
            out=str(out / name),
            progress=not args.quiet,
            tasks=None if task_file is None else str(task_file),
        )
        print(name, json.dumps(result), flush=True)
    summary = summarize(out, args.duration)
    files = {f"tasks:{name}": RUNS[name] for name in args.runs if RUNS[name] is not None}
    summary["provenance"] = provenance.record(files, argv=provenance.script_argv(__file__, argv))
    io.atomic_write_json(out / "demos.json", summary)
    print(json.dumps({k: v for k, v in summary.items() if k != "runs"}, indent=1))


if __name__ == "__main__":
    main()
