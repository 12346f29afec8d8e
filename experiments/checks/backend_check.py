"""Same trajectory on every physics backend (issue: GPU throughput, "same trajectory first").

    python experiments/checks/backend_check.py --out runs/backend_check [--backends warp jax mujoco]

The benchmark scenario (stand, 40 N lateral chest push at 0.3 s for 0.1 s, 1 s), one environment
on each backend in the process's precision, recorded: the largest CoM difference of each backend
against each other one over the second, and their metrics. Writes backend_check.json into --out.
The check (:func:`failures`): every pair within ``BAR_M`` (1 mm, float32 or float64); exit status 1
otherwise.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import pathlib
import sys

import jax
import numpy as np

from wbc_jax.core import checks, io, provenance
from wbc_jax.sim import metrics as metrics_lib
from wbc_jax.sim import physics, runner, scenario
from wbc_jax.sim.state import SimConfig

PUSH = ([0.0, 40.0, 0.0], 0.3, 0.1)
BAR_M = 1e-3  # the largest CoM difference between two backends over the second
BAR = f"the CoM of every pair of backends within {BAR_M * 1e3:g} mm over the 1 s run"


def failures(result: dict) -> list[str]:
    """The pairs of backends whose CoM trajectories differ by more than BAR_M (or not finitely)."""
    pairs = result["max_com_difference_m"]
    out = [
        f"{pair}: CoM differs by {d} m > {BAR_M:g} m"
        for pair, d in pairs.items()
        if not (math.isfinite(d) and d <= BAR_M)
    ]
    return out if pairs else ["no pair of backends compared (give at least two --backends)"]


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog=f"Check: {BAR}; exit status 1 otherwise.")
    p.add_argument("--backends", nargs="+", default=None, choices=[b for b in physics.BACKENDS if b != "auto"])
    p.add_argument("--out", default="runs/backend_check")
    args = p.parse_args(argv)
    backends = args.backends or ["jax", "mujoco"] + (["warp"] if physics.has_warp() and physics.has_cuda() else [])
    runner.enable_compilation_cache()
    com, summary = {}, {}
    for b in backends:
        st = scenario.setup("stand", duration=1.0, sim=SimConfig(physics=physics.PhysicsConfig(backend=b)))
        run = runner.run(st, scenario.single(st, scenario.make_push(*PUSH, st.dtype)))
        com[b] = np.asarray(run.records.com[0], float)
        m = metrics_lib.summarize(jax.tree_util.tree_map(lambda x: x[0], run.metrics), PUSH[1] + PUSH[2])
        summary[b] = {
            "compile_s": round(run.compile_s, 2),
            "com_max_err_m": m["com_max_err_m"],
            "max_foot_slip_m": m["max_foot_slip_m"],
            "upright": bool(m["upright"]),
            "com_excursion_m": float(np.linalg.norm(com[b] - com[b][0], axis=1).max()),
        }
    pairs = {
        f"{a}-{b}": float(np.linalg.norm(com[a] - com[b], axis=1).max()) for a, b in itertools.combinations(backends, 2)
    }
    result = {
        "max_com_difference_m": pairs,
        "backends": summary,
        "dtype": str(scenario.float_dtype()),
        "device": provenance.device_label(),
        "scenario": "stand, 40 N lateral chest push 0.3-0.4 s, 1 s",
        "provenance": provenance.record(argv=provenance.script_argv(__file__, argv)),
    }
    result["check"] = checks.verdict(failures(result), BAR)
    io.atomic_write_json(pathlib.Path(args.out) / "backend_check.json", result)
    print(json.dumps(result), flush=True)
    return result


if __name__ == "__main__":
    sys.exit(checks.exit_status(main()))
