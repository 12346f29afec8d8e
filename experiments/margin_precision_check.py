"""The support-polygon margin under the device's default matrix-product precision, against float64.

    git show 7abb9f8:wbc_jax/sim/metrics.py > /tmp/metrics_7abb9f8.py   # the version before the fix
    python experiments/margin_precision_check.py --old /tmp/metrics_7abb9f8.py --out runs/margin_precision.json

256 random stances (two parallel soles side by side, shifted up to 3 m, a point near their middle):
``metrics.polygon_margin`` jitted on the default device (with the default matrix-product precision,
and with 'highest'), and the one of ``--old`` if given, against float64 on the host. On a GPU whose
float32 products run in TensorFloat-32, the version before the fix flips the margin's sign.
"""

from __future__ import annotations

import argparse
import importlib.util
import pathlib
import sys

import jax
import numpy as np

from wbc_jax.core import io
from wbc_jax.sim import metrics as metrics_lib

ROOT = pathlib.Path(__file__).resolve().parent.parent

SOLE = (-0.07, 0.12, -0.045, 0.045)  # x0, x1, y0, y1 of the CoP rectangle (m), as tests/test_rollout.py


def soles(offset) -> np.ndarray:
    x0, x1, y0, y1 = SOLE
    feet = [np.array([[x, y] for x in (x0, x1) for y in (y0, y1)]) + [0.01, f * 0.07] for f in (-1, 1)]
    return (np.concatenate(feet) + offset).astype(np.float32)


def load_old(path: str):
    spec = importlib.util.spec_from_file_location("metrics_old", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules["metrics_old"] = module
    spec.loader.exec_module(module)
    return module.polygon_margin


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--old", help="a metrics.py of an earlier revision")
    p.add_argument("--n", type=int, default=256)
    p.add_argument("--out", default="runs/margin_precision.json")
    args = p.parse_args(argv)
    rng = np.random.default_rng(2)
    cases = []
    for _ in range(args.n):
        off = rng.uniform(-3, 3, 2)
        cases.append((soles(off), (off + rng.normal(scale=0.05, size=2)).astype(np.float32)))
    with jax.default_device(jax.devices("cpu")[0]), jax.enable_x64(True):
        ref = np.array([float(metrics_lib.polygon_margin(np.float64(pts), np.float64(q))) for pts, q in cases])
    fns = {"current": metrics_lib.polygon_margin, **({"old": load_old(args.old)} if args.old else {})}
    result = {"device": str(jax.devices()[0]), "n": args.n}
    for name, fn in fns.items():
        for precision in (None, "highest"):
            with jax.default_matmul_precision(precision):
                f = jax.jit(fn)
                m = np.array([float(f(pts, q)) for pts, q in cases])
            key = f"{name}_{precision or 'default'}"
            result[key] = {
                "max_abs_err_m": float(np.abs(m - ref).max()),
                "sign_flips": int(np.sum((m < 0) != (ref < 0))),
            }
            print(key, result[key], flush=True)
    result["command"] = "python experiments/margin_precision_check.py " + " ".join(
        argv if argv is not None else sys.argv[1:]
    )
    io.atomic_write_json(pathlib.Path(args.out), result)
    return result


if __name__ == "__main__":
    main()
