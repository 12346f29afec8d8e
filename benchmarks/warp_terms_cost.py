"""What the controller's dynamics terms would cost from MuJoCo Warp (issue 46), before building it.

On a GPU the tick's dynamics terms (``wbc_jax.robot.dynamics.terms``: MJX-JAX's kinematics and its JVP, crb, rne) cost
about 0.21 µs per environment at 65,536 (BENCHMARKS.md, "Where a tick's time goes on one H100"). MJX-Warp wraps
``forward``, which computes what they read (qM, qfrc_bias, qfrc_passive, cdof, cdof_dot, subtree_com, body poses) at
the state, beside collision and the constraint solve. This times, vmapped over ``--batch`` copies of the standing
state with small random joint offsets and velocities, µs per environment of:

- ``jax_terms``: ``dynamics.terms`` (the controller's model, MJX-JAX), as the tick computes them;
- ``warp_forward``: one MJX-Warp ``forward`` at the same states;
- ``warp_step``: one MJX-Warp ``step`` (for scale: ten of them are a control tick's physics).

    python benchmarks/warp_terms_cost.py --batch 65536 --out results/gpu_h100/warp_terms_cost.json

Engines that cannot run here (Warp without a GPU or warp-lang) are skipped and named in the result.
"""

import argparse
import json
import pathlib

import jax
import jax.numpy as jnp
import numpy as np

# from this script's folder (Python puts it first on sys.path): profile_tick's timing, so the figures compare with
# its dynamics_terms stage (the best of --repeats runs, compiled first)
from profile_tick import timed

from wbc_jax.core import io, provenance
from wbc_jax.core import mjx as mjx_device
from wbc_jax.robot import dynamics
from wbc_jax.robot.model import load_robot
from wbc_jax.sim import physics

ENGINES = ("jax_terms", "warp_forward", "warp_step")


def batch_parser(doc: str) -> argparse.ArgumentParser:
    """The flags of a vmapped cost script (this one, mass_solve_cost.py): --batch, --repeats, --robot, --seed, --out;
    check them with :func:`checked`."""
    p = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--batch", type=int, default=1024)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--robot", default="icub")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None, help="JSON file of the result (written atomically)")
    return p


def checked(p: argparse.ArgumentParser, argv) -> argparse.Namespace:
    """The parsed flags of :func:`batch_parser`'s parser, refused as argparse does where --batch or --repeats < 1."""
    a = p.parse_args(argv)
    if a.batch < 1 or a.repeats < 1:
        p.error(f"--batch and --repeats must be >= 1, got {a.batch} and {a.repeats}")
    return a


def parse_args(argv=None) -> argparse.Namespace:
    p = batch_parser(__doc__)
    p.add_argument("--engines", nargs="+", default=list(ENGINES), choices=ENGINES)
    return checked(p, argv)


def measured(measure, a: argparse.Namespace, script: str, argv) -> dict:
    """A cost script's run (this folder's mass_solve_cost.py, projector_cost.py): ``measure(a)`` at the closed loop's
    matmul precision (SimConfig.matmul_precision: "highest"), with its provenance, printed, and written atomically
    to ``a.out`` where given."""
    with jax.default_matmul_precision("highest"):
        result = measure(a)
    result["provenance"] = provenance.record(argv=provenance.script_argv(script, argv))
    print(json.dumps(result, indent=1))
    if a.out:
        io.atomic_write_json(pathlib.Path(a.out), result)
    return result


def states(robot, batch: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(qpos (B, nq), qvel (B, nv)): the standing posture with joint offsets of 0.05 rad and velocities of 0.2 rad/s."""
    rng = np.random.default_rng(seed)
    idx = robot.index
    qpos = np.tile(robot.home_qpos(), (batch, 1)).astype(np.float32)
    qpos[:, idx.qpos_joints] += rng.normal(0.0, 0.05, size=(batch, len(idx.qpos_joints)))
    qvel = rng.normal(0.0, 0.2, size=(batch, idx.nv)).astype(np.float32)
    return qpos, qvel


def main(argv=None) -> dict:
    a = parse_args(argv)
    with jax.default_matmul_precision("highest"):  # the closed loop's (SimConfig.matmul_precision)
        return _measure(a, argv)


def _measure(a: argparse.Namespace, argv) -> dict:
    robot = load_robot(a.robot)
    qpos, qvel = (jnp.asarray(x) for x in states(robot, a.batch, a.seed))
    result = {"batch": a.batch, "robot": a.robot, "device": provenance.device_label(), "us_per_env": {}, "skipped": {}}

    def us_per_env(fn) -> float:  # fn(qpos, qvel) of one environment, vmapped over the batch
        return timed(jax.jit(jax.vmap(fn)), qpos, qvel, repeats=a.repeats) * 1e6 / a.batch

    if "jax_terms" in a.engines:  # the controller's model and data, as the loop builds them (sim/loop.py)
        mx, d0 = mjx_device.put_model(robot.mj_model), mjx_device.make_data(robot.mj_model)
        result["us_per_env"]["jax_terms"] = us_per_env(
            lambda q, v: dynamics.terms(mx, d0.replace(qpos=q, qvel=v), robot.index)
        )
    warp = [e for e in a.engines if e.startswith("warp_")]
    if warp:
        try:
            physics.resolve_backend("warp")
        except ValueError as err:  # no GPU or no warp-lang: named in the result, the rest measured
            result["skipped"].update({e: str(err) for e in warp})
            warp = []
    if warp:
        # Warp's CUDA graphs on a GPU (MJX's default); none on Warp's CPU backend (WBC_JAX_WARP_ON_CPU=1)
        cfg = physics.PhysicsConfig(backend="warp", warp_graph_mode="warp" if physics.has_cuda() else "none")
        mw = physics.device_model(robot.mj_model, "warp", cfg)
        dw = physics.device_data(robot.mj_model, "warp", cfg, robot.home_qpos(), jnp.float32, batch=a.batch)
        fns = {"warp_forward": mjx_device.mjx.forward, "warp_step": mjx_device.mjx.step}
        for name in warp:
            result["us_per_env"][name] = us_per_env(lambda q, v, fn=fns[name]: fn(mw, dw.replace(qpos=q, qvel=v)))
    result["us_per_env"] = {k: round(v, 4) for k, v in result["us_per_env"].items()}
    result["provenance"] = provenance.record(argv=provenance.script_argv(__file__, argv))
    print(json.dumps(result, indent=1))
    if a.out:
        io.atomic_write_json(pathlib.Path(a.out), result)
    return result


if __name__ == "__main__":
    main()
