"""``wbc-jax limit``: the physical limit of push recovery, by trajectory optimisation through MJX.

For a push (body, azimuth, elevation, duration, onset), the largest impulse from which **some**
joint-torque trajectory within the motor limits (the model's actuators) recovers under the strict criterion
(feet in place: slip <= 2 cm, tilt <= 5 deg while in full contact; no fall; the CoM settled over
the support polygon at the end of the horizon). The feasibility test is the trajectory optimiser
of :mod:`wbc_jax.jobs.trajopt` (torques around the balancing controller's in a window after the
onset, the controller alone after it), and a candidate counts only when a trajectory of it passes the
strict criterion replayed in C MuJoCo (float64 physics; the same policy: its u, then the controller);
MJX's strict judge (the engine it was optimised on, float32 on a GPU) picks which u of the
optimisation is replayed (:mod:`wbc_jax.jobs.limit_rounds`).
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

from wbc_jax.core import constants, loader
from wbc_jax.core.options import check_options, option
from wbc_jax.jobs import grids, runs, sweep_config, trajopt
from wbc_jax.robot import model
from wbc_jax.robot.robots import DEFAULT_ROBOT, describe, robot_option
from wbc_jax.sim import scenario

MAX_HORIZON_S = 60.0  # a limit search rolls out its whole horizon per judge: minutes, not hours
MAX_WINDOW_S = 5.0  # optimised seconds: a push is recovered (or not) within seconds
# The flags in N m are checked against the robot's largest motor limit (LimitConfig.check); this
# declared range only keeps a typo's exponent out of the help text's ranges.
MAX_TORQUE_NM = 1e4


def _files(values) -> tuple[str, ...]:
    return tuple(str(v) for v in values)


@dataclasses.dataclass(frozen=True)
class LimitConfig:
    """What ``wbc-jax limit`` searches, and how; its fields are the command's flags, their declared
    ranges checked by :meth:`check`."""

    robot: str = robot_option()
    directions: tuple[float, ...] = grids.directions_option((0.0, 90.0, 180.0, 270.0))
    elevation: float = option(0.0, "push elevation [deg]", ge=-90.0, le=90.0, unit="deg")
    push_duration: float = grids.push_duration_option()
    push_onset: float = grids.push_onset_option()
    body: str = option(
        "trunk",
        "pushed body: a body of the robot or a role (trunk, pelvis, left_hand, right_thigh)",
        names=model.pushable_bodies,
    )
    gains: str | None = option(
        None,
        "gains JSON file of the balancing controller around which torques are optimised",
        metavar="FILE",
        input_file=True,
    )
    horizon: float = option(
        3.0, "seconds per rollout (the strict criterion is judged at its end)", gt=0.0, le=MAX_HORIZON_S, unit="s"
    )
    window: float = option(
        0.6,
        "seconds of optimised torques from the push onset (the controller alone after)",
        gt=0.0,
        le=MAX_WINDOW_S,
        unit="s",
    )
    tail: float = option(
        0.2,
        "seconds of controller-only ticks after the window in the optimiser's cost",
        ge=0.0,
        le=MAX_WINDOW_S,
        unit="s",
    )
    candidates: int = option(4, "impulses per direction in each round (all optimised in one batch)", ge=1, le=64)
    rounds: int = option(3, "rounds of the bisection", ge=1, le=20)
    knot_interval: float = option(
        0.05,
        "seconds between the knots of the optimised torques (linear between; 0.01: every control tick free)",
        ge=0.01,
        le=MAX_WINDOW_S,
        unit="s",
    )
    method: str = option(
        "es",
        "optimiser: es (evolution-strategies gradient, forward rollouts) or gradient (exact, through the closed loop)",
        choices=trajopt.METHODS,
    )
    iterations: int = option(40, "optimiser (Adam) steps per round", ge=1, le=100_000)
    learning_rate: float = option(
        1.0, "Adam's step [N m], at most the robot's largest motor limit", gt=0.0, le=MAX_TORQUE_NM, unit="N m"
    )
    es_pairs: int = option(8, "es: antithetic sample pairs per candidate and step", ge=1, le=1024)
    es_sigma: float = option(
        2.0,
        "es: spread of the samples [N m], at most the robot's largest motor limit",
        gt=0.0,
        le=MAX_TORQUE_NM,
        unit="N m",
    )
    clip_norm: float = option(10.0, "gradient: per-candidate gradient clip (global norm)", gt=0.0, le=1e6)
    judge_every: int = option(
        10, "optimiser steps between strict checks on MJX (a passing trajectory is kept)", ge=1, le=100_000
    )
    envelopes: tuple[str, ...] = option(
        (),
        "strict envelope summaries of controllers (wbc-jax envelope --out DIR: DIR/summary.json) to compare; "
        "the best one per direction starts the search",
        nargs="*",
        metavar="FILE",
        parse=_files,
        input_file=True,
    )
    lower_fraction: float = option(
        0.3, "first impulse of the search without --envelopes, x the LIP bound", gt=0.0, le=10.0
    )
    upper_fraction: float = option(1.3, "last impulse of round 1, x the LIP bound", gt=0.0, le=10.0)
    slip_margin: float = option(
        0.01, "the optimiser's slip margin [m] (strict test: 0.02)", gt=0.0, lt=constants.SURVIVAL_MAX_SLIP_M, unit="m"
    )
    tilt_margin_deg: float = option(
        3.0,
        "the optimiser's sole tilt margin [deg] (strict test: 5)",
        gt=0.0,
        lt=constants.SURVIVAL_MAX_TILT_DEG,
        unit="deg",
    )
    solver_iterations: int | None = option(
        None, "contact solver Newton iterations (default: the model's, 4)", ge=1, le=constants.MAX_SOLVER_ITERATIONS
    )
    time_limit: float | None = option(
        None,
        "wall-clock seconds after which no new round starts and a round's optimisation stops at its next "
        "judge (what passed is still replayed and saved; a rerun resumes; 0: only the summary of what is there); "
        "none: no limit",
        ge=0.0,
        le=1e7,
        unit="s",
    )
    out: str = option("runs/limit", "output folder (a search resumes there)")

    def check(self) -> None:
        """Every check before anything compiles: the declared ranges, then what ties the flags
        together, the envelope files and the output folder."""
        check_options(self)
        if not self.upper_fraction > self.lower_fraction:
            raise ValueError(
                f"--upper-fraction {self.upper_fraction:g} must exceed --lower-fraction {self.lower_fraction:g}"
            )
        if self.push_onset + max(self.push_duration, self.window + self.tail) >= self.horizon:
            ends = f"{self.push_onset:g} + max({self.push_duration:g}, {self.window:g} + {self.tail:g}) s"
            raise ValueError(
                f"--horizon {self.horizon:g} s must end after the push and the optimised window and tail ({ends})"
            )
        self.sweep("mujoco").check()
        check_torque_steps(self)
        load_envelopes(self)
        runs.check_output_dir(self.out, "limit", fingerprint(self))
        if self.time_limit == 0 and not (pathlib.Path(self.out) / "state.json").exists():
            raise ValueError(
                f"--time-limit 0 summarises the rounds on disk, and --out {self.out} holds none: nothing "
                "was measured; give --time-limit > 0 (or none) to run a round"
            )

    def sweep(self, backend: str, body: str | None = None) -> sweep_config.SweepConfig:
        """The sweep config that pushes and simulates alike (its setups and scenarios)."""
        return sweep_config.SweepConfig(
            robot=self.robot,
            magnitudes=(1.0,),
            directions=self.directions,
            elevation=self.elevation,
            push_duration=self.push_duration,
            push_onset=self.push_onset,
            body=body or self.body,
            gains=self.gains,
            horizon=self.horizon,
            solver_iterations=self.solver_iterations,
            backend=backend,
            out=None,
        )

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


def fingerprint(cfg: LimitConfig) -> dict:
    """What determines a search's results (:func:`wbc_jax.jobs.runs.fingerprint`); ``time_limit``
    and ``out`` do not (a capped search resumes under another cap, a folder copied off the GPU
    machine resumes where it lies)."""
    fields = {k: v for k, v in dataclasses.asdict(cfg).items() if k not in ("time_limit", "out")}
    return runs.fingerprint({**fields, "dtype": str(scenario.float_dtype())}, [cfg.gains, *cfg.envelopes], cfg.robot)


def check_torque_steps(cfg: LimitConfig) -> None:
    """Adam's step and the samples' spread (N m, alike on every joint) within the robot's largest
    motor limit: beyond it every sample saturates every joint (one line naming the flag otherwise)."""
    largest = float(np.max(model.load_robot(cfg.robot).index.torque_limit))
    for flag, value in (("--learning-rate", cfg.learning_rate), ("--es-sigma", cfg.es_sigma)):
        if value > largest:
            raise ValueError(
                f"{flag} {value:g} N m exceeds the largest motor limit of robot {cfg.robot!r} ({largest:g} N m); "
                f"valid: > 0 and <= {largest:g}"
            )


def load_envelopes(cfg: LimitConfig) -> dict:
    """{label: {azimuth: impulse N s}} of the ``--envelopes`` files (label: the file's folder), each
    checked to be an envelope of the same push (body, duration, onset, elevation) covering every
    azimuth of the search."""
    out = {}
    for path in cfg.envelopes:
        path = pathlib.Path(path)
        changed = runs.output_changed(path)  # a summary in a run folder: only as its run wrote it
        if changed is not None and runs.run_root(path) is not None:
            raise ValueError(f"--envelopes {changed}; rerun that envelope")
        try:
            data = loader.read_json(path, "--envelopes")
            env = data["envelope"].get("0", data["envelope"].get(0))
            pushed = data["config"]
        except (OSError, json.JSONDecodeError, UnicodeDecodeError, KeyError, AttributeError, TypeError) as err:
            raise ValueError(f"--envelopes {path}: not the summary.json of wbc-jax envelope ({err})") from None
        desc = describe(cfg.robot)
        if desc.body(str(pushed.get("body"))) != desc.body(cfg.body):  # a role and its body are the same push
            raise ValueError(
                f"--envelopes {path}: its pushes have body {desc.body(str(pushed.get('body')))!r}, "
                f"the search {desc.body(cfg.body)!r}"
            )
        for key in ("robot", "push_duration", "push_onset", "elevation"):
            if pushed.get(key, DEFAULT_ROBOT if key == "robot" else None) != getattr(cfg, key):
                raise ValueError(
                    f"--envelopes {path}: its pushes have {key} {pushed.get(key)!r}, the search {getattr(cfg, key)!r}"
                )
        try:
            table = {float(a): float(e["impulse_ns"]) for a, e in env.items()}
        except (KeyError, TypeError, ValueError) as err:
            raise ValueError(f"--envelopes {path}: not the summary.json of wbc-jax envelope ({err})") from None
        bad = {a: j for a, j in table.items() if not (math.isfinite(j) and j >= 0.0)}
        if bad:
            a, j = next(iter(bad.items()))
            raise ValueError(
                f"--envelopes {path}: the envelope at azimuth {a:g} deg is {j!r} N s; an envelope is a "
                "finite impulse >= 0 N s"
            )
        missing = [a for a in cfg.directions if float(a) not in table]
        if missing:
            raise ValueError(
                f"--envelopes {path}: no envelope at azimuths {missing[:4]} of the search "
                f"(it has {sorted(table)[:4]}...); use the same --directions"
            )
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
