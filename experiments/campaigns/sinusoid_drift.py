"""Why tuned gains lose the seed's CoM sinusoid: tracking error and posture drift over time.

    python experiments/campaigns/sinusoid_drift.py --out results/tuning/stiff_com/drift.json

On C MuJoCo (the ``balance`` closed loop): (1) the CoM RMSE of each gain set on the sinusoid task
run for 2, 5, 10 and 20 s (does a short window rank the sets as the 20 s bound does?); (2) for the
``--windowed`` sets, one 20 s run recorded: per time window, the RMS CoM error per axis and the RMS
posture error (joints against their references), and the joints that drift most in the last window.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import tempfile

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[2]
GAINS = ROOT / "experiments" / "gains"
HAND_SET = ROOT / "assets" / "gains" / "com_critical_100.json"  # package data, not in GAINS


def gains_file(name: str) -> pathlib.Path:
    """The gains file of a set's name: experiments/gains/{name}.json, or the hand-set package data."""
    return HAND_SET if name == HAND_SET.stem else GAINS / f"{name}.json"


SETS = (
    "com_critical_100",
    "tuned_gradient",
    "tuned_cmaes",
    "tuned_random",
    "tuned_gradient_stiff_com",
    "tuned_cmaes_stiff_com",
    "tuned_random_stiff_com",
)
WINDOWS = ((0.0, 2.0), (2.0, 5.0), (5.0, 10.0), (10.0, 15.0), (15.0, 20.0))


def windowed(traj, windows=WINDOWS, top: int = 4) -> dict:
    """Per window [a, b) s: RMS CoM error per axis (m) and RMS posture error (rad) of a recorded
    run (trajectory.npz arrays: t, com, com_ref, s, s_des, joints); the ``top`` joints with the
    largest RMS error in the last window."""
    t, err, ds = traj["t"], traj["com"] - traj["com_ref"], traj["s"] - traj["s_des"]
    rows = []
    for a, b in windows:
        m = (t >= a) & (t < b)
        rows.append(
            {
                "window_s": [a, b],
                "com_rms_m_xyz": np.sqrt(np.mean(err[m] ** 2, 0)).tolist(),
                "posture_rms_rad": float(np.sqrt(np.mean(ds[m] ** 2))),
            }
        )
    last = t >= windows[-1][0]
    per_joint = np.sqrt(np.mean(ds[last] ** 2, 0))
    order = np.argsort(-per_joint)[:top]
    return {"windows": rows, "last_window_joints_rad": {str(traj["joints"][i]): float(per_joint[i]) for i in order}}


def main(argv=None) -> int:
    from wbc_jax.control.gains import default_gains, load_gains
    from wbc_jax.core import io, provenance
    from wbc_jax.jobs import balance
    from wbc_jax.robot.icub import DESCRIPTION as ICUB
    from wbc_jax.tuning.algorithms import params as tuning_params
    from wbc_jax.tuning.orchestration import heldout as tuning_eval

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="runs/sinusoid_drift.json")
    p.add_argument(
        "--sets",
        nargs="+",
        default=list(SETS),
        help="experiments/gains/{name}.json, com_critical_100 (assets/gains) or 'default'",
    )
    p.add_argument("--durations", type=float, nargs="+", default=[2.0, 5.0, 10.0, 20.0])
    p.add_argument("--windowed", nargs="*", default=["com_critical_100", "tuned_gradient", "tuned_cmaes"])
    args = p.parse_args(argv)
    names = ["default", *[s for s in args.sets if s != "default"]]
    gains = [default_gains(ICUB) if n == "default" else load_gains(gains_file(n), 23) for n in names]
    files = {f"gains:{n}": gains_file(n) for n in {*names, *args.windowed} if n != "default"}
    prov = provenance.record(files, argv=provenance.script_argv(__file__, argv))  # the files as they are read
    rmse = {n: {} for n in names}
    for dur in args.durations:
        hc = tuning_eval.HeldoutConfig(sinusoid_s=dur, sinusoid_backend="mujoco")
        values, _ = tuning_eval.sinusoid(gains, tuning_params.default_regularisation(), hc)
        for n, v in zip(names, values):
            rmse[n][f"{dur:g}"] = v
    drift = {}
    for n in args.windowed:
        with tempfile.TemporaryDirectory() as tmp:
            balance.run(task="sinusoid", duration=20.0, gains=str(gains_file(n)), out=tmp, plots=False, progress=False)
            drift[n] = windowed(dict(np.load(pathlib.Path(tmp) / "trajectory.npz")))
    report = {
        "sinusoid_com_rmse_m_by_duration": rmse,
        "drift_20s": drift,
        "backend": "mujoco",
        "device": prov["device"]["label"],
        "provenance": prov,
    }
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    io.atomic_write_json(out, report)
    print(
        json.dumps(
            {
                "rmse_mm": {n: {d: round(v * 1e3, 2) for d, v in r.items()} for n, r in rmse.items()},
                "posture_rms_rad": {
                    n: [round(w["posture_rms_rad"], 3) for w in d["windows"]] for n, d in drift.items()
                },
            }
        )
    )
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except (ValueError, FileNotFoundError) as err:
        sys.exit(f"error: {err}")
