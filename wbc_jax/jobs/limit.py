"""``wbc-jax limit``: the physical limit of push recovery, by trajectory optimisation through MJX.

For a push (body, azimuth, elevation, duration, onset), the largest impulse from which **some**
joint-torque trajectory within the motor limits (+-60 N m) recovers under the strict criterion
(feet in place: slip <= 2 cm, tilt <= 5 deg while in full contact; no fall; the CoM settled over
the support polygon at the end of the horizon). The feasibility test is the trajectory optimiser
of :mod:`wbc_jax.jobs.trajopt` (torques around the balancing controller's in a window after the
onset, the controller alone after it), and a candidate counts only when its trajectory passes the
strict criterion twice: on MJX (the engine it was optimised on, float32 on a GPU) and replayed in
C MuJoCo (float64 physics; the same policy: its u, then the controller) (:mod:`wbc_jax.jobs.limit_rounds`).
The torques applied in that replay are a torque trajectory within the limits that C MuJoCo says
recovers: the witness. A failed optimisation proves nothing, so the limit is a lower bound, the
largest impulse with a witness; the bracket's upper end is where the optimiser stopped finding one.

The search is a batched bisection in rounds, all directions x ``candidates`` impulses of a round
optimised in one batch (vmap):

1. round 1: ``candidates`` impulses per direction from the best controller envelope given
   (``--envelopes``; else ``lower_fraction`` x the LIP bound) to ``upper_fraction`` x the LIP bound;
2. each later round: ``candidates`` impulses evenly inside the bracket (largest verified impulse,
   smallest failed one above it), or above the largest tested one where nothing failed (at cap);
   warm starts from the verified trajectory of the same direction with the next lower impulse.

After every round the state is written atomically (``state.json``, ``witness.npz``) and a rerun
with the same ``--out`` resumes after the last finished round. The pushed body travels in the
pushes (``Push.body``), so every body shares one compiled program.
"""

from __future__ import annotations

import dataclasses
import json
import math
import pathlib

import numpy as np

from wbc_jax.core import constants
from wbc_jax.core.types import option
from wbc_jax.jobs import runs, sweep_config, trajopt


def _files(values) -> tuple[str, ...]:
    return tuple(str(v) for v in values)


@dataclasses.dataclass(frozen=True)
class LimitConfig:
    """What ``wbc-jax limit`` searches, and how; its fields are the command's flags."""

    directions: tuple[float, ...] = option(
        (0.0, 90.0, 180.0, 270.0), "number of push azimuths over 360 deg (0 = forward, 90 = left)",
        metavar="N", parse=sweep_config._azimuths, show=len,
    )  # fmt: skip
    elevation: float = option(0.0, "push elevation [deg]")
    push_duration: float = option(0.1, "push length [s]")
    push_onset: float = option(0.5, "push start [s]")
    body: str = option("chest", "pushed body")
    gains: str | None = option(None, "gains JSON file of the balancing controller around which torques are optimised",
                               metavar="FILE")  # fmt: skip
    horizon: float = option(3.0, "seconds per rollout (the strict criterion is judged at its end)")
    window: float = option(0.6, "seconds of optimised torques from the push onset (the controller alone after)")
    tail: float = option(0.2, "seconds of controller-only ticks after the window in the optimiser's cost")
    candidates: int = option(4, "impulses per direction in each round (all optimised in one batch)")
    rounds: int = option(3, "rounds of the bisection")
    knot_interval: float = option(0.05, "seconds between the knots of the optimised torques (linear between; "
                                  "0.01: every control tick free)")  # fmt: skip
    method: str = option("es", "optimiser: es (evolution-strategies gradient, forward rollouts) or gradient (exact, "
                         "through the closed loop)", choices=trajopt.METHODS)  # fmt: skip
    iterations: int = option(40, "optimiser (Adam) steps per round")
    learning_rate: float = option(1.0, "Adam's step [N m]")
    es_pairs: int = option(8, "es: antithetic sample pairs per candidate and step")
    es_sigma: float = option(2.0, "es: spread of the samples [N m]")
    clip_norm: float = option(10.0, "gradient: per-candidate gradient clip (global norm)")
    judge_every: int = option(10, "optimiser steps between strict checks on MJX (a passing trajectory is kept)")
    envelopes: tuple[str, ...] = option(
        (), "strict envelope summaries of controllers (wbc-jax envelope --out DIR: DIR/summary.json) to compare; "
        "the best one per direction starts the search", nargs="*", metavar="FILE", parse=_files,
    )  # fmt: skip
    lower_fraction: float = option(0.3, "first impulse of the search without --envelopes, x the LIP bound")
    upper_fraction: float = option(1.3, "last impulse of round 1, x the LIP bound")
    slip_margin: float = option(0.01, "the optimiser's slip margin [m] (strict test: 0.02)")
    tilt_margin_deg: float = option(3.0, "the optimiser's sole tilt margin [deg] (strict test: 5)")
    solver_iterations: int | None = option(None, "contact solver Newton iterations (default: the model's, 4)")
    out: str = option("runs/limit", "output folder (a search resumes there)")

    def check(self, robot=None) -> None:
        """Every check before anything compiles (``robot``: also the pushed body's name)."""
        if not self.directions:
            raise ValueError("--directions: give at least one direction")
        numbers = ("elevation", "push_duration", "push_onset", "horizon", "window", "tail", "knot_interval",
                   "learning_rate", "es_sigma", "clip_norm", "lower_fraction", "upper_fraction", "slip_margin",
                   "tilt_margin_deg")  # fmt: skip
        for name in numbers:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"--{name.replace('_', '-')} must be a finite number, got {value!r}")
            if name != "elevation" and value < 0:
                raise ValueError(f"--{name.replace('_', '-')} must be >= 0, got {value}")
        for name in ("push_duration", "window", "knot_interval", "learning_rate", "es_sigma", "clip_norm",
                     "lower_fraction", "slip_margin", "tilt_margin_deg"):  # fmt: skip
            if not getattr(self, name) > 0:
                raise ValueError(f"--{name.replace('_', '-')} must be > 0, got {getattr(self, name)}")
        if not self.upper_fraction > self.lower_fraction:
            raise ValueError(
                f"--upper-fraction {self.upper_fraction} must exceed --lower-fraction {self.lower_fraction}"
            )
        if (
            not self.slip_margin < constants.SURVIVAL_MAX_SLIP_M
            or not self.tilt_margin_deg < constants.SURVIVAL_MAX_TILT_DEG
        ):
            raise ValueError(f"the margins must be inside the strict tests (slip < {constants.SURVIVAL_MAX_SLIP_M} m, "
                             f"tilt < {constants.SURVIVAL_MAX_TILT_DEG} deg), got {self.slip_margin}, {self.tilt_margin_deg}")  # fmt: skip
        if self.push_onset + max(self.push_duration, self.window + self.tail) >= self.horizon:
            raise ValueError(f"--horizon {self.horizon} s must end after the push and the optimised window and tail "
                             f"({self.push_onset} + max({self.push_duration}, {self.window} + {self.tail}) s)")  # fmt: skip
        if self.method not in trajopt.METHODS:
            raise ValueError(f"unknown --method {self.method!r}; valid: {list(trajopt.METHODS)}")
        for name in ("candidates", "rounds", "iterations", "judge_every", "es_pairs"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"--{name.replace('_', '-')} must be a whole number >= 1, got {value!r}")
        runs.check_input_file(self.gains, "gains")
        for path in self.envelopes:
            runs.check_input_file(path, "envelopes")
        self.sweep("mujoco").check()
        load_envelopes(self)
        if robot is not None:
            robot.index.body_id(self.body)

    def sweep(self, backend: str, body: str | None = None) -> sweep_config.SweepConfig:
        """The sweep config that pushes and simulates alike (its setups and scenarios)."""
        return sweep_config.SweepConfig(
            magnitudes=(1.0,), directions=self.directions, elevation=self.elevation, push_duration=self.push_duration,
            push_onset=self.push_onset, body=body or self.body, gains=self.gains, horizon=self.horizon,
            solver_iterations=self.solver_iterations, backend=backend, out=None,
        )  # fmt: skip

    def cost(self) -> trajopt.Cost:
        return trajopt.Cost(slip_margin=self.slip_margin, tilt_margin_deg=self.tilt_margin_deg)

    def ticks(self, control_dt: float = constants.CONTROL_DT) -> tuple[int, int, int, int]:
        """(onset tick k0, window ticks T, tail ticks, ticks between knots): the window starts at
        the tick the push starts in."""
        k0 = int(math.floor(self.push_onset / control_dt + 1e-9))
        T = max(1, int(round(self.window / control_dt)))
        return k0, T, int(round(self.tail / control_dt)), max(1, int(round(self.knot_interval / control_dt)))


