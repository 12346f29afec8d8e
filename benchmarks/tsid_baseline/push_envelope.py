"""The TSID peer under pushes (``benchmarks/tsid_peer.py``): the feet-in-place LIP bound, the strict
envelope by the two-phase bisection of ``wbc_jax.jobs.envelope.bisect``, every push of the grid, and the
envelope's sensitivity to the settings without a WBC counterpart (:data:`SENSITIVITY`). JAX-free, as the
rest of the peer. ``args``: the namespace of ``tsid_peer.py``'s flags (magnitudes, directions, push onset
and duration, horizon, body, resolution, sinusoid duration, rollout timeout)."""

from __future__ import annotations

import faulthandler
import math
import time
from collections.abc import Callable

import mujoco
import numpy as np

from .controller import TsidConfig
from .model import constants, sole_contact_rectangle
from .peer import TsidPeer


def lip_bound(m: mujoco.MjModel, qpos: np.ndarray, directions_deg, mass: float | None = None) -> dict:
    """Feet-in-place bound per azimuth (``wbc_jax.jobs.sweep_table.lip_bound``, two feet): the LIP with its
    CoP on the edge of the hull of the soles' contact spheres survives a CoM velocity up to omega d
    (omega = sqrt(g / z_CoM), d the distance from the CoM to the hull along the push); as an impulse
    m omega d. qpos (nq,): the home state. Returns {azimuth: {edge_distance_m, velocity_bound_mps,
    impulse_bound_ns}}."""
    from scipy.spatial import ConvexHull

    d = mujoco.MjData(m)
    d.qpos[:] = qpos
    mujoco.mj_forward(m, d)
    geoms = [
        g for g in range(m.ngeom) if (mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, g) or "").count("_foot_contact_")
    ]
    if not geoms:
        raise ValueError("the model has no foot contact geoms (names '*_foot_contact_*')")
    hull = ConvexHull(d.geom_xpos[geoms, :2])
    base = 1  # the free-floating root body
    com = d.subtree_com[base]
    mass = float(m.body_subtreemass[base]) if mass is None else float(mass)
    omega = math.sqrt(constants.GRAVITY / com[2])
    out = {}
    for az in directions_deg:
        u = np.array([math.cos(math.radians(az)), math.sin(math.radians(az))])
        dist = min((-(eq[:2] @ com[:2] + eq[2]) / (eq[:2] @ u)) for eq in hull.equations if eq[:2] @ u > 1e-12)
        out[float(az)] = {
            "edge_distance_m": dist,
            "velocity_bound_mps": omega * dist,
            "impulse_bound_ns": mass * omega * dist,
        }
    return out


def bisect(
    impulses: np.ndarray, survives: Callable[[np.ndarray, np.ndarray], np.ndarray], searches: int, resolution: float
) -> dict:
    """The two-phase search of ``wbc_jax.jobs.envelope.bisect``: per search, the bracket of grid indices
    [lo, hi] starts at (-1: no push, M - 1: taken as a fall) and is halved until adjacent over the
    sorted distinct ``impulses`` (M,) N s, then the bracket inside that grid step is halved until at
    most ``resolution`` N s wide. ``survives(k, impulse)`` -> bool (len(k),) for the open searches k.

    Returns numpy arrays over the searches: lo (largest impulse seen to survive, 0 if none), hi,
    grid_lo (largest grid impulse seen to survive), at_cap (no grid impulse failed); rollouts, rounds."""
    impulses = np.asarray(impulses, float)
    if impulses.ndim != 1 or impulses.size == 0 or np.any(np.diff(impulses) <= 0) or impulses[0] <= 0:
        raise ValueError(f"impulses must be a sorted 1-D array of distinct positive values, got {impulses}")
    if not (math.isfinite(resolution) and resolution > 0):
        raise ValueError(f"resolution must be a positive number of N s, got {resolution}")
    at = np.concatenate([[0.0], impulses])
    lo_i, hi_i = np.full(searches, -1), np.full(searches, impulses.size - 1)
    failed = np.zeros(searches, bool)
    rollouts = rounds = 0
    while np.any(hi_i - lo_i > 1):
        k = np.flatnonzero(hi_i - lo_i > 1)
        mid = (lo_i[k] + hi_i[k]) // 2
        ok = np.asarray(survives(k, at[mid + 1]), bool)
        lo_i[k], hi_i[k] = np.where(ok, mid, lo_i[k]), np.where(ok, hi_i[k], mid)
        failed[k] |= ~ok
        rollouts, rounds = rollouts + k.size, rounds + 1
    lo, hi = at[lo_i + 1], at[hi_i + 1]
    grid_lo = lo.copy()
    while np.any(hi - lo > resolution * (1 + 1e-9)):
        k = np.flatnonzero(hi - lo > resolution * (1 + 1e-9))
        mid = 0.5 * (lo[k] + hi[k])
        ok = np.asarray(survives(k, mid), bool)
        lo[k], hi[k] = np.where(ok, mid, lo[k]), np.where(ok, hi[k], mid)
        rollouts, rounds = rollouts + k.size, rounds + 1
    return {"lo": lo, "hi": hi, "grid_lo": grid_lo, "at_cap": ~failed, "rollouts": rollouts, "rounds": rounds}


