"""The recovery envelope by batched bisection instead of a magnitude grid.

Per direction and gain set (K searches), the largest survived push impulse is found in two
phases, each round one batch of the sweep's closed loop over the searches still open:

1. bisection over the sweep's own impulses (``cfg.magnitudes`` x ``cfg.push_duration``, M of
   them): the bracket of grid indices [lo, hi] starts at (-1: no push, M - 1: taken as a fall)
   and is halved until adjacent, ceil(log2 M) rounds;
2. bisection inside that grid step, between its two impulses, until the bracket is at most
   ``resolution`` N s wide.

K x (ceil(log2 M) + ceil(log2(step / resolution))) rollouts against K x M for the grid. Survival
is the sweep's (strict) criterion. The search assumes it is monotone in the impulse, as the grid's
monotone envelope does; where it is, phase 1 brackets the grid's monotone envelope exactly when
both see the same outcomes on the grid's impulses (a continuous bisection does not: it steps over
grid impulses, and a boundary set by two thresholds crossed tangentially is not monotone between
them, BENCHMARKS.md). Survival islands near the boundary (experiments/checks/island_check.py) and
run-to-run variation of the engine can still move it by a grid step.
"""

from __future__ import annotations

import dataclasses
import math
import pathlib
from collections.abc import Callable
from typing import ClassVar

import jax
import numpy as np

from wbc_jax.control.gains import gains_to_dict
from wbc_jax.core import io, provenance
from wbc_jax.core.options import flat_dict, option
from wbc_jax.jobs import grids, runs, sweep, sweep_config, sweep_table
from wbc_jax.robot import model
from wbc_jax.sim import metrics as metrics_lib
from wbc_jax.sim import runner, scenario

# The grid of the documented sweeps (results/sweep_h100): 64 trunk pushes of 10-400 N for 0.1 s.
DEFAULT_MAGNITUDES = tuple(float(x) for x in np.linspace(10.0, 400.0, 64))
# Bisection rounds inside one grid step at most: 2^-20 of a step is far below any engine's
# run-to-run variation.
MAX_REFINE_ROUNDS = 20


@dataclasses.dataclass(frozen=True)
class EnvelopeConfig(sweep_config.SweepConfig):
    """An envelope search: the sweep's fields (its grid of impulses: magnitudes x push duration)
    and the bracket width to reach. The CLI flags of ``wbc-jax envelope`` are generated from
    these fields."""

    magnitudes: tuple[float, ...] = grids.magnitudes_option(
        DEFAULT_MAGNITUDES,
        "push force grid [N]: LO HI N (the impulses searched: each x --push-duration)",
        positive=True,
    )
    chunk_size: int = option(
        1024,
        "searches per compiled batch (at most the searches; its memory is estimated and "
        "checked before it is allocated)",
        ge=1,
        le=sweep_config.MAX_ENVS,
    )
    out: str | None = option("runs/envelope", "output folder")
    KIND: ClassVar[str] = "envelope"
    resolution: float = option(0.25, "bracket width to reach [N s]", ge=1e-3, le=1e3, unit="N s")

    def check(self) -> None:
        super().check()
        impulses = np.unique(np.asarray(self.magnitudes, float)) * self.push_duration
        _, refine = rounds_needed(impulses, self.resolution)
        if refine > MAX_REFINE_ROUNDS:
            raise ValueError(
                f"--resolution {self.resolution:g} N s needs {refine} bisection rounds inside a grid step "
                f"of this grid, more than {MAX_REFINE_ROUNDS}; use a coarser resolution"
            )


def default_config() -> EnvelopeConfig:
    """The sweep's defaults on the grid of the documented sweeps."""
    return EnvelopeConfig()


def rounds_needed(impulses: np.ndarray, resolution: float) -> tuple[int, int]:
    """(grid rounds, refinement rounds) of a search over the sorted distinct ``impulses`` (M,)."""
    grid_rounds = math.ceil(math.log2(impulses.size)) if impulses.size > 1 else 0
    widest = float(np.max(np.diff(np.concatenate([[0.0], impulses]))))
    return grid_rounds, max(0, math.ceil(math.log2(widest / resolution)))


