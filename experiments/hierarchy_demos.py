"""Demonstrations 1-2 of the general task hierarchy: reaching while balancing, priority inversion.

    python experiments/hierarchy_demos.py [--duration 20] [--out docs/hierarchy]

Three closed-loop runs of the ``stand`` task (two feet, constant CoM reference), each a
``wbc-jax balance`` run: without motion tasks; with the right hand drawing a 10 cm circle at 0.5 Hz
above the postural task (experiments/tasks/reach_circle.yaml); and the same hand task below an
upper-body posture task (experiments/tasks/reach_below_posture.yaml). Writes demos.json (hand RMSE,
CoM RMSE and their differences) and each run's metrics/plots under OUT/<run>/.
"""

from __future__ import annotations

import argparse
import json
import pathlib

from wbc_jax import balance, io

HERE = pathlib.Path(__file__).resolve().parent
RUNS = {
    "no_hand_task": None,
    "hand_above_posture": HERE / "tasks" / "reach_circle.yaml",
    "hand_below_posture": HERE / "tasks" / "reach_below_posture.yaml",
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--duration", type=float, default=20.0)
    parser.add_argument("--out", default="docs/hierarchy")
    parser.add_argument("--quiet", action="store_true")
    args = parser.parse_args()
    out = pathlib.Path(args.out)
    results = {}
    for name, task_file in RUNS.items():
        results[name] = balance.run("stand", duration=args.duration, out=out / name, progress=not args.quiet,
                                    tasks_file=None if task_file is None else str(task_file))  # fmt: skip
        print(name, json.dumps(results[name]))
    above, below, none = (results[k] for k in ("hand_above_posture", "hand_below_posture", "no_hand_task"))
    summary = {
        "command": f"python experiments/hierarchy_demos.py --duration {args.duration}",
        "duration_s": args.duration,
        "hand_rmse_m": {"above_posture": above["tasks"]["right_hand"]["rmse"],
                        "below_posture": below["tasks"]["right_hand"]["rmse"]},
        "com_rmse_m": {k: r["com_rmse_m"] for k, r in results.items()},
        "com_rmse_change_with_hand_task_m": above["com_rmse_m"] - none["com_rmse_m"],
        "fell": {k: r["fell"] or r["nan"] for k, r in results.items()},
        "runs": results,
    }  # fmt: skip
    io.atomic_write_json(out / "demos.json", summary)
    print(json.dumps({k: v for k, v in summary.items() if k != "runs"}, indent=1))


if __name__ == "__main__":
    main()
