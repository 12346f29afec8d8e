"""Where do reverse-mode gradients and central differences part? (diagnostic for grad_check.py)

    python experiments/grad_check_sources.py VARIANT [--n 100] [--scenario 0] --out FILE

Scenario ``--scenario`` of ``experiments/grad_check.py N`` (same random draws), one gradient and
central differences (step 1e-4, 1e-5) per gain group, with one approximation of the derivative
changed: VARIANT ``default``; ``frozen-projector`` (hold the postural projector
P = pinv(N_Lambda Mbar) N_Lambda Mbar constant in derivatives, the default until 2026-11-23);
``analytic`` (contact forces without the QP, whose implicit derivative is taken at its interior
final iterate). Result (docs/tuning/grad_check_sources.json): the frozen projector alone made the
gradients differ by up to 9 %.
"""

from __future__ import annotations

import argparse
import json
import pathlib

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from wbc_jax.control.controller import ControllerConfig  # noqa: E402
from wbc_jax.control.gains import default_gains  # noqa: E402
from wbc_jax.core import io  # noqa: E402
from wbc_jax.jobs import sweep, sweep_config  # noqa: E402
from wbc_jax.robot import model  # noqa: E402
from wbc_jax.tuning import tune  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("variant", choices=["default", "frozen-projector", "analytic"])
    parser.add_argument("--n", type=int, default=100)
    parser.add_argument("--scenario", type=int, default=0)
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    n, j = args.n, args.scenario
    controller = ControllerConfig(freeze_postural_projector=args.variant == "frozen-projector")
    robot = model.load_robot("icub")
    rng = np.random.default_rng(7)  # the draws of grad_check.py, in its order
    scfg = sweep_config.SweepConfig(magnitudes=(60.0,), directions=(0.0,), push_onset=0.02, push_duration=0.05,
                             horizon=0.1, joint_noise=0.02, friction=(0.6, 1.2), mass_scale=(0.9, 1.1),
                             gain_sets=n, seed=3, backend="jax",
                             forces="analytic" if args.variant == "analytic" else "qp")  # fmt: skip
    base = default_gains(robot.index.n, jnp.float64)
    bounds = tune.default_bounds(base)
    scen, _ = sweep.build_scenarios(scfg, base, robot.index.n, np.float64)
    az, mag = rng.uniform(0, 2 * np.pi, n), rng.uniform(0, 150, n)
    force = np.stack([mag * np.cos(az), mag * np.sin(az), np.zeros(n)], 1)[:, None]
    scen = scen.replace(push=scen.push.replace(force=force))
    params = {k: jnp.asarray(rng.normal(scale=0.7, size=(n,) + v.shape))
              for k, v in tune.gains_to_params(base, bounds).items()}  # fmt: skip
    params["regularisation"] = jnp.asarray(rng.normal(scale=0.3, size=(n, 2)))
    reg_default = jnp.asarray([1.0, 0.1])
    loss_fn = tune.make_batched_loss(robot.index.robot, scfg, tune.LossConfig(), checkpoint=True, controller=controller)

    def one(p, s):
        gains = tune.params_to_gains({k: v for k, v in p.items() if k != "regularisation"}, bounds, base)
        reg = reg_default * jnp.exp(p["regularisation"])
        return loss_fn(gains, jax.tree_util.tree_map(lambda x: x[None], s),
                       {"pinv_damping": reg[0], "kp_postural_reg": reg[1]})[0]  # fmt: skip

    pj = {g: v[j] for g, v in params.items()}
    sj = jax.tree_util.tree_map(lambda x: x[j], scen)
    loss, grad = jax.jit(jax.value_and_grad(one))(pj, sj)
    f = jax.jit(one)
    out = {}
    for k in (*tune.TUNED_FIELDS, "regularisation"):  # the directions of grad_check.py
        d = rng.normal(size=params[k].shape[1:])
        fds = [float((f({**pj, k: pj[k] + e * d}, sj) - f({**pj, k: pj[k] - e * d}, sj)) / (2 * e))
               for e in (1e-4, 1e-5)]  # fmt: skip
        ad = float(np.vdot(grad[k], d))
        out[k] = {"ad": ad, "fd_1e-4": fds[0], "fd_1e-5": fds[1], "rel_err": abs(ad - fds[1]) / abs(fds[1])}
    result = {"variant": args.variant, "n": n, "scenario": j, "loss": float(loss), "groups": out,
              "finite": bool(all(np.all(np.isfinite(np.asarray(g))) for g in grad.values()))}  # fmt: skip
    print(json.dumps(result))
    io.atomic_write_json(pathlib.Path(args.out), result)


if __name__ == "__main__":
    main()
