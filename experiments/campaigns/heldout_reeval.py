"""Evaluate gains files on issue 20's held-out set again, without their tuning runs.

    python experiments/campaigns/heldout_reeval.py --out runs/heldout_reeval [--previous docs/tuning/heldout.json]
        [--sets default gradient=experiments/gains/tuned_gradient.json ...] [--sinusoid-s 0]

``wbc-jax heldout --sets NAME=FILE ...`` evaluates any gains files; this script is that job with the
budgets and sinusoid figures of an earlier heldout.json kept (the sets of docs/tuning by default), and
writes heldout.json and envelope_polar.png as ``wbc-jax tune``'s report does. What a gains file does
not hold is taken from ``--previous`` (a heldout.json): each set's tuning budget (sim_steps, wall_s)
and, with ``--sinusoid-s 0``, its 20 s sinusoid RMSE (run on C MuJoCo on the host).
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

ROOT = pathlib.Path(__file__).resolve().parents[2]

GAINS = ROOT / "experiments" / "gains"
DEFAULT_SETS = ("default", f"gradient={GAINS / 'tuned_gradient.json'}", f"cmaes={GAINS / 'tuned_cmaes.json'}",
                f"random={GAINS / 'tuned_random.json'}", f"critical={ROOT / 'assets' / 'gains' / 'com_critical_100.json'}")  # fmt: skip


def parse(argv=None):
    from wbc_jax.tuning import heldout as tuning_eval

    hc0 = tuning_eval.HeldoutConfig()
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="runs/heldout_reeval")
    p.add_argument("--previous", default=str(ROOT / "docs" / "tuning" / "heldout.json"),
                   help="heldout.json whose budgets (and sinusoid RMSE, with --sinusoid-s 0) are kept")  # fmt: skip
    p.add_argument("--sets", nargs="+", default=list(DEFAULT_SETS), help="NAME=GAINS.json, or 'default'")
    p.add_argument("--sinusoid-s", type=float, default=hc0.sinusoid_s, help="0: keep --previous's RMSE")
    p.add_argument("--no-one-foot", action="store_true")
    p.add_argument("--backend", default=hc0.heldout_backend)
    p.add_argument("--chunk-size", type=int, default=8320)
    p.add_argument("--magnitudes", type=float, nargs=3, default=(10.0, 400.0, 64), metavar=("LO", "HI", "N"))
    p.add_argument("--directions", type=int, default=len(hc0.grid_directions))
    p.add_argument("--variation-magnitudes", type=int, default=hc0.variation_magnitudes)
    p.add_argument("--variation-directions", type=int, default=hc0.variation_directions)
    p.add_argument("--horizon", type=float, default=hc0.grid_horizon, help="s, of the stand task's pushes")
    return p.parse_args(argv)


def load_sets(specs: list, robot, dtype) -> dict:
    """{name: (Gains, regularisation)} from 'NAME=FILE' or 'default' (clear errors before compiling)."""
    from wbc_jax.control.gains import default_gains, load_gains
    from wbc_jax.tuning import params as tuning_params

    reg0 = tuning_params.default_regularisation()
    sets = {}
    for spec in specs:
        name, _, path = spec.partition("=")
        if name in sets:
            raise ValueError(f"gain set {name!r} given twice")
        if name == "default" and not path:
            sets[name] = (default_gains(robot, dtype), reg0)
        elif not path:
            raise ValueError(f"--sets entries are NAME=GAINS.json or 'default', got {spec!r}")
        else:
            sets[name] = (load_gains(path, len(robot.joints), dtype), reg0)  # load_gains checks the file and its values
    return sets


def main(argv=None) -> int:
    from wbc_jax.core import provenance
    from wbc_jax.jobs import grids
    from wbc_jax.report import tuning_plots
    from wbc_jax.robot.model import load_robot
    from wbc_jax.sim import scenario
    from wbc_jax.tuning import heldout as tuning_eval

    args = parse(argv)
    prev = json.loads(pathlib.Path(args.previous).read_text()) if args.previous else {}
    hc = tuning_eval.HeldoutConfig(
        grid_magnitudes=grids.magnitude_grid(args.magnitudes),
        grid_directions=grids.azimuths(args.directions),
        grid_horizon=args.horizon,
        variation_magnitudes=args.variation_magnitudes,
        variation_directions=args.variation_directions,
        sinusoid_s=args.sinusoid_s,
        one_foot=not args.no_one_foot,
        heldout_backend=args.backend,
        chunk_size=args.chunk_size,
    )  # checks the sizes before anything compiles
    robot = load_robot("icub")
    sets = load_sets(args.sets, robot.description, scenario.float_dtype())
    inputs = {f"gains:{name}": path for name, _, path in (x.partition("=") for x in args.sets) if path}
    prov = provenance.record({**inputs, "previous": args.previous}, argv=provenance.script_argv(__file__, argv))
    out = pathlib.Path(args.out)
    results = tuning_eval.heldout(sets, hc, out / "heldout")
    for name in sets:
        if hc.sinusoid_s == 0 and name in prev:
            results[name]["sinusoid_com_rmse_m"] = prev[name].get("sinusoid_com_rmse_m")
    budgets = {n: {"sim_steps": prev[n]["sim_steps"], "wall_s": prev[n]["wall_s"]} for n in sets if n in prev}
    shown = [f"{n}={provenance.display_path(f)}" if f else n for n, _, f in (x.partition("=") for x in args.sets)]
    extra = {"provenance": prov, "sets": shown,
             "budgets_and_sinusoid_from": args.previous if prev else None}  # fmt: skip
    if "nava_2016" in prev:  # the stability conditions depend on the gains alone
        extra["nava_2016"] = {n: v for n, v in prev["nava_2016"].items() if n in sets}
    rep = tuning_eval.write_heldout(out / "heldout.json", results, budgets, extra=extra)
    tuning_plots.envelope_polar(rep, out / "envelope_polar.png")
    line = {n: {k: rep[n][k] for k in ("envelope_fraction_median", "envelope_fraction_min", "survival_rate",
                                       "upright_rate", "sinusoid_com_rmse_m")} for n in sets}  # fmt: skip
    print(json.dumps({"heldout": line, "targets": rep["targets"]}), flush=True)
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except (ValueError, FileNotFoundError) as err:
        sys.exit(f"error: {err}")
