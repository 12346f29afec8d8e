"""What the torque law's mass-matrix solve costs by engine (issue 46; ``ControllerConfig.mass_solve_engine``).

The torque law factorises each environment's M (nv x nv) and solves with D + 1 + n right-hand sides (the contact
Jacobians' transposes, the bias, M^-1's joint columns: 29 x 36 for the iCub, :func:`wbc_jax.control.torques.torque_terms`).
On the H100 XLA ran that as batched ``potrf`` and ``trsm`` calls, 0.091 µs per environment (BENCHMARKS.md). This
times, vmapped over ``--batch`` copies of the standing M with small random joint offsets (and random right-hand sides
of the same shape), µs per environment of each engine (the best of ``--repeats`` runs, compiled first), and how far
the Warp kernel's L and M^-1 B lie from JAX's (relative to their largest entries):

    python benchmarks/mass_solve_cost.py --batch 65536 --out results/gpu_h100/mass_solve_cost.json

Engines that cannot run here (no warp-lang) are skipped and named in the result.
"""

import argparse

import jax
import jax.numpy as jnp
import numpy as np

# from this script's folder (Python puts it first on sys.path): profile_tick's timing (best of --repeats, compiled
# first) and warp_terms_cost's flags and states
from profile_tick import timed
from warp_terms_cost import batch_parser, checked, measured, states

from wbc_jax.control.torques import MASS_SOLVE_ENGINES
from wbc_jax.core import mjx as mjx_device
from wbc_jax.core import provenance
from wbc_jax.core.math import cholesky_solve
from wbc_jax.robot import dynamics
from wbc_jax.robot.model import load_robot
from wbc_jax.sim import physics


def parse_args(argv=None) -> argparse.Namespace:
    return checked(batch_parser(__doc__), argv)


def main(argv=None) -> dict:
    return measured(_measure, parse_args(argv), __file__, argv)


def _measure(a: argparse.Namespace) -> dict:
    robot = load_robot(a.robot)
    idx = robot.index
    qpos, qvel = (jnp.asarray(x) for x in states(robot, a.batch, a.seed))
    mx, d0 = mjx_device.put_model(robot.mj_model), mjx_device.make_data(robot.mj_model)
    M = jax.jit(jax.vmap(lambda q, v: dynamics.terms(mx, d0.replace(qpos=q, qvel=v), idx).M))(qpos, qvel)
    columns = 12 + 1 + (idx.nv - 6)  # two feet's wrenches, the bias, M^-1's joint columns
    B = jnp.asarray(np.random.default_rng(a.seed).normal(size=(a.batch, idx.nv, columns)), M.dtype)
    result = {
        "batch": a.batch,
        "robot": a.robot,
        "shape": {"M": [idx.nv, idx.nv], "B": [idx.nv, columns]},
        "dtype": str(M.dtype),
        "device": provenance.device_label(),
        "us_per_env": {},
        "skipped": {},
    }
    solves = {"jax": cholesky_solve}
    if physics.has_warp():
        from wbc_jax.control.cholesky_warp import cholesky_solve_warp

        solves["warp"] = cholesky_solve_warp
    else:
        result["skipped"]["warp"] = "warp-lang is not installed"
    outputs = {}
    for name in MASS_SOLVE_ENGINES:
        if name not in solves:
            continue
        fn = jax.jit(jax.vmap(solves[name]))
        outputs[name] = fn(M, B)
        result["us_per_env"][name] = round(timed(fn, M, B, repeats=a.repeats) * 1e6 / a.batch, 4)
    if "warp" in outputs:
        (L_j, X_j), (L_w, X_w) = outputs["jax"], outputs["warp"]
        result["warp_against_jax"] = {
            "L": float(jnp.max(jnp.abs(L_w - L_j)) / jnp.max(jnp.abs(L_j))),
            "X": float(jnp.max(jnp.abs(X_w - X_j)) / jnp.max(jnp.abs(X_j))),
        }
    return result


if __name__ == "__main__":
    main()
