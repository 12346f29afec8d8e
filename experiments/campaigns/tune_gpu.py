"""Issue 20 in one command: does the loss predict survival, gradient tuning at scale, CMA-ES and
random search at equal simulated steps (and equal wall time), held-out evaluation, figures.

    python experiments/campaigns/tune_gpu.py --out runs/tune_gpu [--quick] [--phases ...] [sizes]

Phases (each resumable: run again with the same --out and it continues where it stopped):

* ``predict``: the loss against strict survival on --predict-pushes held-out pushes (Spearman, ROC
  area, survival_vs_loss.png, prediction.json);
* ``train``: gradient tuning (wbc_jax/tuning/tune.py), --steps x --batch pushes, history + checkpoint;
* ``cmaes``, ``random``: the baselines (wbc_jax/tuning/baselines.py) until both the gradient run's
  simulated physics steps and its wall time are spent;
* ``heldout``: default, gradient, cmaes, random (equal steps), cmaes_wall, random_wall (equal wall
  time) and the hand-set critical gains on the held-out grid, the unseen variations, the one-foot
  task and the 20 s sinusoid (wbc_jax/tuning/heldout.py);
* ``report``: heldout.json, envelope_polar.png, learning_curves.png, summary.json.

Every TuneConfig field is a flag (``wbc-jax tune``'s); --quick shrinks every size for a CPU check.
The persistent compilation cache is on (--cache). On the GPU machine, experiments/campaigns/tune_gpu.sh
installs the carried wheels and sets XLA's flags first.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import pathlib
import sys
import time

ROOT = pathlib.Path(__file__).resolve().parents[2]

PHASES = ("predict", "train", "cmaes", "random", "heldout", "report")
QUICK = dict(steps=2, batch=2, horizon=0.6, push_onset=0.05, duration_range=(0.05, 0.15), population=2, es_batch=1,
             eval_horizon=0.8, eval_pushes=2, wall_budget=False)  # fmt: skip
QUICK_HELDOUT = dict(magnitudes=(20.0, 200.0, 3), directions=4, variation_magnitudes=2, variation_directions=2,
                     horizon=1.0, onset=0.2, one_foot_onset=7.5, one_foot_horizon=7.8, sinusoid_s=0.5,
                     variations=("l_hand", "duration_0.02s"))  # fmt: skip


def parse(argv=None):
    from wbc_jax import cli
    from wbc_jax.tuning import tune

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    cli.add_config_arguments(p, tune.default_config(), skip=("out",))
    p.add_argument("--out", default="runs/tune_gpu", help="output folder (default: runs/tune_gpu)")
    p.add_argument("--quick", action="store_true", help="tiny sizes (a CPU check of the whole pipeline)")
    p.add_argument("--phases", nargs="+", default=list(PHASES), choices=PHASES, help="phases to run (default: all)")
    p.add_argument("--predict-pushes", type=int, default=64, help="held-out pushes of the prediction check")
    p.add_argument("--grid-magnitudes", type=float, nargs=3, default=(10.0, 400.0, 64), metavar=("LO", "HI", "N"))
    p.add_argument("--grid-directions", type=int, default=32)
    p.add_argument("--variation-magnitudes", type=int, default=16)
    p.add_argument("--variation-directions", type=int, default=16)
    p.add_argument("--no-one-foot", action="store_true", help="skip the one-foot task")
    p.add_argument("--sinusoid-s", type=float, default=20.0, help="seconds of the CoM sinusoid (0: skip)")
    p.add_argument("--heldout-backend", default="auto", help="physics of the held-out grid (the sweep's)")
    p.add_argument("--sinusoid-backend", default="mujoco", help="physics of the sinusoid (balance's CPU default)")
    p.add_argument("--chunk-size", type=int, default=16384, help="environments per held-out program call")
    p.add_argument(
        "--critical",
        default=str(ROOT / "experiments" / "gains" / "com_critical_100.json"),
        help="hand-set gains row (critically damped CoM)",
    )
    p.add_argument("--cache", default=None, help="persistent compilation cache (default: $WBC_JAX_CACHE or "
                   "the user's cache folder)")  # fmt: skip
    args = p.parse_args(argv)
    tc = cli.config_from_args(args, tune.default_config())
    if args.quick:
        given = {a.lstrip("-").replace("-", "_").split("=")[0] for a in (argv or sys.argv[1:]) if a.startswith("--")}
        tc = dataclasses.replace(tc, **{k: v for k, v in QUICK.items() if k not in given})
        if "predict_pushes" not in given:
            args.predict_pushes = 4
    tc = dataclasses.replace(tc, out=args.out)
    return args, tc


def heldout_config(args):
    from wbc_jax.tuning import heldout as tuning_eval

    lo, hi, n = args.grid_magnitudes
    kw = dict(magnitudes=(lo, hi, int(n)), directions=args.grid_directions, variation_magnitudes=args.variation_magnitudes,
              variation_directions=args.variation_directions, one_foot=not args.no_one_foot, sinusoid_s=args.sinusoid_s,
              backend=args.heldout_backend, sinusoid_backend=args.sinusoid_backend, chunk_size=args.chunk_size,
              tasks=args.tasks, angular_weight_soft=args.angular_weight_soft)  # fmt: skip
    if args.quick:
        kw.update(QUICK_HELDOUT)
    return tuning_eval.HeldoutConfig(**kw)


def main(argv=None) -> int:
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")
    args, tc = parse(argv)
    hc = heldout_config(args)  # every check before anything compiles

    from wbc_jax.control.gains import default_gains, load_gains
    from wbc_jax.core import io, provenance
    from wbc_jax.report import tuning_plots
    from wbc_jax.sim import runner
    from wbc_jax.tuning import baselines, tune
    from wbc_jax.tuning import heldout as tuning_eval
    from wbc_jax.tuning import problem as tp
    from wbc_jax.tuning.params import check_in_bounds, nava_conditions

    if args.predict_pushes < 2:
        raise ValueError("--predict-pushes must be >= 2")
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    runner.enable_compilation_cache(args.cache)
    problem = tp.make_problem(tc)
    critical = load_gains(args.critical, problem.robot.index.n, problem.setup.dtype)
    check_in_bounds(critical, problem.reg0, problem.bounds, source=f"--critical {args.critical}")
    inputs = {"critical": args.critical, "init_gains": tc.init_gains, "tasks": tc.tasks, "envelope": tc.envelope}
    prov = provenance.record(inputs, argv=provenance.script_argv(__file__, argv))
    io.atomic_write_json(out / "config.json", {"tune": dataclasses.asdict(tc), "heldout": dataclasses.asdict(hc),
                                               "argv": sys.argv[1:] if argv is None else argv, "device": prov["device"]["label"],
                                               "provenance": prov})  # fmt: skip
    timings = _load(out / "timings.json")
    print(json.dumps({"device": provenance.device_label(), "batch": tc.batch, "steps": tc.steps, "horizon": tc.horizon,
                      "population": tc.population, "candidate_batch": tc.candidate_batch,
                      "steps_per_rollout": problem.steps_per_rollout}), flush=True)  # fmt: skip

    def timed(name, fn):
        t0 = time.perf_counter()
        result = fn()
        timings[name] = round(time.perf_counter() - t0, 1)
        io.atomic_write_json(out / "timings.json", timings)
        print(json.dumps({"phase": name, "s": timings[name]}), flush=True)
        return result

    if "predict" in args.phases:
        res = timed("predict", lambda: tuning_eval.survival_prediction(problem, args.predict_pushes, out=out))
        print(
            json.dumps(
                {
                    k: res[k]
                    for k in (
                        "n",
                        "survival_rate",
                        "spearman_train_horizon",
                        "auc_train_horizon",
                        "spearman_full",
                        "auc_full",
                        "spearman_impulse_fraction",
                    )
                }
            ),
            flush=True,
        )
    rows = tune_rows = None
    if "train" in args.phases:
        _, _, rows, info = timed("train", lambda: tune.train(problem, out / "gradient"))
        print(json.dumps({"train": info}), flush=True)
    if (out / "gradient" / "history.csv").exists():
        tune_rows = _rows(out / "gradient" / "history.csv")
    searches = {}
    for kind in baselines.KINDS:
        if kind in args.phases or (out / kind / "checkpoint.npz").exists():
            if tune_rows is None:
                raise ValueError(f"the {kind} baseline needs the gradient run's budget: run --phases train first")
            budget = {"sim_steps": int(tune_rows[-1]["sim_steps"]), "wall_s": float(tune_rows[-1]["wall_s"])}
            if kind in args.phases:
                searches[kind] = timed(kind, lambda k=kind, b=budget: baselines.search(problem, k, out / k, budget=b))
            else:
                searches[kind] = baselines.result(problem, kind, out / kind, budget)
    if "heldout" in args.phases or "report" in args.phases:
        if tune_rows is None:
            raise ValueError("held-out evaluation needs the gradient run: run --phases train first")
        g_gains = load_gains(out / "gradient" / "tuned_gains.json", problem.robot.index.n, problem.setup.dtype)
        reg0 = problem.reg0
        g_reg = _reg(out / "gradient" / "tuned_regularisation.json", reg0)
        sets = {
            "default": (default_gains(problem.robot.index.n, problem.setup.dtype), reg0),
            "gradient": (g_gains, g_reg),
        }
        budgets = {"gradient": {"sim_steps": int(tune_rows[-1]["sim_steps"]), "wall_s": float(tune_rows[-1]["wall_s"])}}
        for kind, res in searches.items():
            for tag, name in (("equal_steps", kind), ("equal_wall", f"{kind}_wall")):
                if tag == "equal_wall" and not res[tag]["reached"]:
                    continue  # the wall budget was not run (--no-wall-budget) or not reached yet
                sets[name] = res[tag]["controls"]
                budgets[name] = {"sim_steps": res[tag]["sim_steps"], "wall_s": res[tag]["wall_s"]}
        sets["critical"] = (critical, reg0)
        for name, (g, _) in sets.items():
            io.atomic_write_json(out / "gains" / f"{name}.json", _gains_dict(g))
        if "heldout" in args.phases:
            results = timed("heldout", lambda: tuning_eval.heldout(sets, hc, out / "heldout"))
            io.atomic_write_json(out / "heldout_raw.json", results)
        if "report" in args.phases:
            results = _load(out / "heldout_raw.json")
            if not results:
                raise ValueError("no held-out results yet: run --phases heldout first")
            # The gain sets evaluated, by sha256 (experiments/gains/index.json lists the copies kept).
            sets_files = {f"gains:{n}": out / "gains" / f"{n}.json" for n in sets}
            extra = {"provenance": provenance.record({**inputs, **sets_files}, argv=provenance.script_argv(__file__, argv)),
                     "nava_2016": {n: nava_conditions(*v) for n, v in sets.items()}, "timings_s": timings,
                     "config": {"tune": dataclasses.asdict(tc), "heldout": dataclasses.asdict(hc)}}  # fmt: skip
            if (out / "prediction.json").exists():
                pred = _load(out / "prediction.json")
                extra["loss_predicts_survival"] = {
                    k: pred[k]
                    for k in (
                        "n",
                        "spearman_train_horizon",
                        "auc_train_horizon",
                        "spearman_full",
                        "auc_full",
                        "survival_rate",
                    )
                }
            rep = tuning_eval.write_heldout(out / "heldout.json", results, budgets, extra=extra)
            tuning_plots.envelope_polar(rep, out / "envelope_polar.png")
            hist = {"gradient": tune_rows, **{k: v["history"] for k, v in searches.items()}}
            tuning_plots.learning_curves(hist, out / "learning_curves.png", budgets["gradient"])
            line = {n: {k: rep[n][k] for k in ("envelope_fraction_median", "envelope_fraction_min", "survival_rate",
                                               "sinusoid_com_rmse_m", "sim_steps", "wall_s")}
                    for n in sets if n in rep}  # fmt: skip
            io.atomic_write_json(out / "summary.json", {"sets": line, "targets": rep["targets"]})
            print(json.dumps({"heldout": line, "targets": rep["targets"]}), flush=True)
    return 0


def _load(path) -> dict:
    path = pathlib.Path(path)
    return json.loads(path.read_text()) if path.exists() else {}


def _rows(path) -> list:
    from wbc_jax.tuning import problem as tuning_problem

    return tuning_problem.read_csv(path)


def _reg(path, reg0):
    import numpy as np

    d = _load(path)
    return np.array([d["pinv_damping"], d["kp_postural_reg"]]) if d else reg0


def _gains_dict(g) -> dict:
    from wbc_jax.control.gains import gains_to_dict

    return gains_to_dict(g)


if __name__ == "__main__":
    try:
        sys.exit(main())
    except (ValueError, FileNotFoundError) as err:
        print(f"tune_gpu: error: {err}", file=sys.stderr)
        sys.exit(2)
