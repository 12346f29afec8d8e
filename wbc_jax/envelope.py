"""[experiments] The recovery envelope by batched bisection instead of a magnitude grid.

Per direction and gain set (K searches), the largest survived push impulse is bracketed in
[lo, hi] and halved each round: round r runs the K midpoints as one batch on the sweep's closed
loop. ``rounds = ceil(log2(impulse_max / resolution))`` rounds cost K x rounds rollouts, against
K x M for an M-magnitude grid. Survival is the sweep's (strict) criterion; a search assumes it
is monotone in the impulse, as the grid's monotone envelope does (survival islands near the
boundary, experiments/island_check.py, can move the bisection by a grid step).
"""

from __future__ import annotations

import dataclasses
import math
import pathlib

import numpy as np

from wbc_jax import io, model, runs, scenario, sweep
from wbc_jax import metrics as metrics_lib
from wbc_jax.gains import gains_to_dict


def search(cfg: sweep.SweepConfig, *, impulse_max: float, resolution: float = 0.25, robot_name: str = "icub",
           progress: bool = True) -> dict:  # fmt: skip
    """Bisect the largest survived impulse per direction (and gain set) of ``cfg`` in
    [0, ``impulse_max``] N s to ``resolution`` N s (``cfg.magnitudes`` is not used). Each search
    keeps one draw of the plant and posture perturbations for all its rounds.

    Returns {"envelope": {gain set: {azimuth: {"impulse_ns", "bracket_ns", "bound_impulse_ns",
    "fraction_of_bound"}}}, "rollouts", "rounds", "run_s", "compile_s", ...}; writes summary.json
    into ``cfg.out`` when set."""
    from tqdm.auto import tqdm

    cfg.check()
    if not (math.isfinite(impulse_max) and impulse_max > 0 and math.isfinite(resolution) and resolution > 0):
        raise ValueError(f"impulse_max and resolution must be positive, got {impulse_max}, {resolution}")
    if cfg.out is not None:
        runs.check_output_dir(cfg.out, "envelope")
    dtype = scenario.float_dtype()
    robot = model.load_robot(robot_name)
    base = sweep.base_gains(cfg, robot.index.n, dtype)
    robot.index.body_id(cfg.body)
    st = sweep.make_setup(cfg, base, robot_name=robot_name)
    rng = np.random.default_rng(cfg.seed)
    sets = sweep.gain_sets(base, cfg.gain_sets, cfg.gain_scale_range, rng)
    azi, gset = (
        a.ravel() for a in np.meshgrid(np.asarray(cfg.directions, float), np.arange(cfg.gain_sets), indexing="ij")
    )
    K = azi.size
    friction, mass_scale = rng.uniform(*cfg.friction, K), rng.uniform(*cfg.mass_scale, K)
    joint_offset = (
        rng.normal(scale=cfg.joint_noise, size=(K, robot.index.n)) if cfg.joint_noise else np.zeros((K, robot.index.n))
    )
    rounds = max(1, math.ceil(math.log2(impulse_max / resolution)))
    lo, hi = np.zeros(K), np.full(K, float(impulse_max))
    push_end = cfg.push_onset + cfg.push_duration
    compile_s = run_s = 0.0
    for _ in tqdm(range(rounds), unit="round", disable=not progress, desc=f"envelope ({st.backend})"):
        mid = 0.5 * (lo + hi)
        scen, _ = sweep.scenarios_at(cfg, sets, mid / cfg.push_duration, azi, gset, friction, mass_scale,
                                     joint_offset, dtype)  # fmt: skip
        result = scenario.run(st, scen, batch_size=K)
        compile_s += result.compile_s
        run_s += result.run_s
        survived = np.asarray(metrics_lib.summarize(result.metrics, push_end)["survived"])
        lo, hi = np.where(survived, mid, lo), np.where(survived, hi, mid)
    support = "left-foot" if cfg.task == "one-foot" else "two-feet"
    bound = sweep.lip_bound(st.robot, sorted(set(azi.tolist())), support)
    envelope: dict = {}
    for k in range(K):
        b = bound[float(azi[k])]["impulse_bound_ns"]
        envelope.setdefault(int(gset[k]), {})[float(azi[k])] = {
            "impulse_ns": float(lo[k]), "bracket_ns": [float(lo[k]), float(hi[k])],
            "bound_impulse_ns": b, "fraction_of_bound": float(lo[k]) / b,
        }  # fmt: skip
    summary = {
        "envelope": envelope, "rounds": rounds, "rollouts": K * rounds, "searches": K,
        "impulse_max_ns": impulse_max, "resolution_ns": resolution, "backend": st.backend,
        "compile_s": round(compile_s, 2), "run_s": round(run_s, 2), "config": dataclasses.asdict(cfg),
        "gains": gains_to_dict(base),
    }  # fmt: skip
    if cfg.out is not None:
        out = pathlib.Path(cfg.out)
        runs.claim_output_dir(out, "envelope", runs.fingerprint({**dataclasses.asdict(cfg), "impulse_max": impulse_max,
                                                                 "resolution": resolution}, [cfg.gains, cfg.tasks]))  # fmt: skip
        io.atomic_write_json(out / "summary.json", summary)
    return summary


def compare_with_grid(found: dict, grid_summary: dict, grid_step_ns: float) -> dict:
    """Per direction of gain set 0: the bisection's impulse against the grid's monotone envelope,
    and whether they agree within one grid step."""
    rows, worst = {}, 0.0
    for az, e in found["envelope"][0].items():
        g = grid_summary["envelope"][str(az)] if str(az) in grid_summary["envelope"] else grid_summary["envelope"][az]
        diff = e["impulse_ns"] - g["monotone_impulse_ns"]
        worst = max(worst, abs(diff))
        rows[az] = {
            "bisection_ns": e["impulse_ns"],
            "grid_monotone_ns": g["monotone_impulse_ns"],
            "difference_ns": diff,
        }
    return {"directions": rows, "max_abs_difference_ns": worst, "grid_step_ns": grid_step_ns,
            "within_one_grid_step": worst <= grid_step_ns + 1e-9}  # fmt: skip
