"""Gain tuning on every local GPU against one GPU: the same loss and gradient, and the speed-up (issue 45).

    python experiments/checks/tune_gpus_check.py --out DIR [--repeats 3] [--max-rel-diff 1e-3] [-- TUNE FLAGS]

At the race's settings (experiments/campaigns/race_piece.sh: batch 2,048 rollouts of 2 s, the implicit solver
gradient, a checkpoint per tick, CMA-ES with 16 candidates x 60 pushes on --search-backend auto; TUNE FLAGS,
``wbc-jax tune``'s, come after them and win), in one process, first on the first device alone and then on all N
local devices (one single-device program per device, :class:`wbc_jax.tuning.algorithms.objectives.DevicePrograms`):

* the gradient step of the training (``GradientStep``): its compile, the gradient of step 0 (its rollouts'
  values and gradients combined by the estimator) and its loss; then ``--repeats`` whole steps (push sampling,
  the gradient program, the optimiser step, the transfer), their median the step's seconds;
* the CMA-ES search (``baselines.search``): its compile, then 1 + ``--repeats`` generations; generation 0's
  objective of the mean and its best and median candidates, the median of the later generations' seconds.

On N devices the N per-device shares of step 0's rollouts are also run one after another on the first device
(the per-device program's shape) and combined alike: what the split and gather must give exactly; they run twice,
and the second run, the same executable on the same device from the same inputs, is the device's repeat floor (on a
GPU not zero: XLA's atomics round in another order each run, and the closed loop grows it; ``XLA_FLAGS=
--xla_gpu_deterministic_ops=true`` asks XLA for determinism). Against one
device's whole batch they differ by float32 rounding of another batch shape, grown through the closed loop's ticks
(two host CPU devices, batch 4 of 0.3 s: rollout values 0.8 % apart, the gradient 17 % of its largest entry; in
float64 bit-equal, tests/test_tune_devices.py).

DIR/tune_gpus.json holds per device count the figures above, the devices that ran the last call, and the
comparison: the largest difference of the N-device gradient from the shares run on one device and from the
one-device whole batch, relative to the latter's largest entry, the shares' own difference from the whole batch
(the float noise), the losses' and objectives' relative differences, the speed-ups (one device's seconds over N's),
with provenance (command, device names). Exits 1 when the N-device gradient differs from the shares' by more than
``--max-rel-diff`` or fewer than two devices are there.
Compiled programs go to JAX's persistent cache (``$WBC_JAX_CACHE``): a call cut off by a time limit leaves them
for the next. The one-device half's figures are written to DIR/tune_gpus_one_device.json as soon as it ends; a later
call with the same tune flags, --repeats and device kind takes them from there and runs only the N-device half. On a CPU, host devices: ``XLA_FLAGS=--xla_force_host_platform_device_count=2``.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import sys
import tempfile
import time

import numpy as np

from wbc_jax.core import checks, io, provenance

MAX_REL_DIFF = 1e-3  # default bound: float32 rounding of other per-device batch shapes through the closed loop
# Where the device is not deterministic run to run, the bound is this many times the shares' own repeat. On
# 2 x H200 (results/tuning/tune_gpus_h200x2_s56/) the same executable on the same device from the same inputs gave
# other values in 1023 of 1024 rollouts (median 0.38 %, the chaotic closed loop growing XLA's atomics' rounding);
# the three noise-level gradient differences there (whole batch vs shares 0.162, 2 devices vs shares 0.184, vs the
# whole batch 0.219 of the largest entry) lie within 1.35x of each other, the rollouts' medians within 1.03x.
FLOOR_FACTOR = 2.0
BAR = (
    "the N-device gradient (relative to its largest entry) and its rollouts' values (the median relative difference) "
    f"within --max-rel-diff (default {MAX_REL_DIFF:g}) of the same per-device shares run one after another on the "
    f"first device, or within {FLOOR_FACTOR:g}x those shares' own repeat there where the device is not deterministic "
    "(the split and gather exact; the difference from one device's whole batch, float32 rounding of another batch "
    "shape through the closed loop, is reported beside it); every device's share of the last step finished"
)
RACE_FLAGS = [
    "--batch",
    "2048",
    "--quality-pushes",
    "2048",
    "--horizon",
    "2",
    "--solver-gradient",
    "implicit",
    "--checkpoint",
    "tick",
    "--lr",
    "0.1",
    "--push-scale",
    "lip",
    "--magnitude-range",
    "0.3",
    "1.0",
    "--init-gains",
    "assets/gains/com_critical_100.json",
    "--population",
    "16",
    "--es-batch",
    "60",
    "--search-backend",
    "auto",
]


def tune_config(flags: list[str]):
    """The checked config of ``wbc-jax tune RACE_FLAGS FLAGS`` (later flags win)."""
    from wbc_jax import cli
    from wbc_jax.tuning import config

    return cli.config_from_args(cli.build_parser().parse_args(["tune", *RACE_FLAGS, *flags]), config.TuneConfig())


def measure(problem, devices: list, repeats: int, work: pathlib.Path) -> dict:
    """The gradient step's and a CMA-ES generation's figures on ``devices`` (module docstring)."""
    import jax
    import jax.numpy as jnp
    from jax.sharding import Mesh

    from wbc_jax.tuning.algorithms import baselines, estimators, gradient

    tc = problem.tc
    mesh = Mesh(np.asarray(devices), ("batch",))
    step = gradient.GradientStep(problem, gradient.make_optimizer(tc.lr, tc.clip_norm), mesh)
    params = problem.init_params()
    opt_state = step.optimizer.init(params)
    compile_s = step.compile(params, opt_state)
    params_b, eps, rollouts, _, _ = step.rows_of(params, 0)
    values, grads, _, _ = step.grads(params_b, rollouts)
    combine = jax.jit(
        lambda v, g, e: estimators.combine(
            tc.estimator, v, g, e, sigma=tc.smoothing_sigma, clip_factor=tc.env_clip, bias_factor=tc.bias_factor
        )
    )
    grad, stats = combine(jnp.asarray(values), jax.tree_util.tree_map(jnp.asarray, grads), eps)
    shares = []
    # The same shares, one after another on the first device (what the split must give), twice: the second run is
    # the repeat floor, what the same executable gives again on the same device from the same inputs.
    for _ in range(2 if len(devices) > 1 else 0):
        on_first = shares_on_first_device(step.grads, params_b, rollouts, devices[0], len(devices))
        shares_grad, _ = combine(*on_first[:2], eps)
        shares.append({"values": np.asarray(on_first[0], float).tolist(), "gradient": flat(shares_grad)})
    values = np.asarray(values, float)
    _, _, first = step(params, opt_state, 0)  # its first call: what compiles lazily (the host-side programs)
    step_s = []
    for k in range(1, repeats + 1):
        t0 = time.perf_counter()
        step(params, opt_state, k)
        step_s.append(time.perf_counter() - t0)
    ran_on = list(step.grads.ran_on)
    found = baselines.search(
        problem,
        "cmaes",
        work / f"cmaes_{len(devices)}",
        budget={"sim_steps": 10**15, "wall_s": 0.0},
        max_generations=1 + repeats,
        progress=False,
        mesh=mesh,
    )
    gens = found["history"]
    return {
        "devices": len(devices),
        "ran_on": ran_on,
        "compile_s": round(compile_s, 2),
        "loss": float(first["loss"]),
        "finite_rollouts": int(np.isfinite(values).sum()),
        "values": values.tolist(),
        "gradient": flat(grad),
        "shares_on_first_device": shares[0] if shares else None,
        "shares_repeat_on_first_device": shares[1] if shares else None,
        "nonfinite_envs": int(stats["nonfinite_envs"]),
        "step_s": [round(s, 4) for s in step_s],
        "step_s_median": float(np.median(step_s)),
        "cmaes": {
            "compile_s": found["compile_s"],
            "gen_s": [float(r["gen_s"]) for r in gens],
            "gen_s_median": float(np.median([float(r["gen_s"]) for r in gens[1:]] or [np.nan])),
            "generation_0": {k: float(gens[0][k]) for k in ("loss", "best_candidate_loss", "median_candidate_loss")},
        },
    }


def flat(tree) -> list[float]:
    """A gradient pytree as one flat list."""
    from jax.flatten_util import ravel_pytree

    return np.asarray(ravel_pytree(tree)[0], float).tolist()


def shares_on_first_device(grads, params_b, rollouts, device, n: int) -> tuple:
    """(values (B,), per-rollout grads {group: (B, ...)}) of the N-device program's own executable for ``device``
    (``grads.program.compiled[device]``, :class:`wbc_jax.sim.per_device.PerDevice`) run over the batch's ``n``
    contiguous shares one after another, concatenated in batch order. Reusing that executable costs no trace or
    compile (a fresh ``jit`` of the reverse-mode closed loop took minutes on the GPU machine, 2026-11-26)."""
    import jax
    import jax.numpy as jnp

    if grads.pre is not None or grads.post is not None:
        raise ValueError(
            "shares_on_first_device: the gradient program has a pre or post stage; expected its core alone"
        )
    program = grads.program.compiled[device]
    size = int(jax.tree_util.tree_leaves(rollouts)[0].shape[0]) // n
    outs = []
    for k in range(n):
        rows = slice(k * size, (k + 1) * size)
        share = jax.tree_util.tree_map(
            lambda x, rows=rows: jax.device_put(np.asarray(x)[rows], device), (params_b, rollouts)
        )
        outs.append(jax.device_get(program(*share)[:2]))
    return jax.tree_util.tree_map(lambda *xs: jnp.concatenate(xs), *outs)


def relative(a, b) -> float:
    """max |a - b| / max |b| over finite entries of b (NaN when b has none)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    ok = np.isfinite(b)
    if not ok.any():
        return float("nan")
    scale = max(float(np.max(np.abs(b[ok]))), 1e-300)
    return float(np.max(np.abs(a[ok] - b[ok])) / scale) if np.isfinite(a[ok]).all() else float("inf")