def bisect(
    impulses: np.ndarray,
    survives: Callable[[np.ndarray, np.ndarray], np.ndarray],
    searches: int,
    resolution: float,
    on_round: Callable[[], None] | None = None,
) -> dict:
    """Largest survived impulse of each of ``searches`` searches, by the two phases of this
    module over the sorted distinct ``impulses`` (M,) N s.

    ``survives(k, impulse)``: survival (bool (n,)) of searches ``k`` (int (n,)) pushed with
    ``impulse`` (n,) N s; only the searches whose bracket is still open are asked. Returns numpy
    arrays over the searches: "lo" (largest impulse seen to survive, 0 if none), "hi" (smallest
    seen to fail, or the largest grid impulse, never run, for "at_cap"), "grid_lo" (largest grid
    impulse seen to survive), "at_cap" (no grid impulse failed), and "rollouts", "rounds"."""
    impulses = np.asarray(impulses, float)
    if impulses.ndim != 1 or impulses.size == 0 or np.any(np.diff(impulses) <= 0) or impulses[0] <= 0:
        raise ValueError(f"impulses must be a sorted 1-D array of distinct positive values, got {impulses}")
    if not (math.isfinite(resolution) and resolution > 0):
        raise ValueError(f"resolution must be a positive number of N s, got {resolution}")
    at = np.concatenate([[0.0], impulses])  # at[i + 1]: grid index i; at[0]: no push
    lo_i = np.full(searches, -1)
    hi_i = np.full(searches, impulses.size - 1)
    rollouts = rounds = 0
    failed_in_grid = np.zeros(searches, bool)
    while np.any(hi_i - lo_i > 1):
        k = np.flatnonzero(hi_i - lo_i > 1)
        mid = (lo_i[k] + hi_i[k]) // 2
        ok = np.asarray(survives(k, at[mid + 1]), bool)
        lo_i[k] = np.where(ok, mid, lo_i[k])
        hi_i[k] = np.where(ok, hi_i[k], mid)
        failed_in_grid[k] |= ~ok
        rollouts, rounds = rollouts + k.size, rounds + 1
        if on_round is not None:
            on_round()
    lo, hi = at[lo_i + 1], at[hi_i + 1]
    grid_lo = lo.copy()
    while np.any(hi - lo > resolution * (1 + 1e-9)):
        k = np.flatnonzero(hi - lo > resolution * (1 + 1e-9))
        mid = 0.5 * (lo[k] + hi[k])
        ok = np.asarray(survives(k, mid), bool)
        lo[k] = np.where(ok, mid, lo[k])
        hi[k] = np.where(ok, hi[k], mid)
        rollouts, rounds = rollouts + k.size, rounds + 1
        if on_round is not None:
            on_round()
    return {"lo": lo, "hi": hi, "grid_lo": grid_lo, "at_cap": ~failed_in_grid, "rollouts": rollouts, "rounds": rounds}


