"""Where the hand task's CoM error comes from: precision, control rate, solver iterations, regularisation.

    python experiments/archive/hierarchy_diagnose.py --duration 6 --control-dt 0.01 0.001 [--solver-iterations 4 8]
        [--projector-reg 1e-5 1e-7] [--damping 1e-3] [--tasks experiments/tasks/reach_circle.yaml] [--out DIR]

Precision follows JAX (JAX_ENABLE_X64=1 for float64). One ``balance.run`` per combination; prints
one JSON line each (hand RMSE, CoM RMSE, slip, force error) and writes OUT/diagnose_<dtype>.json.
"""

from __future__ import annotations

import argparse
import itertools
import json
import pathlib

import jax

from wbc_jax.control import hierarchy
from wbc_jax.control.controller import ControllerConfig
from wbc_jax.core import io
from wbc_jax.jobs import balance

EXPERIMENTS = pathlib.Path(__file__).resolve().parents[1]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--duration", type=float, default=6.0)
    p.add_argument("--control-dt", type=float, nargs="+", default=[0.01])
    p.add_argument("--solver-iterations", type=int, nargs="+", default=[4])
    p.add_argument("--projector-reg", type=float, nargs="+", default=[None])
    p.add_argument("--damping", type=float, nargs="+", default=[None])
    p.add_argument("--tasks", nargs="+", default=[str(EXPERIMENTS / "tasks" / "reach_circle.yaml")])
    p.add_argument("--out", default="runs/hierarchy_diagnose")
    args = p.parse_args()
    size = 8 if jax.config.jax_enable_x64 else 4
    rows = []
    for tasks, dt, it, reg, damp in itertools.product(
        args.tasks, args.control_dt, args.solver_iterations, args.projector_reg, args.damping
    ):
        controller = ControllerConfig(projector_reg=reg, solution_damping=damp)
        r = balance.run(
            task="stand",
            duration=args.duration,
            out=None,
            progress=False,
            plots=False,
            tasks=None if tasks == "none" else tasks,
            control_dt=dt,
            solver_iterations=it,
            controller=controller,
        )
        row = {
            "dtype": f"float{8 * size}",
            "tasks": pathlib.Path(tasks).stem,
            "control_dt": dt,
            "solver_iterations": it,
            "projector_reg": hierarchy.PROJECTOR_REG[size] if reg is None else reg,
            "damping": hierarchy.SOLUTION_DAMPING[size] if damp is None else damp,
            "fell": r["fell"] or r["nan"],
            "com_rmse_m": r["com_rmse_m"],
            "max_foot_slip_m": r["max_foot_slip_m"],
            "force_rel_err_median": r["force_rel_err_median"],
            "tasks_rmse": {k: v["rmse"] for k, v in r.get("tasks", {}).items()},
            "wall_time_s": r["wall_time_s"],
        }
        print(json.dumps(row), flush=True)
        rows.append(row)
    io.atomic_write_json(pathlib.Path(args.out) / f"diagnose_float{8 * size}.json", rows)


if __name__ == "__main__":
    main()