def median_relative(a, b) -> float:
    """The median over finite entries of b of |a - b| / |b| (inf where a is not finite there; NaN when b has none)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    ok = np.isfinite(b)
    if not ok.any():
        return float("nan")
    rel = np.abs(a[ok] - b[ok]) / np.maximum(np.abs(b[ok]), 1e-300)
    return float(np.median(np.where(np.isfinite(rel), rel, np.inf)))


def compare(one: dict, many: dict, bound: float) -> dict:
    """The N-device figures against one device's: relative differences and speed-ups."""
    shares, repeat = many.get("shares_on_first_device"), many.get("shares_repeat_on_first_device")
    against_shares = {}
    if shares:
        against_shares = {
            "gradient_vs_shares_max_rel_diff": relative(many["gradient"], shares["gradient"]),
            "rollout_values_vs_shares_max_rel_diff": relative(many["values"], shares["values"]),
            "rollout_values_vs_shares_median_rel_diff": median_relative(many["values"], shares["values"]),
            "shares_vs_one_gradient_max_rel_diff": relative(shares["gradient"], one["gradient"]),
        }
    if shares and repeat:  # the repeat floor: the same executable, device and inputs again
        against_shares["repeat_gradient_max_rel_diff"] = relative(repeat["gradient"], shares["gradient"])
        against_shares["repeat_rollout_values_median_rel_diff"] = median_relative(repeat["values"], shares["values"])
    return {
        **against_shares,
        "gradient_max_rel_diff": relative(many["gradient"], one["gradient"]),
        "loss_rel_diff": relative([many["loss"]], [one["loss"]]),
        "rollout_values_max_rel_diff": relative(many["values"], one["values"]),
        "finiteness_differs": int(np.sum(np.isfinite(many["values"]) != np.isfinite(one["values"]))),
        "cmaes_generation_0_rel_diff": {
            k: relative([many["cmaes"]["generation_0"][k]], [one["cmaes"]["generation_0"][k]])
            for k in one["cmaes"]["generation_0"]
        },
        "step_speedup": one["step_s_median"] / many["step_s_median"],
        "cmaes_generation_speedup": one["cmaes"]["gen_s_median"] / many["cmaes"]["gen_s_median"],
        "max_rel_diff_bound": bound,
    }


