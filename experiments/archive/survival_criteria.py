"""Which test of the strict survival criterion fails, per engine and batch, on the benchmark scenario.

    python experiments/archive/survival_criteria.py --out runs/survival_criteria.json jax:32 [warp:65536 ...]

The scenario of benchmarks/benchmark.py (stand, 0.5 s, one 40 N chest push per environment, 0.1 s at
0.2 s, azimuths over 360 deg, default gains, 4 Newton iterations). For each ENGINE:BATCH: the survival
rate, how many environments fail each test of ``constants.SURVIVAL_CRITERION`` (and the lax one),
quantiles of each tested quantity, the failures per 45 deg sector, and 16 sample environments.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[2]

QUANTITIES = ("max_foot_slip_m", "max_foot_tilt_deg", "end_com_speed_mps", "end_com_support_margin_m", "com_max_err_m")


def load_benchmark():
    """benchmarks/loop_timing.py (the benchmark's closed loop and pushes; a script, not a package), loaded
    from its file."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("loop_timing", ROOT / "benchmarks" / "loop_timing.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def probe(backend: str, batch: int) -> dict:
    benchmark = load_benchmark()

    from wbc_jax.core import provenance
    from wbc_jax.sim import metrics as metrics_lib
    from wbc_jax.sim import runner

    t0 = time.perf_counter()
    st = benchmark.make_setup(backend, 0.5, 4)
    r = runner.run(st, benchmark.push_batch(st, batch, 0.2, 0.1))
    cols = {k: np.asarray(v) for k, v in metrics_lib.summarize(r.metrics, 0.3).items()}
    azimuth = np.linspace(0, 360, batch, endpoint=False)
    fails = metrics_lib.failed_tests(cols)
    idx = np.linspace(0, batch - 1, min(16, batch)).astype(int)
    return {
        "backend": backend,
        "batch": batch,
        "dtype": str(st.dtype),
        "device": provenance.device_label(),
        "wall_s": round(time.perf_counter() - t0, 1),
        "survived_rate": float(np.mean(cols["survived"])),
        "failing": {k: int(v.sum()) for k, v in fails.items()},
        "quantiles_0_50_90_99_100": {
            k: np.quantile(cols[k], [0, 0.5, 0.9, 0.99, 1]).round(5).tolist() for k in QUANTITIES
        },
        "failed_per_45deg": np.histogram(azimuth[~cols["survived"].astype(bool)], bins=8, range=(0, 360))[0].tolist(),
        "samples": [
            {
                "azimuth_deg": float(azimuth[i]),
                "survived": bool(cols["survived"][i]),
                **{k: round(float(cols[k][i]), 5) for k in QUANTITIES},
            }
            for i in idx
        ],
    }


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="+", help="ENGINE:BATCH, e.g. jax:32 warp:65536")
    p.add_argument("--out", default="runs/survival_criteria.json")
    args = p.parse_args(argv)
    plan = []
    for spec in args.runs:
        engine, _, batch = spec.partition(":")
        if engine not in ("jax", "warp", "mujoco") or not batch.isdigit() or int(batch) < 1:
            raise ValueError(f"runs are ENGINE:BATCH with ENGINE one of jax, warp, mujoco and BATCH >= 1, got {spec!r}")
        plan.append((engine, int(batch)))
    out, result = pathlib.Path(args.out), {}
    for engine, batch in plan:
        row = probe(engine, batch)
        print(json.dumps({k: v for k, v in row.items() if k != "samples"}), flush=True)
        result[f"{engine}:{batch}"] = row
    from wbc_jax.core import io, provenance

    result["provenance"] = provenance.record(argv=provenance.script_argv(__file__, argv))
    io.atomic_write_json(out, result)
    return result


if __name__ == "__main__":
    try:
        main()
    except ValueError as err:
        sys.exit(f"error: {err}")
