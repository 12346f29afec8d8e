"""The support-polygon margin under the device's default matrix-product precision, against float64.

    git show 7abb9f8:wbc_jax/metrics.py > /tmp/metrics_7abb9f8.py   # the version before the fix
    python experiments/checks/margin_precision_check.py --old /tmp/metrics_7abb9f8.py --out runs/margin_precision.json

256 random stances (two parallel soles side by side, shifted up to 3 m, a point near their middle):
``metrics.polygon_margin`` jitted on the default device (with the default matrix-product precision,
and with 'highest'), and the one of ``--old`` if given, against float64 on the host. On a GPU whose
float32 products run in TensorFloat-32, the version before the fix flips the margin's sign.

The check (:func:`failures`): today's function, at both precisions, flips no sign and is within
``BAR_M`` (1e-6 m, the margin's own tolerance) of float64; exit status 1 otherwise. ``--old`` is
shown, not checked.
"""

from __future__ import annotations

import argparse
import importlib.util
import pathlib
import sys

import jax
import numpy as np

from wbc_jax.core import checks, io, provenance
from wbc_jax.sim import metrics as metrics_lib

BAR_M = 1e-6  # m: the polygon margin's own tolerance
BAR = f"today's polygon_margin, at the default and the highest precision: no sign flip, within {BAR_M:g} m of float64"

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


def failures(result: dict) -> list[str]:
    """Today's margin (``current_*``) flipping a sign or off float64 by more than BAR_M."""
    out = []
    for key in ("current_default", "current_highest"):
        r = result.get(key)
        if r is None:
            out.append(f"{key}: not measured")
            continue
        if r["sign_flips"]:
            out.append(f"{key}: {r['sign_flips']} of {result['n']} margins with the wrong sign")
        if not r["max_abs_err_m"] <= BAR_M:
            out.append(f"{key}: off float64 by {r['max_abs_err_m']:.3g} m > {BAR_M:g} m")
    return out


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=f"Check: {BAR}; exit status 1 otherwise.",
    )
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
    result = {"device": provenance.device_label(), "n": args.n}
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
    result["provenance"] = provenance.record({"old": args.old}, argv=provenance.script_argv(__file__, argv))
    result["check"] = checks.verdict(failures(result), BAR)
    io.atomic_write_json(pathlib.Path(args.out), result)
    return result


if __name__ == "__main__":
    sys.exit(checks.exit_status(main()))