def push_of(magnitude: float, azimuth_deg: float, onset: float, duration: float) -> dict:
    """A horizontal push of ``magnitude`` N toward ``azimuth_deg`` (0 = forward = world +x, 90 =
    left), from ``onset`` for ``duration`` s (``TsidPeer.simulate``'s push dict)."""
    a = math.radians(azimuth_deg)
    return {"force": magnitude * np.array([math.cos(a), math.sin(a), 0.0]), "onset": onset, "duration": duration}


def _survived(peer: TsidPeer, config, magnitude, azimuth, args) -> tuple[bool, dict]:
    """One push rollout of the stand task: (strict survival, the summary). A rollout that runs
    longer than ``args.rollout_timeout`` s ends the process with a traceback (faulthandler: a C++
    solver that never returns holds the GIL, so no Python-level timer could stop it)."""
    faulthandler.dump_traceback_later(args.rollout_timeout, exit=True)
    try:
        r = peer.simulate(
            "stand",
            duration=args.horizon,
            push=push_of(magnitude, azimuth, args.push_onset, args.push_duration),
            push_body=args.body,
            config=config,
            record=False,
        )
    finally:
        faulthandler.cancel_dump_traceback_later()
    return bool(r["summary"]["survived"]), r["summary"]


def envelope(peer: TsidPeer, config, args, log=print) -> dict:
    """The strict envelope by :func:`bisect` over the grid's impulses, per azimuth, with the LIP bound."""
    magnitudes = np.unique(np.linspace(*args.magnitudes[:2], int(args.magnitudes[2])))
    impulses = magnitudes * args.push_duration
    azimuths = np.arange(args.directions) * 360.0 / args.directions
    start = time.perf_counter()

    def survives(k: np.ndarray, impulse: np.ndarray) -> np.ndarray:
        out = np.array(
            [_survived(peer, config, imp / args.push_duration, azimuths[j], args)[0] for j, imp in zip(k, impulse)]
        )
        log(f"  round: {k.size} rollouts, {int(out.sum())} survived ({time.perf_counter() - start:.0f} s)")
        return out

    found = bisect(impulses, survives, azimuths.size, args.resolution)
    run_s = time.perf_counter() - start
    bound = lip_bound(peer.mj_model, peer.qpos0, azimuths.tolist(), peer.mass)
    rows = {}
    for j, az in enumerate(azimuths.tolist()):
        b = bound[az]["impulse_bound_ns"]
        rows[f"{az:g}"] = {
            "impulse_ns": float(found["lo"][j]),
            "bracket_ns": [float(found["lo"][j]), float(found["hi"][j])],
            "grid_impulse_ns": float(found["grid_lo"][j]),
            "at_cap": bool(found["at_cap"][j]),
            "bound_impulse_ns": b,
            "fraction_of_bound": float(found["lo"][j]) / b,
        }
    frac = np.array([r["fraction_of_bound"] for r in rows.values()])
    imp = np.array([r["impulse_ns"] for r in rows.values()])
    return {
        "fraction_of_bound_median": float(np.median(frac)),
        "fraction_of_bound_min": float(np.min(frac)),
        "impulse_ns_median": float(np.median(imp)),
        "impulse_ns_min": float(np.min(imp)),
        "min_at_azimuth_deg": float(azimuths[int(np.argmin(frac))]),
        "rollouts": int(found["rollouts"]),
        "rounds": int(found["rounds"]),
        "grid_rollouts": int(impulses.size * azimuths.size),
        "run_s": round(run_s, 2),
        "grid_impulses": int(impulses.size),
        "resolution_ns": args.resolution,
        "directions": rows,
    }