def search(cfg: sweep_config.SweepConfig, *, resolution: float | None = None, progress: bool = True) -> dict:
    """The largest survived impulse per direction (and gain set) of ``cfg`` to its ``resolution``
    N s (a :class:`~wbc_jax.jobs.sweep_config.SweepConfig` is searched at ``resolution``, default
    0.25, in batches of the envelope's default chunk size), by :func:`bisect` over the impulses of the sweep's grid (``cfg.magnitudes`` x
    ``cfg.push_duration``). Each search keeps one draw of the plant and posture perturbations for
    all its rounds; each round runs the open searches in batches of ``cfg.chunk_size`` (and
    ``cfg.queue`` scenarios per batch slot).

    Returns {"envelope": {gain set: {azimuth: {"impulse_ns", "bracket_ns", "grid_impulse_ns",
    "at_cap", "bound_impulse_ns", "fraction_of_bound"}}}, "rollouts", "rounds", "run_s",
    "compile_s", ...}; writes summary.json into ``cfg.out`` when set."""
    from tqdm.auto import tqdm

    if not isinstance(cfg, EnvelopeConfig):  # a sweep's grid and settings; its chunk size is the grid's, not ours
        fields = {f.name: getattr(cfg, f.name) for f in dataclasses.fields(cfg)}  # nested groups kept whole
        cfg = EnvelopeConfig(
            **{**fields, "chunk_size": EnvelopeConfig.chunk_size}, resolution=0.25 if resolution is None else resolution
        )
    elif resolution is not None:
        cfg = dataclasses.replace(cfg, resolution=resolution)
    cfg.check()
    resolution = cfg.resolution
    magnitudes = np.unique(np.asarray(cfg.magnitudes, float))
    dtype = scenario.float_dtype()
    robot = model.load_robot(cfg.robot)
    base = sweep.base_gains(cfg, robot.index.n, dtype)
    st = sweep.make_setup(cfg, base)
    rng = np.random.default_rng(cfg.seed)
    sets = sweep.gain_sets(base, cfg.gain_sets, cfg.gain_scale_range, rng)
    azi, gset = (
        a.ravel() for a in np.meshgrid(np.asarray(cfg.directions, float), np.arange(cfg.gain_sets), indexing="ij")
    )
    K = azi.size
    batch = min(cfg.chunk_size, K)
    runner.check_memory(st, batch, envs=K, queue=cfg.queue, flag="--chunk-size")
    if cfg.out is not None:
        runs.claim_output_dir(cfg.out, cfg.KIND, cfg.fingerprint())
    friction, mass_scale = rng.uniform(*cfg.friction, K), rng.uniform(*cfg.mass_scale, K)
    joint_offset = (
        rng.normal(scale=cfg.joint_noise, size=(K, robot.index.n)) if cfg.joint_noise else np.zeros((K, robot.index.n))
    )
    push_end = cfg.push_onset + cfg.push_duration
    impulses = magnitudes * cfg.push_duration
    timing = {"compile_s": 0.0, "run_s": 0.0, "started": None}
    finished_run_s: list[float] = []  # each batch's run: the watchdog's default bound (--stall-timeout-s)

    def survives(k: np.ndarray, impulse: np.ndarray) -> np.ndarray:
        scen, _ = sweep.scenarios_at(
            cfg, sets, impulse / cfg.push_duration, azi[k], gset[k], friction[k], mass_scale[k], joint_offset[k], dtype
        )
        alive = []
        for lo in range(0, k.size, batch):  # one compiled shape for every round
            part = jax.tree_util.tree_map(lambda x, lo=lo: np.asarray(x)[lo : lo + batch], scen)
            watch = cfg.watchdog(len(finished_run_s), finished_run_s)  # its chunks: the batches run so far
            result = runner.run(st, part, batch_size=batch, queue=cfg.queue, watch=watch)
            finished_run_s.append(result.run_s)
            timing["compile_s"] += result.compile_s
            timing["started"] = timing["started"] or result.started
            timing["run_s"] += result.run_s
            alive.append(np.asarray(metrics_lib.summarize(result.metrics, push_end)["survived"]))
        return np.concatenate(alive)

    bar = tqdm(
        total=sum(rounds_needed(impulses, resolution)),
        unit="round",
        disable=not progress,
        desc=f"envelope ({st.backend})",
    )
    found = bisect(impulses, survives, K, resolution, on_round=lambda: bar.update(1))
    bar.close()
    support = "left-foot" if cfg.task == "one-foot" else "two-feet"
    bound = sweep_table.lip_bound(st.robot, sorted(set(azi.tolist())), support, cfg.elevation)
    envelope: dict = {}
    for k in range(K):
        b = bound[float(azi[k])]["impulse_bound_ns"]
        envelope.setdefault(int(gset[k]), {})[float(azi[k])] = {
            "impulse_ns": float(found["lo"][k]),
            "bracket_ns": [float(found["lo"][k]), float(found["hi"][k])],
            "grid_impulse_ns": float(found["grid_lo"][k]),
            "at_cap": bool(found["at_cap"][k]),
            "bound_impulse_ns": b,
            "fraction_of_bound": sweep_table.fraction(float(found["lo"][k]), b),
        }
    summary = {
        "envelope": envelope,
        "rounds": found["rounds"],
        "rollouts": int(found["rollouts"]),
        "searches": K,
        "grid_impulses": int(impulses.size),
        "grid_rollouts": int(K * impulses.size),
        "resolution_ns": resolution,
        "backend": st.backend,
        "device": provenance.device_label(),
        "compile_s": round(timing["compile_s"], 2),
        "run_s": round(timing["run_s"], 2),
        "started_s": round(timing["started"] - provenance.process_started(), 2),
        "config": flat_dict(cfg),
        "gains": gains_to_dict(base),
        "provenance": provenance.record({"gains": cfg.gains, "tasks": cfg.controller.tasks}),
    }
    if cfg.out is not None:
        io.atomic_write_json(pathlib.Path(cfg.out) / "summary.json", summary)
        runs.record_output(pathlib.Path(cfg.out) / "summary.json")
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
            "bisection_grid_ns": e.get("grid_impulse_ns"),
            "grid_monotone_ns": g["monotone_impulse_ns"],
            "difference_ns": diff,
        }
    return {
        "directions": rows,
        "max_abs_difference_ns": worst,
        "grid_step_ns": grid_step_ns,
        "within_one_grid_step": worst <= grid_step_ns + 1e-9,
        "grid_cell_agrees": sum(
            1
            for r in rows.values()
            if r["bisection_grid_ns"] is not None and abs(r["bisection_grid_ns"] - r["grid_monotone_ns"]) < 1e-9
        ),
    }
