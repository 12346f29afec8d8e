"""Evaluate gains files on issue 20's held-out set again, without their tuning runs.

    python experiments/campaigns/heldout_reeval.py --out runs/heldout_reeval [--previous results/tuning/heldout.json]
        [--sets default gradient=experiments/gains/tuned_gradient.json ...] [--sinusoid-s 0] [wbc-jax heldout's flags]

``wbc-jax heldout --sets NAME=FILE ...`` evaluates any gains files; this script is that job with the
budgets and sinusoid figures of an earlier heldout.json kept (the sets of results/tuning by default), and
writes heldout.json and envelope_polar.png as ``wbc-jax tune``'s report does. What a gains file does
not hold is taken from ``--previous`` (a heldout.json): each set's tuning budget (sim_steps, wall_s)
and, with ``--sinusoid-s 0``, its 20 s sinusoid RMSE (run on C MuJoCo on the host).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import sys

ROOT = pathlib.Path(__file__).resolve().parents[2]

GAINS = ROOT / "experiments" / "gains"
DEFAULT_SETS = (
    "default",
    f"gradient={GAINS / 'tuned_gradient.json'}",
    f"cmaes={GAINS / 'tuned_cmaes.json'}",
    f"random={GAINS / 'tuned_random.json'}",
    f"critical={ROOT / 'assets' / 'gains' / 'com_critical_100.json'}",
)


def defaults():
    """The held-out job's config (``wbc-jax heldout``'s flags and defaults) with this script's sets and
    folder."""
    from wbc_jax.tuning.heldout_config import heldout_default_config

    return dataclasses.replace(heldout_default_config(), sets=DEFAULT_SETS, out="runs/heldout_reeval")


def parse(argv=None):
    """(the held-out config, checked before anything compiles; --previous): ``wbc-jax heldout``'s
    flags, generated from its config, and --previous."""
    from wbc_jax import cli

    base = defaults()
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    cli.add_config_arguments(p, base)
    p.add_argument(
        "--previous",
        default=str(ROOT / "results" / "tuning" / "heldout.json"),
        help="heldout.json whose budgets (and sinusoid RMSE, with --sinusoid-s 0) are kept",
    )
    args = p.parse_args(argv)
    hc = cli.config_from_args(args, base)
    hc.check()
    return hc, args.previous


def main(argv=None) -> int:
    from wbc_jax.core import provenance
    from wbc_jax.report import tuning_plots
    from wbc_jax.robot.model import load_robot
    from wbc_jax.sim import scenario
    from wbc_jax.tuning.orchestration import heldout as tuning_eval

    hc, previous = parse(argv)
    prev = json.loads(pathlib.Path(previous).read_text()) if previous else {}
    robot = load_robot(hc.robot)
    sets = tuning_eval.load_sets(hc.sets, robot.description, scenario.float_dtype())
    inputs = {f"gains:{name}": path for name, path in tuning_eval.set_files(hc.sets, robot.description).items()}
    prov = provenance.record({**inputs, "previous": previous}, argv=provenance.script_argv(__file__, argv))
    out = pathlib.Path(hc.out)
    results = tuning_eval.heldout(sets, hc, out / "heldout")
    for name in sets:
        if hc.sinusoid_s == 0 and name in prev:
            results[name]["sinusoid_com_rmse_m"] = prev[name].get("sinusoid_com_rmse_m")
    budgets = {n: {"sim_steps": prev[n]["sim_steps"], "wall_s": prev[n]["wall_s"]} for n in sets if n in prev}
    shown = [f"{n}={provenance.display_path(f)}" if f else n for n, _, f in (x.partition("=") for x in hc.sets)]
    extra = {"provenance": prov, "sets": shown, "budgets_and_sinusoid_from": previous if prev else None}
    if "nava_2016" in prev:  # the stability conditions depend on the gains alone
        extra["nava_2016"] = {n: v for n, v in prev["nava_2016"].items() if n in sets}
    rep = tuning_eval.write_heldout(out / "heldout.json", results, budgets, extra=extra)
    tuning_plots.envelope_polar(rep, out / "envelope_polar.png")
    line = {
        n: {
            k: rep[n][k]
            for k in (
                "envelope_fraction_median",
                "envelope_fraction_min",
                "survival_rate",
                "upright_rate",
                "sinusoid_com_rmse_m",
            )
        }
        for n in sets
    }
    print(json.dumps({"heldout": line, "targets": rep["targets"]}), flush=True)
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except (ValueError, FileNotFoundError) as err:
        sys.exit(f"error: {err}")