def full_grid(peer: TsidPeer, config, args, log=print) -> dict:
    """Every push of the grid: strict and lax survival rates, the grid's envelope per azimuth
    (largest survived impulse; monotone: the largest below the first failure, as
    ``wbc_jax.jobs.sweep_table.envelope_of``), with the LIP bound."""
    magnitudes = np.unique(np.linspace(*args.magnitudes[:2], int(args.magnitudes[2])))
    azimuths = np.arange(args.directions) * 360.0 / args.directions
    start = time.perf_counter()
    survived = np.zeros((magnitudes.size, azimuths.size), bool)
    upright = np.zeros_like(survived)
    for i, mag in enumerate(magnitudes):
        for j, az in enumerate(azimuths):
            survived[i, j], s = _survived(peer, config, mag, az, args)
            upright[i, j] = s["upright"]
        log(f"  grid: {i + 1} of {magnitudes.size} magnitudes ({time.perf_counter() - start:.0f} s)")
    run_s = time.perf_counter() - start
    bound = lip_bound(peer.mj_model, peer.qpos0, azimuths.tolist(), peer.mass)
    impulses = magnitudes * args.push_duration
    rows = {}
    for j, az in enumerate(azimuths.tolist()):
        alive = survived[:, j]
        first_fail = int(np.argmin(alive)) if not alive.all() else impulses.size
        monotone = float(impulses[first_fail - 1]) if first_fail > 0 else 0.0
        b = bound[az]["impulse_bound_ns"]
        rows[f"{az:g}"] = {
            "largest_survived_impulse_ns": float(impulses[alive].max()) if alive.any() else 0.0,
            "monotone_impulse_ns": monotone,
            "islands": int(alive[first_fail:].sum()),
            "bound_impulse_ns": b,
            "monotone_fraction_of_bound": monotone / b,
        }
    frac = np.array([r["monotone_fraction_of_bound"] for r in rows.values()])
    return {
        "survival_rate": float(survived.mean()),
        "upright_rate": float(upright.mean()),
        "monotone_fraction_of_bound_median": float(np.median(frac)),
        "monotone_fraction_of_bound_min": float(np.min(frac)),
        "rollouts": int(survived.size),
        "run_s": round(run_s, 2),
        "directions": rows,
        "survived": survived.astype(int).tolist(),
        "magnitudes_n": magnitudes.tolist(),
        "azimuths_deg": azimuths.tolist(),
    }


# Settings without a WBC counterpart (and the posture's damping), one at a time against the
# defaults: how far the envelope moves with them (``--sensitivity``).
SENSITIVITY = {
    "w_am=1e-2": {"w_am": 1e-2},
    "w_am=1e-4": {"w_am": 1e-4},
    "w_posture=1e-4": {"w_posture": 1e-4},
    "w_posture=1e-2": {"w_posture": 1e-2},
    "contact_kp=10": {"contact_kp": 10.0},
    "kd_com=2sqrt(kp_com) (TSID's critical damping)": {"kd_com": "critical"},  # of the robot's K_P,CoM
    "foot_size=the soles' contact spheres": {"foot_size": "contact spheres"},  # sole_contact_rectangle
}


def sensitivity(peer: TsidPeer, args, log=print) -> dict:
    """The sinusoid's CoM RMSE and the bisection envelope of each :data:`SENSITIVITY` variant."""
    out = {}
    for name, change in SENSITIVITY.items():
        log(f"sensitivity: {name}")
        if change.get("foot_size") == "contact spheres":
            change = {**change, "foot_size": sole_contact_rectangle(peer.mj_model, robot=peer.robot)}
        if change.get("kd_com") == "critical":
            change = {**change, "kd_com": tuple(2 * np.sqrt(peer.description.gains.kp_com))}
        config = TsidConfig(**change)
        sin = peer.simulate("sinusoid", duration=args.sinusoid_duration, config=config, record=False)["summary"]
        e = envelope(peer, config, args, log=lambda _: None)
        out[name] = {
            "change": {k: list(v) if isinstance(v, tuple) else v for k, v in change.items()},
            "sinusoid_com_rmse_m": sin["com_rmse_m"],
            "sinusoid_survived": sin["survived"],
            "fraction_of_bound_median": e["fraction_of_bound_median"],
            "fraction_of_bound_min": e["fraction_of_bound_min"],
            "fraction_of_bound": {az: round(r["fraction_of_bound"], 4) for az, r in e["directions"].items()},
            "rollouts": e["rollouts"],
            "run_s": e["run_s"],
        }
    return out