def failures(result: dict) -> list[str]:
    """The gradient, or the rollouts' values, apart from the shares' by more than the bound: --max-rel-diff, or
    FLOOR_FACTOR x the shares' own repeat where that is larger (or any of them not finite); a device whose share did
    not run."""
    cmp, many = result["comparison"], result["all"]
    out, n = [], many["devices"]
    floor = {k: cmp.get(f"repeat_{k}") for k in ("gradient_max_rel_diff", "rollout_values_median_rel_diff")}
    if any(v is not None and not np.isfinite(v) for v in floor.values()):
        out.append(f"the shares' repeat on one device is not finite: {floor}")
    if "gradient_vs_shares_max_rel_diff" in cmp:
        diff, against = cmp["gradient_vs_shares_max_rel_diff"], "the same shares on one device"
    else:
        diff, against = cmp["gradient_max_rel_diff"], "one device's"
    checked = [("gradient differs", diff, "of its largest entry", floor["gradient_max_rel_diff"])]
    if "rollout_values_vs_shares_median_rel_diff" in cmp:
        checked.append(
            ("rollouts' values differ", cmp["rollout_values_vs_shares_median_rel_diff"], "in the median",
             floor["rollout_values_median_rel_diff"])
        )  # fmt: skip
    for what, value, how, repeat in checked:
        bound, bound_text = cmp["max_rel_diff_bound"], f"{cmp['max_rel_diff_bound']:g}"
        if repeat is not None and np.isfinite(repeat) and FLOOR_FACTOR * repeat > bound:
            bound, bound_text = (
                FLOOR_FACTOR * repeat,
                f"{FLOOR_FACTOR:g} x the shares' own repeat, {FLOOR_FACTOR * repeat:.3g}",
            )
        if not value <= bound:  # NaN fails too
            out.append(f"the {n}-device {what} from {against} by {value:.3g} {how} (bound {bound_text})")
    if len(set(many["ran_on"])) != many["devices"]:
        out.append(f"the {many['devices']}-device step's last call finished on {many['ran_on']} only")
    return out


