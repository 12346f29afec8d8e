"""A push grid's outcomes with the force QP cold and warm-started (``qp_warm_start``), C MuJoCo (issue 46).

    python benchmarks/qp_warm_start_sweep.py --out runs/qp_warm_start_sweep.json [--magnitudes 20 120 11] [--directions 12]

The default push sweep's settings (``wbc-jax push-sweep``: robot, task, horizon, gains), its grid
replaced by ``--magnitudes LO HI N`` (N) x ``--directions D`` (azimuths 360/D apart), run twice in
one process: with ``ControllerConfig(qp_warm_start=False)`` (the default) and ``True``. Reports
how many environments survive (the strict criterion) in each, the survival flips between them and
the relative change of each environment's CoM max error (median, max).
"""

from __future__ import annotations

import os

os.environ.setdefault("PJRT_NPROC", "1")

import argparse
import json
import pathlib
import sys
import time

ROOT = pathlib.Path(__file__).resolve().parent.parent


def main(argv=None) -> dict:
    argv = list(sys.argv[1:] if argv is None else argv)
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default=str(ROOT / "runs" / "qp_warm_start_sweep.json"))
    p.add_argument("--magnitudes", nargs=3, type=float, default=(20.0, 120.0, 11), metavar=("LO", "HI", "N"))
    p.add_argument("--directions", type=int, default=12)
    args = p.parse_args(argv)
    lo, hi, count = args.magnitudes
    if not (0 < lo <= hi and count >= 1 and count == int(count)) or args.directions < 1:
        p.error("--magnitudes needs 0 < LO <= HI and a whole N >= 1; --directions a whole number >= 1")
    import numpy as np

    from wbc_jax.control.controller import ControllerConfig
    from wbc_jax.core import io, options, provenance
    from wbc_jax.jobs import sweep, sweep_config
    from wbc_jax.robot import model as model_lib
    from wbc_jax.sim import metrics, runner, scenario

    runner.enable_compilation_cache()
    cfg = options.replace(
        sweep_config.default_config(),
        magnitudes=tuple(np.linspace(lo, hi, int(count)).tolist()),
        directions=tuple((np.arange(args.directions) * 360.0 / args.directions).tolist()),
    )
    dtype = scenario.float_dtype()
    n = model_lib.load_robot(cfg.robot).index.n
    base = sweep.base_gains(cfg, n, dtype)
    scenarios, _ = sweep.build_scenarios(cfg, base, n, dtype)
    outcomes = {}
    for warm in (False, True):
        st = sweep.make_setup(cfg, base, controller=ControllerConfig(qp_warm_start=warm))
        summary = metrics.summarize(runner.run(st, scenarios).metrics)
        outcomes[warm] = {k: np.asarray(summary[k]) for k in ("survived", "com_max_err_m")}
    cold, warm = outcomes[False], outcomes[True]
    change = np.abs(warm["com_max_err_m"] - cold["com_max_err_m"]) / np.abs(cold["com_max_err_m"])
    result = {
        "command": "python benchmarks/qp_warm_start_sweep.py " + " ".join(argv),
        "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "device": provenance.device_label(),
        "environments": int(cold["survived"].size),
        "survived_cold": int(cold["survived"].sum()),
        "survived_warm": int(warm["survived"].sum()),
        "survival_flips": int((cold["survived"] != warm["survived"]).sum()),
        "com_max_err_relative_change": {
            "median": float(f"{np.median(change):.3g}"),
            "max": float(f"{change.max():.3g}"),
        },
        "provenance": provenance.record(argv=[__file__, *argv]),
    }
    io.atomic_write_json(pathlib.Path(args.out), result)
    print(json.dumps({k: v for k, v in result.items() if k != "provenance"}), flush=True)
    return result


if __name__ == "__main__":
    main()
