"""Tuned gains that keep the seed's task: raise K_P,CoM in x and y to a floor, keep the damping ratios.

    python experiments/campaigns/stiffen_com.py --out results/tuning/stiff_com [--floors 30 50 70 85 100] [--write-gains]
        [--restore-yaw]

The three tuners of results/tuning lower K_P,CoM in x and y from 100 to 15-22, and the seed's 20 s CoM
sinusoid (2 cm along y at 0.2 Hz) is then tracked with 2.2-4.4 mm RMSE against issue 20's bound of
1.5 mm. This measures, on C MuJoCo (the ``balance`` closed loop, all sets in one batch), the
sinusoid RMSE of each tuned set with K_P,CoM x, y raised to each floor (K_D,CoM = 2 zeta sqrt(K_P,CoM),
zeta of the tuned set; nothing else changes), and with ``--write-gains`` writes, per set, the
lowest floor whose RMSE is within the bound (the highest floor if none is) as
``experiments/gains/tuned_{set}{--suffix}.json`` (``_stiff_com``), refusing to overwrite a file
that holds other gains (results name gains files by sha256: choose another ``--suffix`` and add the
new files to experiments/gains/index.json). ``--restore-yaw`` first raises the yaw (z) gains
of the angular-momentum task, K_P,w and K_I,w, back to at least the WBC defaults (horizontal pushes
hardly excite yaw, so the push loss leaves them free, and with them lowered the upper body slowly
yaws against the feet over the 20 s); its files end in ``_stiff_com_yaw.json`` by default. Their push envelope is then measured on the GPU
with ``experiments/campaigns/heldout_reeval.py`` (docs/tuning/README.md).
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[2]
GAINS = ROOT / "experiments" / "gains"


def with_com_floor(gains, floor: float):
    """Gains with K_P,CoM x, y raised to ``floor`` (N/m per kg) and K_D,CoM keeping each axis's
    damping ratio; z and every other gain unchanged."""
    from wbc_jax.tuning.algorithms.params import damping_ratio

    kp = np.asarray(gains.kp_com, float)
    zeta = damping_ratio(np.asarray(gains.kd_com, float), kp)
    kp_new = kp.copy()
    kp_new[:2] = np.maximum(kp[:2], floor)
    dtype = np.asarray(gains.kp_com).dtype
    return gains.replace(kp_com=kp_new.astype(dtype), kd_com=(2.0 * zeta * np.sqrt(kp_new)).astype(dtype))


def with_yaw_floor(gains, reference):
    """Gains with K_P,w and K_I,w about z raised to at least ``reference``'s; all else unchanged."""
    kp, ki = np.asarray(gains.kp_ang).copy(), np.asarray(gains.ki_ang).copy()
    kp[2] = max(kp[2], float(np.asarray(reference.kp_ang)[2]))
    ki[2] = max(ki[2], float(np.asarray(reference.ki_ang)[2]))
    return gains.replace(kp_ang=kp, ki_ang=ki)


def main(argv=None) -> int:
    from wbc_jax.control.gains import default_gains, gains_to_dict, load_gains
    from wbc_jax.core import constants, io, provenance
    from wbc_jax.robot.icub import DESCRIPTION as ICUB
    from wbc_jax.robot.model import load_robot
    from wbc_jax.tuning.algorithms import params as tuning_params
    from wbc_jax.tuning.orchestration import heldout as tuning_eval

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="runs/stiff_com")
    p.add_argument(
        "--sets", nargs="+", default=["gradient", "cmaes", "random"], help="experiments/gains/tuned_{set}.json"
    )
    p.add_argument("--floors", type=float, nargs="+", default=[30.0, 50.0, 70.0, 85.0, 100.0])
    p.add_argument("--sinusoid-s", type=float, default=20.0)
    p.add_argument("--write-gains", action="store_true", help="write experiments/gains/tuned_{set}{suffix}.json")
    p.add_argument(
        "--suffix",
        default=None,
        help="of the gains files written (default: _stiff_com, with "
        "--restore-yaw _stiff_com_yaw); an existing file with other gains is never overwritten",
    )
    p.add_argument("--restore-yaw", action="store_true", help="first raise K_P,w z and K_I,w z to the WBC defaults")
    args = p.parse_args(argv)
    if not args.floors or any(not (np.isfinite(f) and f > 0) for f in args.floors):
        raise ValueError(f"--floors must be positive, got {args.floors}")
    floors = [0.0, *sorted(args.floors)]
    n = load_robot("icub").index.n
    tuned = {s: load_gains(GAINS / f"tuned_{s}.json", n) for s in args.sets}
    if args.restore_yaw:
        tuned = {s: with_yaw_floor(g, default_gains(ICUB, np.asarray(g.kp_ang).dtype)) for s, g in tuned.items()}
    suffix = args.suffix or ("_stiff_com_yaw" if args.restore_yaw else "_stiff_com")
    targets = {s: GAINS / f"tuned_{s}{suffix}.json" for s in args.sets}
    prov = provenance.record(
        {f"gains:{s}": GAINS / f"tuned_{s}.json" for s in args.sets}, argv=provenance.script_argv(__file__, argv)
    )
    rows = [(s, f, with_com_floor(g, f)) for s, g in tuned.items() for f in floors]
    hc = tuning_eval.HeldoutConfig(sinusoid_s=args.sinusoid_s, sinusoid_backend="mujoco")
    rmse, timing = tuning_eval.sinusoid([g for _, _, g in rows], tuning_params.default_regularisation(), hc)
    bound = constants.SINUSOID_MAX_COM_RMSE_M
    table = {s: {} for s in args.sets}
    for (s, f, _), r in zip(rows, rmse):
        table[s][f"{f:g}"] = r
    chosen = {}
    for s in args.sets:
        ok = [f for f in floors[1:] if table[s][f"{f:g}"] <= bound]
        chosen[s] = {"floor": ok[0] if ok else floors[-1], "within_bound": bool(ok)}
        chosen[s]["sinusoid_com_rmse_m"] = table[s][f"{chosen[s]['floor']:g}"]
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    report = {
        "sinusoid_com_rmse_m": table,
        "chosen": chosen,
        "bound_m": bound,
        "sinusoid_s": args.sinusoid_s,
        "restore_yaw": args.restore_yaw,
        "backend": "mujoco",
        "timing": timing,
        "device": prov["device"]["label"],
        "provenance": prov,
    }
    io.atomic_write_json(out / "sinusoid_cpu.json", report)
    if args.write_gains:  # after the report: a name taken by other gains loses no measurement
        for s, c in chosen.items():
            io.write_new_json(targets[s], gains_to_dict(with_com_floor(tuned[s], c["floor"])))
        report["gains_written"] = {s: provenance.display_path(t) for s, t in targets.items()}
        io.atomic_write_json(out / "sinusoid_cpu.json", report)
    print(
        json.dumps(
            {"chosen": chosen, "rmse_mm": {s: {f: round(v * 1e3, 3) for f, v in t.items()} for s, t in table.items()}}
        )
    )
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except (ValueError, FileNotFoundError, FileExistsError) as err:
        sys.exit(f"error: {err}")
