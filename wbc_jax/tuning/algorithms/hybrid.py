"""The race's hybrid (issue 42): the gradient as a local refiner of CMA-ES's best candidate, within the budget.

For each race budget B (the ``--snapshots-s`` within ``--budget-s``, and ``--budget-s``), the hybrid starts
from CMA-ES's current solution at B / 2 (its mean after the last generation within B / 2: the set
``cmaes_t<B/2>``, which the race keeps when phase ``hybrid`` is asked for) and refines it with the
gradient for the remaining B / 2 seconds of wall time: the training of phase ``train`` (same flags,
optimiser, estimator, batch; :func:`wbc_jax.tuning.algorithms.gradient.train` from the parent's parameters), its
program built afresh and that time counted in that half (on one device a load of the program phase
``train`` compiled, :func:`wbc_jax.sim.executables.compiled`: seconds, where tracing it again took minutes
on a CPU). Its set at B (``hybrid_t<B>``, ``hybrid`` at ``--budget-s``) is the parameters after its last
step within B / 2 (the parent itself when none fits), with the wall time and simulated steps of both
halves added. One resumable gradient run per budget, in ``hybrid/t<B>/``.
"""

from __future__ import annotations

import json
import pathlib

import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from wbc_jax.core import provenance
from wbc_jax.tuning import store
from wbc_jax.tuning.algorithms import gradient as tuning
from wbc_jax.tuning.algorithms import problem as tp

PARENT = "cmaes"  # the gradient-free search whose set the hybrid refines


def halves(times) -> list[float]:
    """The wall times [s] at which the hybrid's parents are taken: half of each race budget."""
    return sorted({float(t) / 2 for t in times})


def folder(out: pathlib.Path, budget: float) -> pathlib.Path:
    """The hybrid's gradient run for race budget ``budget`` [s]."""
    return pathlib.Path(out) / "hybrid" / f"t{budget:g}"


def parent(problem: tp.Problem, out: pathlib.Path, budget: float) -> dict:
    """CMA-ES's set at ``budget`` / 2 in run ``out``: {"name", "sha256", "params" (the unconstrained
    pytree), "generation", "sim_steps", "wall_s"}. A set the run lacks, or whose file or checkpoint no
    longer matches its record, is a one-line error (read from files: nothing compiles)."""
    out = pathlib.Path(out)
    half = budget / 2
    name = store.set_name(PARENT, half)
    index_path = out / "gains" / "provenance.json"
    index = json.loads(index_path.read_text()) if index_path.exists() else {}
    if name not in index:
        raise ValueError(
            f"--phases hybrid: the race budget {budget:g} s needs CMA-ES's set at {half:g} s "
            f"({out / 'gains' / name}.json), which this run lacks: run --phases cmaes hybrid "
            "(CMA-ES keeps its sets at half of every budget when the hybrid phase is asked for)"
        )
    entry, path = index[name], out / "gains" / f"{name}.json"
    if not path.exists() or provenance.sha256(path) != entry["sha256"]:
        raise ValueError(
            f"--phases hybrid: {path} is missing or differs from its record in {index_path}; use another --out"
        )
    params0 = problem.init_params()
    flat0, unravel = ravel_pytree(params0)
    generation = int(entry["generation"])
    params = params0
    if generation >= 0:
        with np.load(out / PARENT / "checkpoint.npz") as z:
            snapshots = z["extra_snapshots"]
        if generation >= len(snapshots):
            raise ValueError(
                f"--phases hybrid: {out / PARENT / 'checkpoint.npz'} has {len(snapshots)} generations, "
                f"{name} was generation {generation}; use another --out"
            )
        params = unravel(jnp.asarray(snapshots[generation], flat0.dtype))
    return {
        "name": name,
        "sha256": entry["sha256"],
        "params": params,
        "generation": generation,
        "sim_steps": int(entry["sim_steps"]),
        "wall_s": float(entry["wall_s"]),
    }


def run(problem: tp.Problem, out: pathlib.Path, times, *, progress: bool = True, mesh=None, step_fn=None) -> dict:
    """The hybrid at every race budget in ``times`` (module docstring). ``step_fn``: as
    :func:`wbc_jax.tuning.algorithms.gradient.train`'s (tests); default: each budget compiles its own program.
    Returns {set name: (controls, regularisation (2,), origin dict)}; every parent is checked first."""
    out = pathlib.Path(out)
    parents = {float(b): parent(problem, out, float(b)) for b in times}
    sets = {}
    for budget, par in parents.items():
        run_dir = folder(out, budget)
        _, _, rows, info = tuning.train(
            problem,
            run_dir,
            progress=progress,
            mesh=mesh,
            step_fn=step_fn,
            start_params=par["params"],
            budget_s=budget / 2,
        )
        i = tuning.at_time(rows, budget / 2)
        controls, reg = tuning.snapshot_controls(problem, run_dir, i, start_params=par["params"])
        row = rows[i] if i >= 0 else {"sim_steps": 0, "wall_s": 0.0}
        grad_steps, grad_wall = int(row["sim_steps"]), float(row["wall_s"])
        origin = {
            "method": "hybrid",
            "budget_s": budget,
            "parent": par["name"],
            "parent_sha256": par["sha256"],
            "parent_generation": par["generation"],
            "parent_sim_steps": par["sim_steps"],
            "parent_wall_s": par["wall_s"],
            "step": i,
            "gradient_sim_steps": grad_steps,
            "gradient_wall_s": grad_wall,
            "gradient_compile_s": info.get("compile_s"),
            "sim_steps": par["sim_steps"] + grad_steps,
            "wall_s": round(par["wall_s"] + grad_wall, 3),
        }
        sets[store.set_name("hybrid", None if budget == problem.tc.budget_s else budget)] = (controls, reg, origin)
    return sets


def histories(out: pathlib.Path, index: dict) -> dict:
    """{set name: the hybrid run's history, its sim_steps and wall_s offset by its parent's} (learning curves)."""
    found = {}
    for name, origin in index.items():
        path = folder(out, float(origin["budget_s"])) / "history.csv" if origin.get("method") == "hybrid" else None
        if path is None or not path.exists():
            continue
        found[name] = [
            {
                **r,
                "sim_steps": int(r["sim_steps"]) + origin["parent_sim_steps"],
                "wall_s": float(r["wall_s"]) + origin["parent_wall_s"],
            }
            for r in store.read_csv(path)
        ]
    return found
