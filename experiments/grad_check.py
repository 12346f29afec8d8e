"""Gradient check of the differentiable closed loop (issue: gradient-based gain tuning).

    python experiments/grad_check.py N [--out FILE]

Per-scenario reverse-mode gradients of the tuning loss over N random push scenarios (0.1 s horizon,
float64, random gains inside the bounds, random push magnitudes 0-150 N and azimuths), a count of
non-finite values, and central finite differences against the gradient for every gain group on
scenario 0: the tuned groups (CoM, angular momentum, postural) and the regularisation
(Reg.pinvDamp and Reg.KP_postural, as log-scale factors on their defaults 1 and 0.1). Prints one JSON line (and writes it to --out). tests/test_tune.py runs it with N = 24;
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

from wbc_jax import io, model, sweep, tune  # noqa: E402
from wbc_jax.gains import default_gains  # noqa: E402


FD_STEPS = (1e-3, 1e-4, 1e-5)  # central-difference steps in the (log-scale) parameters


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("n", type=int, help="number of random scenarios")
    parser.add_argument("--out", default=None, help="also write the JSON here")
    parser.add_argument("--fd-scenarios", type=int, default=3, help="scenarios checked by central differences")
    args = parser.parse_args()
    n = args.n
    robot = model.load_robot("icub")
    rng = np.random.default_rng(7)
    scfg = sweep.SweepConfig(magnitudes=(60.0,), directions=(0.0,), push_onset=0.02, push_duration=0.05,
                             horizon=0.1, joint_noise=0.02, friction=(0.6, 1.2), mass_scale=(0.9, 1.1),
                             gain_sets=n, seed=3, backend="jax")  # fmt: skip
    base = default_gains(robot.index.n, jnp.float64)
    bounds = tune.default_bounds(base)
    scen, _ = sweep.build_scenarios(scfg, base, robot.index.n, np.float64)
    # Random push magnitudes (0-150 N) and azimuths; random gains inside the bounds.
    az, mag = rng.uniform(0, 2 * np.pi, n), rng.uniform(0, 150, n)
    force = np.stack([mag * np.cos(az), mag * np.sin(az), np.zeros(n)], 1)[:, None]
    scen = scen.replace(push=scen.push.replace(force=force))
    params = {k: jnp.asarray(rng.normal(scale=0.7, size=(n,) + v.shape))
              for k, v in tune.gains_to_params(base, bounds).items()}  # fmt: skip
    params["regularisation"] = jnp.asarray(rng.normal(scale=0.3, size=(n, 2)))
    reg_default = jnp.asarray([1.0, 0.1])  # Reg.pinvDamp, Reg.KP_postural (ControllerConfig's)
    loss_fn = tune.make_batched_loss(robot.index.robot, scfg, tune.LossConfig(), checkpoint=True)

    def one(p, s):
        gains = tune.params_to_gains({k: v for k, v in p.items() if k != "regularisation"}, bounds, base)
        reg = reg_default * jnp.exp(p["regularisation"])
        reg = {"pinv_damping": reg[0], "kp_postural_reg": reg[1]}
        return loss_fn(gains, jax.tree_util.tree_map(lambda x: x[None], s), reg)[0]

    loss, grad = jax.jit(jax.vmap(jax.value_and_grad(one)))(params, scen)
    # Scenarios with any non-finite gradient entry, plus non-finite losses.
    nonfinite = int(sum(np.sum(~np.isfinite(np.asarray(g)).reshape(n, -1).all(1)) for g in grad.values())
                    + np.sum(~np.isfinite(np.asarray(loss))))  # fmt: skip
    # Central differences along a random direction per gain group, on the first K scenarios, at
    # three step sizes: where they agree (within 1 %) the loss is smooth at that scale and the
    # gradient must match them; where they do not, a contact or active-set change lies within the
    # step and no derivative is defined there.
    f = jax.jit(one)
    fd = {}
    for k in (*tune.TUNED_FIELDS, "regularisation"):
        d = rng.normal(size=params[k].shape[1:])
        rows = []
        for j in range(min(args.fd_scenarios, n)):
            pj = {g: v[j] for g, v in params.items()}
            sj = jax.tree_util.tree_map(lambda x: x[j], scen)  # noqa: B023
            fds = {}
            for eps in FD_STEPS:
                up, dn = {**pj, k: pj[k] + eps * d}, {**pj, k: pj[k] - eps * d}
                fds[str(eps)] = float((f(up, sj) - f(dn, sj)) / (2 * eps))
            a, b = fds[str(FD_STEPS[1])], fds[str(FD_STEPS[2])]
            smooth = abs(a - b) <= 0.01 * max(abs(a), abs(b)) and abs(b) > 1e-9
            ad = float(np.vdot(grad[k][j], d))
            rows.append({"scenario": j, "ad": ad, "fd": fds, "smooth": bool(smooth),
                         "rel_err": abs(ad - b) / max(abs(b), 1e-300)})  # fmt: skip
        fd[k] = rows
    result = {"nonfinite": nonfinite, "n": n, "loss": np.asarray(loss).tolist(), "fd": fd,
              "command": f"python experiments/grad_check.py {n}", "device": str(jax.devices()[0])}  # fmt: skip
    print(json.dumps(result))
    if args.out:
        io.atomic_write_json(pathlib.Path(args.out), result)


if __name__ == "__main__":
    main()
