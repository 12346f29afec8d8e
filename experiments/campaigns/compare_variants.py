"""Controller variants on one push grid: qp vs analytic forces, stable vs seed postural, two feet vs
one foot. Each variant is a `wbc-jax push-sweep` into OUT/<variant>/; the comparison (survival rate
and envelope fraction of the LIP bound per direction) goes to OUT/comparison.json.

    python experiments/campaigns/compare_variants.py --out results/variants_cpu \
        [--magnitudes 20 160 8] [--directions 8] [--horizon 2.5]

Small defaults for the CPU; `experiments/gpu_run.sh variants one-foot` runs a 32 x 16 grid.
"""

from __future__ import annotations

import argparse
import json
import pathlib

from wbc_jax import cli
from wbc_jax.core import io, provenance

VARIANTS = {  # name -> push-sweep arguments
    "qp-stable": ["--forces", "qp", "--postural", "stable"],
    "analytic-stable": ["--forces", "analytic", "--postural", "stable"],
    "qp-seed": ["--forces", "qp", "--postural", "seed"],
    "one-foot-qp-stable": ["--task", "one-foot", "--push-onset", "7.5"],
}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="runs/variants")
    parser.add_argument("--magnitudes", type=float, nargs=3, default=[20.0, 160.0, 8])
    parser.add_argument("--directions", type=int, default=8)
    parser.add_argument("--horizon", type=float, default=2.5, help="s after the push onset + 0.5")
    parser.add_argument("--only", nargs="*", default=list(VARIANTS), choices=list(VARIANTS))
    args = parser.parse_args(argv)
    record = provenance.record(argv=provenance.script_argv(__file__, argv))
    out = pathlib.Path(args.out)
    comparison = {}
    for name in args.only:
        extra = list(VARIANTS[name])
        # Two feet: push at 0.5 s; one foot: at 7.5 s (single support 7-9 s), ending at 9 s.
        horizon = 9.0 if "one-foot" in name else args.horizon
        argv = [
            "push-sweep",
            "--out",
            str(out / name),
            "--quiet",
            "--magnitudes",
            *[str(x) for x in args.magnitudes],
            "--directions",
            str(args.directions),
            "--horizon",
            str(horizon),
            "--chunk-size",
            "64",
            *extra,
        ]
        if cli.main(argv) != 0:
            raise SystemExit(f"variant {name} failed")
        summary = json.loads((out / name / "summary.json").read_text())
        env = summary["envelope"]
        comparison[name] = {
            "survival_rate": summary["survival_rate"],
            "support": summary["support"],
            "nan_envs": summary["nan_envs"],
            "qp_infeasible_envs": summary["qp_infeasible_envs"],
            "largest_survived_impulse_ns": {k: v["largest_survived_impulse_ns"] for k, v in env.items()},
            "fraction_of_bound": {k: v["fraction_of_bound"] for k, v in env.items()},
            "mean_fraction_of_bound": sum(v["fraction_of_bound"] for v in env.values()) / len(env),
            "device": record["device"]["label"],
            "provenance": record,
        }
        io.atomic_write_json(out / "comparison.json", comparison)
        print(
            json.dumps(
                {name: {k: comparison[name][k] for k in ("survival_rate", "mean_fraction_of_bound", "nan_envs")}}
            ),
            flush=True,
        )


if __name__ == "__main__":
    main()