ONE_DEVICE_FILE = "tune_gpus_one_device.json"


def one_device_half(path: pathlib.Path, half: dict) -> dict | None:
    """The one-device figures an earlier call with the same tune flags, repeats and device kind left in ``path``
    (written as soon as that half finished, so a call cut off in the N-device half loses nothing); None when there
    are none or they were measured otherwise."""
    try:
        earlier = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(earlier, dict) or any(earlier.get(k) != v for k, v in half.items()) or "one" not in earlier:
        return None
    print(f"one device: the figures of an earlier call ({path})", flush=True)
    return earlier["one"]


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=f"Check: {BAR}; exit status 1 otherwise.",
    )
    parser.add_argument("--out", required=True, help="folder of tune_gpus.json")
    parser.add_argument("--repeats", type=int, default=3, help="timed steps and generations after the first")
    parser.add_argument(
        "--max-rel-diff",
        type=float,
        default=MAX_REL_DIFF,
        help="bound of the gradients' largest difference relative to the one-device gradient's largest entry",
    )
    raw = list(sys.argv[1:] if argv is None else argv)
    split = raw.index("--") if "--" in raw else len(raw)
    args = parser.parse_args(raw[:split])
    if args.repeats < 1 or not 0.0 < args.max_rel_diff < 1.0:
        parser.error(
            f"--repeats must be >= 1 (got {args.repeats}) and --max-rel-diff in (0, 1) (got {args.max_rel_diff:g})"
        )
    tc = tune_config(raw[split + 1 :])  # a bad tune flag: the job's own one-line error, before anything compiles

    import jax

    from wbc_jax.sim import runner
    from wbc_jax.tuning.algorithms import problem as tp

    devices = jax.devices()
    if len(devices) < 2:
        parser.error(
            f"needs at least 2 devices, this machine has {len(devices)} ({devices[0].platform}); on a CPU "
            "set XLA_FLAGS=--xla_force_host_platform_device_count=2"
        )
    runner.enable_compilation_cache()
    problem = tp.make_problem(tc)
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    half = {
        "tune_flags": [*RACE_FLAGS, *raw[split + 1 :]],
        "repeats": args.repeats,
        "device": devices[0].device_kind,
        "xla_flags": os.environ.get("XLA_FLAGS", ""),  # deterministic ops or not: other numbers, other speed
    }
    with tempfile.TemporaryDirectory() as work:
        one = one_device_half(out / ONE_DEVICE_FILE, half)
        if one is None:
            one = measure(problem, devices[:1], args.repeats, pathlib.Path(work))
            record = {**half, "one": one, "provenance": provenance.record({"init_gains": tc.init_gains})}
            io.atomic_write_json(out / ONE_DEVICE_FILE, record)  # a call cut off later keeps it
        print(json.dumps({"devices": 1, "step_s_median": one["step_s_median"], "loss": one["loss"]}), flush=True)
        many = measure(problem, devices, args.repeats, pathlib.Path(work))
    result = {
        "comparison": compare(one, many, args.max_rel_diff),
        "one": one,
        "all": many,
        "device_names": sorted({d.device_kind for d in devices}),
        "tune_flags": [*RACE_FLAGS, *raw[split + 1 :]],
        "xla_flags": half["xla_flags"],
        "provenance": provenance.record({"init_gains": tc.init_gains}),
    }
    result["check"] = checks.verdict(failures(result), BAR)
    io.atomic_write_json(out / "tune_gpus.json", result)
    summary = {
        k: result["comparison"][k]
        for k in (
            "gradient_vs_shares_max_rel_diff",
            "repeat_gradient_max_rel_diff",
            "rollout_values_vs_shares_median_rel_diff",
            "repeat_rollout_values_median_rel_diff",
            "shares_vs_one_gradient_max_rel_diff",
            "gradient_max_rel_diff",
            "loss_rel_diff",
            "step_speedup",
            "cmaes_generation_speedup",
        )
        if k in result["comparison"]
    }
    print(json.dumps({**summary, "passed": result["check"]["passed"]}))
    return result


if __name__ == "__main__":
    sys.exit(checks.exit_status(main()))