def default_config() -> LimitConfig:
    return LimitConfig()


def load_envelopes(cfg: LimitConfig) -> dict:
    """{label: {azimuth: impulse N s}} of the ``--envelopes`` files (label: the file's folder), each
    checked to be an envelope of the same push (body, duration, onset, elevation) covering every
    azimuth of the search."""
    out = {}
    for path in cfg.envelopes:
        path = pathlib.Path(path)
        try:
            data = json.loads(path.read_text())
            env = data["envelope"].get("0", data["envelope"].get(0))
            pushed = data["config"]
        except (OSError, json.JSONDecodeError, UnicodeDecodeError, KeyError, AttributeError, TypeError) as err:
            raise ValueError(f"--envelopes {path}: not the summary.json of wbc-jax envelope ({err})") from None
        for key in ("body", "push_duration", "push_onset", "elevation"):
            if pushed.get(key) != getattr(cfg, key):
                raise ValueError(f"--envelopes {path}: its pushes have {key} {pushed.get(key)!r}, the search "
                                 f"{getattr(cfg, key)!r}")  # fmt: skip
        table = {float(a): float(e["impulse_ns"]) for a, e in env.items()}
        missing = [a for a in cfg.directions if float(a) not in table]
        if missing:
            raise ValueError(f"--envelopes {path}: no envelope at azimuths {missing[:4]} of the search "
                             f"(it has {sorted(table)[:4]}...); use the same --directions")  # fmt: skip
        label = path.parent.name if path.name == "summary.json" else path.stem
        out[label] = {float(a): table[float(a)] for a in cfg.directions}
    return out


# ---------------------------------------------------------------------------------------------
# The bracket of one direction, from what was tested: [(impulse, verified)]


def bracket(tested: list) -> tuple[float, float]:
    """(largest verified impulse (0: none), smallest failed impulse above it (inf: none))."""
    lo = max([J for J, ok in tested if ok], default=0.0)
    hi = min([J for J, ok in tested if not ok and J > lo], default=math.inf)
    return lo, hi


def next_impulses(tested: list, K: int, lower: float, upper: float) -> np.ndarray:
    """The K impulses of a direction's next round: round 1 (nothing tested) K from ``lower`` to
    ``upper``; later K evenly inside the bracket, or, when nothing above the largest verified
    impulse failed, K evenly above it over the span of round 1."""
    if not tested:
        return np.linspace(lower, upper, K) if K > 1 else np.array([upper])
    lo, hi = bracket(tested)
    if math.isinf(hi):
        top = max(J for J, _ in tested)
        return top + (upper - lower) * np.arange(1, K + 1) / K
    return lo + (hi - lo) * np.arange(1, K + 1) / (K + 1)
