"""The strict envelope against the QP's CoP rectangle (issue: gradient tuning, the 0.8 target).

    python experiments/campaigns/cop_margin.py --out results/tuning/cop_margin/wbc_8 --scales 1.0 0.9 0.8 0.7 0.6 \
        --gains gradient=experiments/gains/tuned_gradient.json critical=assets/gains/com_critical_100.json
    python experiments/campaigns/cop_margin.py --rectangle sole --out results/tuning/cop_margin/sole_8 ...
    python experiments/campaigns/cop_margin.py --rectangle sole --scales 0.95 --angular-weights 1 0.1 0.01 ...

Foot tilt ends most directions' strict envelope (experiments/campaigns/envelope_limits.py): the force QP may
put each foot's CoP on the edge of the sole, where the real foot starts to rotate. This shrinks the
CoP rectangle of both feet about its centre (a task file of the two feet with ``cop`` set,
wbc_jax/robot/contacts.py) and bisects the envelope (``wbc_jax.jobs.envelope.search``, C MuJoCo, the held-out
grid's pushes) per gain set and scale. Writes cop_margin.json (envelope / LIP bound per direction,
median and min) and the task files.

The rectangle scaled is the QP's default (``--rectangle wbc``: ContactParams.foot_size, the WBC
footSize) or each foot's real support in the model (``--rectangle sole``: the extent of its four
contact spheres in the sole frame, the polygon the LIP bound of wbc_jax/jobs/sweep.py uses). The two
differ: the default reaches 1.6 mm behind the heel's contact points, stops 1.05 cm short of the
toe's and 0.8 cm short of the outer edge.

``--angular-weights``: the soft momentum QP's angular_weight_soft (wbc_jax/control/forces.py) of each run;
``--body``: the pushed body (chest, as the held-out grid; root_link: 6 cm above the CoM instead of
14.5 cm, less moment about the CoM for the same impulse).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import sys

import mujoco
import numpy as np

from wbc_jax.core import io, options, provenance
from wbc_jax.jobs import envelope
from wbc_jax.robot import contacts, model
from wbc_jax.sim import runner

WBC_RECTANGLE = contacts.ContactParams().foot_size  # the QP's default CoP rectangle


def sole_rectangles(robot: model.Robot) -> dict[str, tuple]:
    """Per foot, ((x_min, x_max), (y_min, y_max)) of its contact spheres' centres in its sole
    frame at the home posture: the support the simulated foot really has."""
    m = robot.mj_model
    d = mujoco.MjData(m)
    d.qpos[:] = robot.home_qpos()
    mujoco.mj_forward(m, d)
    out = {}
    for side, site, geoms in zip(("left", "right"), robot.index.foot_sites, robot.index.foot_geoms):
        local = (d.geom_xpos[geoms] - d.site_xpos[site]) @ d.site_xmat[site].reshape(3, 3)
        lo, hi = local[:, :2].min(0), local[:, :2].max(0)
        out[side] = ((float(lo[0]), float(hi[0])), (float(lo[1]), float(hi[1])))
    return out


def scaled(rect, scale: float) -> list[list[float]]:
    """A rectangle shrunk about its centre by ``scale``."""
    return [[0.5 * (a + b) + (a - 0.5 * (a + b)) * scale, 0.5 * (a + b) + (b - 0.5 * (a + b)) * scale] for a, b in rect]


def task_file(rectangles: dict[str, tuple], scale: float) -> str:
    feet = [
        {"name": f"{side}_foot", "frame": f"{side[0]}_sole", "normal": [0, 0, 1], "cop": scaled(rect, scale)}
        for side, rect in rectangles.items()
    ]
    return json.dumps({"contacts": feet}, indent=1)


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument(
        "--gains", nargs="+", required=True, help="NAME=GAINS_FILE (GAINS_FILE 'default': the default gains)"
    )
    p.add_argument("--scales", nargs="+", type=float, default=[1.0, 0.9, 0.8, 0.7, 0.6])
    p.add_argument("--directions", type=int, default=8)
    p.add_argument("--backend", default="mujoco")
    p.add_argument(
        "--rectangle",
        choices=("wbc", "sole"),
        default="wbc",
        help="the rectangle scaled: the QP's default (wbc) or each foot's contact spheres (sole)",
    )
    p.add_argument(
        "--angular-weights",
        nargs="+",
        type=float,
        default=[1.0],
        help="the soft momentum QP's angular_weight_soft of each run (1: WBC)",
    )
    p.add_argument("--body", default="chest", help="pushed body")
    p.add_argument("--out", default="runs/cop_margin")
    args = p.parse_args(argv)
    if any(not (0 < s <= 1) for s in args.scales):
        raise ValueError(f"--scales must lie in (0, 1], got {args.scales}")
    if any(not (np.isfinite(w) and w > 0) for w in args.angular_weights):
        raise ValueError(f"--angular-weights must be positive and finite, got {args.angular_weights}")
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    runner.enable_compilation_cache()
    base = dataclasses.replace(
        envelope.default_config(),
        horizon=3.0,
        backend=args.backend,
        out=None,
        body=args.body,
        directions=tuple(float(a) for a in np.arange(args.directions) * 360.0 / args.directions),
    )
    robot = model.load_robot()
    robot.index.body_id(args.body)  # an unknown body: the error lists the bodies
    if args.rectangle == "wbc":
        rectangles = {"left": WBC_RECTANGLE, "right": WBC_RECTANGLE}
    else:
        rectangles = sole_rectangles(robot)
    result = {"rectangle": args.rectangle, "body": args.body, "cop_rectangles_m": rectangles, "runs": {}}
    gains_files = {f"gains:{n}": path for n, _, path in (g.partition("=") for g in args.gains) if path != "default"}
    prov = provenance.record(gains_files, argv=provenance.script_argv(__file__, argv))  # the files as they are read
    for spec in args.gains:
        name, _, path = spec.partition("=")
        if not path:
            raise ValueError(f"give gain sets as NAME=GAINS_FILE, got {spec!r}")
        gains = None if path == "default" else path  # NAME=default: the controller's default gains
        for scale in args.scales:
            tasks = out / f"feet_{args.rectangle}{round(scale * 100)}.json"
            io.atomic_write_bytes(tasks, task_file(rectangles, scale).encode())
            for weight in args.angular_weights:
                cfg = options.replace(base, gains=gains, tasks=str(tasks), angular_weight_soft=weight)
                found = envelope.search(cfg, progress=False)
                frac = {az: e["fraction_of_bound"] for az, e in found["envelope"][0].items()}
                key = f"{name}@{scale:g}" + ("" if weight == 1.0 else f"@w{weight:g}")
                result["runs"][key] = {
                    "gains": path,
                    "cop_scale": scale,
                    "angular_weight_soft": weight,
                    "fraction_of_bound": frac,
                    "median": float(np.median(list(frac.values()))),
                    "min": float(np.min(list(frac.values()))),
                    "rollouts": found["rollouts"],
                    "run_s": found["run_s"],
                }
                print(
                    json.dumps(
                        {"run": key, "median": result["runs"][key]["median"], "min": result["runs"][key]["min"]}
                    ),
                    flush=True,
                )
    result["device"] = prov["device"]["label"]
    result["provenance"] = prov
    io.atomic_write_json(out / "cop_margin.json", result)
    return result


if __name__ == "__main__":
    try:
        main()
    except (ValueError, FileNotFoundError) as err:
        sys.exit(f"error: {err}")
