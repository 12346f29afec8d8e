"""Gradient check of the differentiable closed loop on the tuning loss (issues 5, 20).

    python experiments/checks/grad_check.py N [--out FILE] [--qp-warm-start]

Per-scenario reverse-mode gradients of the tuning loss (wbc_jax/tuning/algorithms/loss.py: capture point,
foot tilt and slip, settling, CoM, effort; log1p of the total) over N random push scenarios
(0.1 s horizon, float64, random parameters of every group inside the bounds, random push
magnitudes 0-150 N and azimuths, friction 0.6-1.2, mass +-10 %, joint noise), a count of
non-finite values, and central finite differences against the gradient for every parameter
group on the first scenarios: the CoM, angular-momentum and postural gains and damping ratios and
the regularisation (Reg.pinvDamp, Reg.KP_postural). Prints one JSON line (and writes it to
--out). tests/test_tune.py runs it with N = 24; results/tuning/grad_check_100.json is N = 100.
XLA's backend optimisation is lowered by the caller (XLA_FLAGS) to keep the compile to minutes on
a 2-core CPU.

The check (:func:`failures`): every loss and gradient finite; in every parameter group at least
one scenario where the central differences agree (the loss is smooth at that scale), and on each
such scenario the gradient within ``MAX_REL_ERR`` (5 %) of them; exit status 1 otherwise.
"""

from __future__ import annotations

import argparse
import json
import math
import pathlib
import sys

import numpy as np

from wbc_jax.core import checks, provenance

FD_STEPS = (1e-3, 1e-4, 1e-5)  # central-difference steps in the (unconstrained) parameters
MAX_REL_ERR = 0.05
BAR = (
    f"no non-finite loss or gradient; per parameter group a smooth scenario, and the gradient within "
    f"{100 * MAX_REL_ERR:g} % of the central differences on every smooth one"
)


def failures(result: dict) -> list[str]:
    """Non-finite values; groups without a smooth scenario; smooth scenarios off by more than MAX_REL_ERR."""
    out = [f"{result['nonfinite']} non-finite losses or gradients"] if result["nonfinite"] else []
    out += [f"non-finite loss of scenario {i}" for i, v in enumerate(result["loss"]) if not math.isfinite(v)]
    for group in result.get("groups", result["fd"]):
        rows = result["fd"].get(group, [])
        smooth = [r for r in rows if r["smooth"]]
        if not smooth:
            out.append(f"{group}: the central differences disagree between steps on every scenario checked")
        out += [
            f"{group}, scenario {r['scenario']}: gradient {r['ad']:.6g} vs central difference "
            f"{r['fd'][str(FD_STEPS[2])]:.6g} ({100 * r['rel_err']:.2f} % > {100 * MAX_REL_ERR:g} %)"
            for r in smooth
            if not r["rel_err"] < MAX_REL_ERR
        ]
    return out


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=f"Check: {BAR}; exit status 1 otherwise.",
    )
    parser.add_argument("n", type=int, help="number of random scenarios")
    parser.add_argument("--out", default=None, help="also write the JSON here")
    parser.add_argument("--fd-scenarios", type=int, default=3, help="scenarios checked by central differences")
    parser.add_argument(
        "--qp-warm-start",
        action="store_true",
        help="the force QP warm-started from the last tick's solution (ControllerConfig.qp_warm_start)",
    )
    args = parser.parse_args(argv)
    n = args.n
    if n < 1:
        parser.error("N must be >= 1")
    import jax

    jax.config.update("jax_enable_x64", True)  # before any array is made
    import jax.numpy as jnp

    from wbc_jax.control.flags import ControllerFlags
    from wbc_jax.core import io
    from wbc_jax.tuning import config
    from wbc_jax.tuning.algorithms import params as tuning_params
    from wbc_jax.tuning.algorithms import problem as tp

    rng = np.random.default_rng(7)
    tc = config.TuneConfig(
        horizon=0.1,
        push_onset=0.02,
        duration_range=(0.05, 0.05),
        joint_noise=0.02,
        friction_range=(0.6, 1.2),
        mass_range=(0.9, 1.1),
        tune_regularisation=True,
        eval_horizon=0.1,
        controller=ControllerFlags(qp_warm_start=args.qp_warm_start),
    )
    problem = tp.make_problem(tc, checkpoint=True)
    robot = problem.robot
    # Random push magnitudes (0-150 N) and azimuths on the chest; random plant and posture.
    az, mag = rng.uniform(0, 360, n), rng.uniform(0, 150, n)
    scen, _ = tp.pushes_at(
        robot,
        az,
        mag * 0.05,
        np.full(n, robot.index.body_id("chest")),
        np.full(n, 0.05),
        tc.push_onset,
        rng.uniform(0.6, 1.2, n),
        rng.uniform(0.9, 1.1, n),
        rng.normal(scale=0.02, size=(n, robot.index.n)),
        np.float64,
    )
    # Random parameters of every group inside the bounds, around the start.
    p0 = problem.init_params()
    params = {
        k: jnp.asarray(v + rng.normal(scale=0.3 if k == "regularisation" else 0.7, size=(n,) + v.shape))
        for k, v in p0.items()
    }
    loss_fn = tp.make_batched_loss(problem, fixed_solver=True)

    def one(p, s):
        gains, reg = problem.controls(p)
        return loss_fn(gains, reg, jax.tree_util.tree_map(lambda x: x[None], s))[0]

    loss, grad = jax.jit(jax.vmap(jax.value_and_grad(one)))(params, scen)
    # Scenarios with any non-finite gradient entry, plus non-finite losses.
    nonfinite = int(
        sum(np.sum(~np.isfinite(np.asarray(g)).reshape(n, -1).all(1)) for g in grad.values())
        + np.sum(~np.isfinite(np.asarray(loss)))
    )
    # Central differences along a random direction per group, on the first K scenarios, at three
    # step sizes: where they agree (within 1 %) the loss is smooth at that scale and the gradient
    # must match them; where they do not, a contact or active-set change lies within the step and
    # no derivative is defined there.
    f = jax.jit(one)
    fd = {}
    for k in tuning_params.PARAM_GROUPS:
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
            rows.append(
                {
                    "scenario": j,
                    "ad": ad,
                    "fd": fds,
                    "smooth": bool(smooth),
                    "rel_err": abs(ad - b) / max(abs(b), 1e-300),
                }
            )
        fd[k] = rows
    result = {
        "nonfinite": nonfinite,
        "n": n,
        "loss": np.asarray(loss).tolist(),
        "fd": fd,
        "groups": list(tuning_params.PARAM_GROUPS),
        "device": provenance.device_label(),
        "provenance": provenance.record(argv=provenance.script_argv(__file__, argv)),
    }
    result["check"] = checks.verdict(failures(result), BAR)
    print(json.dumps(result))
    if args.out:
        io.atomic_write_json(pathlib.Path(args.out), result)
    return result


if __name__ == "__main__":
    sys.exit(checks.exit_status(main()))
