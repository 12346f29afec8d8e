"""Gradient check of the differentiable closed loop (issue: gradient-based gain tuning).

    python experiments/grad_check.py N [--out FILE]

Per-scenario reverse-mode gradients of the tuning loss over N random push scenarios (0.1 s horizon,
float64, random gains inside the bounds, random push magnitudes 0-150 N and azimuths), a count of
non-finite values, and central finite differences against the gradient for every gain group on
scenario 0. Prints one JSON line (and writes it to --out). tests/test_tune.py runs it with N = 24;
docs/tuning/grad_check_100.json is N = 100. XLA's backend optimisation is lowered by the caller
(XLA_FLAGS) to keep the compile to minutes on a 2-core CPU.
"""

from __future__ import annotations

import argparse
import json
import pathlib

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from wbc_jax import controller as C  # noqa: E402
from wbc_jax import io, model, sweep, tune  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("n", type=int, help="number of random scenarios")
    parser.add_argument("--out", default=None, help="also write the JSON here")
    args = parser.parse_args()
    n = args.n
    robot = model.load_robot("icub")
    rng = np.random.default_rng(7)
    scfg = sweep.SweepConfig(magnitudes=(60.0,), directions=(0.0,), push_onset=0.02, push_duration=0.05,
                             horizon=0.1, joint_noise=0.02, friction=(0.6, 1.2), mass_scale=(0.9, 1.1),
                             gain_sets=n, seed=3)  # fmt: skip
    base = C.default_gains(robot.index.n, jnp.float64)
    bounds = tune.default_bounds(base)
    scen, _ = sweep.build_scenarios(scfg, base, robot.index.n, np.float64)
    # Random push magnitudes (0-150 N) and azimuths; random gains inside the bounds.
    az, mag = rng.uniform(0, 2 * np.pi, n), rng.uniform(0, 150, n)
    force = np.stack([mag * np.cos(az), mag * np.sin(az), np.zeros(n)], 1)[:, None]
    scen = scen.replace(push=scen.push.replace(force=force))
    params = {k: jnp.asarray(rng.normal(scale=0.7, size=(n,) + v.shape))
              for k, v in tune.gains_to_params(base, bounds).items()}  # fmt: skip
    loss_fn = tune.make_batched_loss(robot, scfg, tune.LossConfig(), checkpoint=True)

    def one(p, s):
        return loss_fn(tune.params_to_gains(p, bounds, base), jax.tree_util.tree_map(lambda x: x[None], s))[0]

    loss, grad = jax.jit(jax.vmap(jax.value_and_grad(one)))(params, scen)
    # Scenarios with any non-finite gradient entry, plus non-finite losses.
    nonfinite = int(sum(np.sum(~np.isfinite(np.asarray(g)).reshape(n, -1).all(1)) for g in grad.values())
                    + np.sum(~np.isfinite(np.asarray(loss))))  # fmt: skip
    # Central differences on scenario 0 at its random gains, a random direction per gain group.
    f = jax.jit(one)
    p0 = {k: v[0] for k, v in params.items()}
    s0 = jax.tree_util.tree_map(lambda x: x[0], scen)
    fd, eps = {}, 1e-4
    for k in tune.TUNED_FIELDS:
        d = rng.normal(size=p0[k].shape)
        up, dn = {**p0, k: p0[k] + eps * d}, {**p0, k: p0[k] - eps * d}
        fd[k] = [float((f(up, s0) - f(dn, s0)) / (2 * eps)), float(np.vdot(grad[k][0], d))]
    result = {"nonfinite": nonfinite, "n": n, "loss": np.asarray(loss).tolist(), "fd": fd,
              "command": f"python experiments/grad_check.py {n}", "device": str(jax.devices()[0])}  # fmt: skip
    print(json.dumps(result))
    if args.out:
        io.atomic_write_json(pathlib.Path(args.out), result)


if __name__ == "__main__":
    main()
