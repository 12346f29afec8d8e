"""The rounds of ``wbc-jax limit`` (:mod:`wbc_jax.jobs.limit`): optimise, judge, replay, checkpoint.

One round, for B = directions x candidates pushes at once:

1. warm starts (the verified u of the same direction with the next lower impulse, else 0);
2. ``iterations`` Adam steps of :class:`wbc_jax.jobs.trajopt.Optimiser`; before the first and every
   ``judge_every`` steps the whole rollout (the policy, then the controller to the horizon) is
   judged by the strict criterion on MJX (forward, :func:`wbc_jax.sim.runner.run` with the
   feedforward torques); the last u that passed is kept; the round stops early once all passed;
3. C MuJoCo replays (float64 physics, the same policy through the host loop) the kept u of every
   candidate that passed on MJX, and the last u and the warm start of every other (float32 MJX
   and C MuJoCo part at the criterion's edge); verified = a replay passed. Only verified
   candidates move a bracket, give warm starts and make the limit.
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
import time

import jax
import numpy as np

from wbc_jax.control.gains import gains_to_dict
from wbc_jax.core import constants, io, provenance
from wbc_jax.jobs import limit, runs, sweep, sweep_table, trajopt
from wbc_jax.robot import model as model_lib
from wbc_jax.sim import loop as loop_lib
from wbc_jax.sim import metrics as metrics_lib
from wbc_jax.sim import runner, scenario
from wbc_jax.sim.state import Feedforward

# The setups' push body; the pushed body travels in Push.body, so all bodies share the programs.
SETUP_BODY = "trunk"
REPLAY_COLUMNS = (
    "max_foot_slip_m",
    "max_foot_tilt_deg",
    "end_com_speed_mps",
    "end_com_support_margin_m",
    "min_com_height_m",
    "max_abs_torque_nm",
)


class Search:
    """The search of one config: setups, bounds, optimiser; :meth:`round` runs one round."""

    def __init__(self, cfg: limit.LimitConfig):
        self.cfg = cfg
        self.dtype = scenario.float_dtype()
        robot = model_lib.load_robot(cfg.robot)
        self.body_id = robot.index.pushable_body_id(cfg.body)
        self.envelopes = limit.load_envelopes(cfg)
        self.base = sweep.base_gains(cfg.sweep("jax"), robot.index.n, self.dtype)
        self.n = robot.index.n

        def setup(backend, **kw):
            return sweep.make_setup(cfg.sweep(backend, SETUP_BODY), self.base, **kw)

        # The optimiser's loop: a smooth trace per tick, the tick rematerialised for exact gradients.
        grad_setup = setup("jax")
        self.grad_setup = dataclasses.replace(
            grad_setup,
            loop=loop_lib.compose(grad_setup.loop, trace=loop_lib.smooth_trace, remat=cfg.method == "gradient"),
        )
        self.judge_setup, self.replay_setup = setup("jax"), setup("mujoco")
        self.k0, self.T, self.tail, knot = cfg.ticks(self.grad_setup.loop.cfg.control_dt)
        self.opt = trajopt.Optimiser(
            self.grad_setup,
            self.k0,
            self.T,
            self.tail,
            method=cfg.method,
            learning_rate=cfg.learning_rate,
            clip_norm=cfg.clip_norm,
            knot=knot,
            pairs=cfg.es_pairs,
            sigma=cfg.es_sigma,
            cost=cfg.cost(),
        )
        self.Kn = self.opt.W.shape[1]
        self.azimuths = [float(a) for a in cfg.directions]
        self.lip = sweep_table.lip_bound(robot, self.azimuths)
        bound = np.array([self.lip[a]["impulse_bound_ns"] for a in self.azimuths])
        best = np.array([max((e[a] for e in self.envelopes.values()), default=0.0) for a in self.azimuths])
        self.lower = np.where(best > 0, best, cfg.lower_fraction * bound)
        self.upper = np.maximum(cfg.upper_fraction * bound, self.lower * 1.05)
        self.push_end = cfg.push_onset + cfg.push_duration
        self.timing = {"optimiser_compile_s": 0.0, "optimiser_s": 0.0, "judge_s": 0.0, "replay_s": 0.0}
        self.steps = 0  # optimiser steps taken (all rounds), for the throughput

    @property
    def physics_steps_per_candidate_step(self) -> int:
        """Physics steps of one candidate in one optimiser step (its rollouts of window and tail)."""
        return (self.T + self.tail) * self.grad_setup.loop.n_sub * self.opt.rollouts_per_step

    def scenarios(self, d: np.ndarray, impulse: np.ndarray):
        """Scenarios (B,) of the pushes of directions ``d`` (B,) (indices) with ``impulse`` (B,) N s."""
        cfg = self.cfg
        B = d.size
        scen, _ = sweep.scenarios_at(
            cfg.sweep("jax"),
            [self.base],
            impulse / cfg.push_duration,
            np.asarray(self.azimuths)[d],
            np.zeros(B, int),
            np.ones(B),
            np.ones(B),
            np.zeros((B, self.n)),
            self.dtype,
        )
        return scen.replace(push=scen.push.replace(body=np.full((B, 1), self.body_id, np.int32)))

    def _feedforward(self, u) -> Feedforward:
        u = np.asarray(u)
        return Feedforward(start=np.full(u.shape[0], self.k0, np.int32), torque=u)

    def judge(self, scen, z, backend: str) -> dict:
        """Strict summary columns of the whole rollouts of the policies of knots z (B, Kn, n) on
        ``backend`` ("jax": MJX, forward; "mujoco": the C MuJoCo replay); "failed": per rollout,
        the strict tests it fails."""
        st = self.judge_setup if backend == "jax" else self.replay_setup
        t0 = time.perf_counter()
        result = runner.run(st, scen, feedforward=self._feedforward(self.opt.torques(np.asarray(z))))
        self.timing["judge_s" if backend == "jax" else "replay_s"] += time.perf_counter() - t0
        cols = metrics_lib.summarize(result.metrics, self.push_end)
        cols["failed"] = [sorted(k for k, v in metrics_lib.failed_tests(cols).items() if v[b]) for b in range(len(z))]
        return cols

    def round(
        self, impulses: np.ndarray, warm: np.ndarray, on_step=None, on_judge=None, deadline: float | None = None
    ) -> tuple[dict, np.ndarray]:
        """One round over all directions: ``impulses`` (D, K) N s, warm starts (D * K, Kn, n);
        the optimisation stops at its first judge after ``deadline`` (``time.perf_counter()``;
        None: never). Returns (per-candidate columns (D * K,), the knots kept (D * K, Kn, n):
        verified where ``verified``)."""
        D, K = impulses.shape
        d = np.repeat(np.arange(D), K)
        scen = self.scenarios(d, impulses.ravel())
        state, info = self._optimise(scen, warm, on_step, on_judge, deadline)
        passed = np.asarray(state.passed)
        # What C MuJoCo replays: the knots that passed on MJX; for a candidate that never did, its
        # last knots and its warm start (MJX in float32 and C MuJoCo part at the strict criterion's
        # edge, e.g. the controller's own trajectory at its envelope's impulse).
        tries = [np.asarray(state.pass_z), np.asarray(state.z), np.asarray(warm)]
        replay, kept = self._replay(scen, tries, [passed, ~passed, ~passed])
        columns = {
            "direction": d,
            "impulse_ns": impulses.ravel(),
            "mjx_passed": passed,
            "passed_step": np.asarray(state.passed_step),
            **info,
            "verified": replay.pop("survived"),
            **replay,
        }
        return columns, kept

    def _optimise(self, scen, warm: np.ndarray, on_step, on_judge, deadline: float | None = None):
        """``cfg.iterations`` optimiser steps from the warm starts, judged on MJX before the first,
        every ``judge_every`` steps and after the last (the current knots and the best sample of
        each candidate still open; the first that passes is kept); cut at the first judge after
        ``deadline`` ("time_cut"). Returns (state, columns)."""
        cfg, B = self.cfg, len(warm)
        carry0 = self.opt.standing()
        state = self.opt.init(warm)
        obj = obj0 = np.full(B, np.nan)
        terms, failed, first_failed = {}, [[] for _ in range(B)], None
        steps, cut = 0, False
        for i in range(cfg.iterations + 1):
            if i % cfg.judge_every == 0 or i == cfg.iterations:
                state, failed = self._judge_open(scen, state, i, failed)
                first_failed = failed if first_failed is None else first_failed
                if on_judge is not None:
                    on_judge(int(np.sum(np.asarray(state.passed))), B)
                cut = deadline is not None and time.perf_counter() >= deadline and i < cfg.iterations
                if bool(np.all(np.asarray(state.passed))) or i == cfg.iterations or cut:
                    break
            t0 = time.perf_counter()
            compiled = ("step", state.z.shape) in self.opt._programs
            state, obj, terms = self.opt.step(state, scen.push, carry0)
            obj = np.asarray(jax.block_until_ready(obj))
            obj0 = obj if i == 0 else obj0
            self.timing["optimiser_s" if compiled else "optimiser_compile_s"] += time.perf_counter() - t0
            steps += 1
            if on_step is not None:
                on_step(1)
        self.steps += steps
        if on_step is not None:
            on_step(cfg.iterations - steps)
        info = {
            "warm_failed": first_failed,
            "mjx_failed": failed,
            "objective_first": obj0,
            "objective_last": obj,
            "steps": np.full(B, steps),
            "time_cut": np.full(B, cut),
            **{f"cost_{k}": np.asarray(v) for k, v in terms.items()},
        }
        return state, info

    def _judge_open(self, scen, state, step: int, failed: list):
        """Judge the current knots and the best sample of every candidate on MJX; a candidate not
        yet passed that passes with either keeps it (the current knots first). Returns (state,
        the strict tests each candidate's current knots fail, kept for those passed before)."""
        B = state.z.shape[0]
        both = jax.tree_util.tree_map(lambda x: np.concatenate([np.asarray(x)] * 2), scen)
        cols = self.judge(both, np.concatenate([np.asarray(state.z), np.asarray(state.best_z)]), "jax")
        ok = np.asarray(cols["survived"]).reshape(2, B)
        before = np.asarray(state.passed)
        z = np.where(ok[0][:, None, None], np.asarray(state.z), np.asarray(state.best_z))
        state = trajopt.record_passes(state, (ok[0] | ok[1]) & ~before, z, step)
        failed = [failed[b] if before[b] else cols["failed"][b] for b in range(B)]
        return state, failed

    def _replay(self, scen, tries: list, which: list) -> tuple[dict, np.ndarray]:
        """The C MuJoCo replay of knots ``tries[i]`` (B, Kn, n) of the candidates ``which[i]``
        (B,) bool, in one batch padded to one compiled shape (2B: the tries of a candidate are
        either the first alone or the other two). A candidate is verified by the first of its
        tries that survives. Returns ({"survived", "replayed" (which try verified it: its index,
        -1: none), "replay_failed", "replay_<column>"} (B,), the knots kept (B, Kn, n): the
        verifying try's, else the first tried)."""
        B = len(which[0])
        entries = [(b, i) for i in range(len(tries)) for b in np.flatnonzero(which[i])]
        b_idx = np.array([b for b, _ in entries], int)
        z = np.stack([tries[i][b] for b, i in entries])
        sub = jax.tree_util.tree_map(lambda x: np.asarray(x)[b_idx], scen)
        size = max(2 * B, len(entries))
        cols = self.judge(runner.pad_batch(sub, size), runner.pad_batch(z, size), "mujoco")
        out = {
            "survived": np.zeros(B, bool),
            "replayed": np.full(B, -1),
            "replay_failed": [None] * B,
            **{f"replay_{k}": np.full(B, np.nan) for k in REPLAY_COLUMNS},
        }
        kept = np.zeros_like(tries[0])
        for j, (b, i) in enumerate(entries):
            first = out["replay_failed"][b] is None
            if not (first or (cols["survived"][j] and not out["survived"][b])):
                continue
            out["survived"][b] = bool(cols["survived"][j])
            out["replayed"][b] = i if cols["survived"][j] else -1
            out["replay_failed"][b] = cols["failed"][j]
            kept[b] = z[j]
            for name in REPLAY_COLUMNS:
                out[f"replay_{name}"][b] = cols[name][j]
        return out, kept


def _records(columns: dict, round_: int) -> list:
    """Per-candidate JSON records of a round's columns."""
    B = len(columns["direction"])
    out = []
    for b in range(B):
        rec = {"round": round_, "device": provenance.device_label()}
        for k, v in columns.items():
            x = v[b]
            rec[k] = x.item() if isinstance(x, np.generic) else x
        out.append(rec)
    return out


def _load_state(out: pathlib.Path):
    """(records, witnesses {(direction, impulse): u}) of a checkpointed search (empty when none)."""
    path, npz = out / "state.json", out / "witness.npz"
    if not path.exists():
        return [], {}
    for name in (path, npz):  # the search goes on from its checkpoint only as it wrote it
        why = runs.output_changed(name)
        if why is not None:
            raise ValueError(f"--out {out}: {why}; remove the folder to start over")
    try:
        records = json.loads(path.read_text())["candidates"]
        with np.load(npz) as f:
            z, d, imp = f["z"], f["direction"], f["impulse_ns"]
    except (OSError, ValueError, KeyError, json.JSONDecodeError) as err:
        raise ValueError(
            f"--out {out}: its checkpoint is unreadable ({err}); remove the folder to start over"
        ) from None
    return records, {(int(a), float(b)): x for a, b, x in zip(d, imp, z, strict=True)}


def _save_state(out: pathlib.Path, search: Search, records: list, witnesses: dict) -> None:
    """witness.npz (every verified trajectory: its knots z, its torques u = W z, direction index,
    impulse), then state.json (every candidate), atomically."""
    keys = sorted(witnesses)
    z = np.array([witnesses[k] for k in keys]).reshape(len(keys), search.Kn, search.n)
    io.atomic_save_npz(
        out / "witness.npz",
        z=z,
        u=search.opt.torques(z),
        direction=np.array([k[0] for k in keys], int),
        impulse_ns=np.array([k[1] for k in keys]),
        onset_tick=np.asarray(search.k0),
    )
    runs.record_output(out / "witness.npz")
    io.atomic_write_json(out / "state.json", {"candidates": records})
    runs.record_output(out / "state.json")


def run(cfg: limit.LimitConfig, *, progress: bool = True) -> dict:
    """Run (or resume) the search of ``cfg`` into ``cfg.out``: state.json and witness.npz after
    every round, summary.json and limit.png at the end. Returns the summary."""
    from tqdm.auto import tqdm

    t_start = time.perf_counter()
    deadline = None if cfg.time_limit is None else t_start + cfg.time_limit
    cfg.check()
    out = pathlib.Path(cfg.out)
    search = Search(cfg)
    runs.claim_output_dir(out, "limit", limit.fingerprint(cfg), resume=True)
    records, witnesses = _load_state(out)
    D = len(search.azimuths)
    done = max((r["round"] for r in records), default=-1) + 1
    bar = tqdm(
        total=cfg.rounds * cfg.iterations,
        initial=done * cfg.iterations,
        unit="step",
        disable=not progress,
        desc=f"limit {cfg.body}",
    )
    for r in range(done, cfg.rounds):
        if deadline is not None and time.perf_counter() >= deadline:
            break
        tested = [_tested(records, d) for d in range(D)]
        impulses = np.stack(
            [limit.next_impulses(tested[d], cfg.candidates, search.lower[d], search.upper[d]) for d in range(D)]
        )
        pairs = [(d, float(J)) for d in range(D) for J in impulses[d]]
        by_dir = [[(J, z) for (dd, J), z in witnesses.items() if dd == d] for d in range(D)]
        warm = trajopt.warm_starts(by_dir, pairs, search.Kn, search.n)
        bar.set_description(f"limit {cfg.body} round {r + 1}/{cfg.rounds}")
        columns, best_z = search.round(
            impulses,
            warm,
            on_step=bar.update,
            on_judge=lambda n, B: bar.set_postfix(passed_mjx=f"{n}/{B}"),
            deadline=deadline,
        )
        for b, (d, J) in enumerate(pairs):
            if columns["verified"][b]:
                witnesses[(d, J)] = best_z[b]
        records += _records(columns, r)
        _save_state(out, search, records, witnesses)
    bar.close()
    if not records:  # no round finished: nothing was measured, so no limit is claimed
        raise ValueError(
            f"--time-limit {cfg.time_limit:g} s ran out before round 1 finished: nothing was measured; "
            "give a longer --time-limit (a rerun resumes)"
        )
    summary = summarize(cfg, search, records, time.perf_counter() - t_start)
    if done >= cfg.rounds and runs.output_changed(out / "summary.json") is None:
        # A re-run of a finished search: its summary.json (the timings measured when it ran) stays as it
        # is; the caller gets this process's (no optimiser step).
        return summary
    io.atomic_write_json(out / "summary.json", summary)
    runs.record_output(out / "summary.json")
    from wbc_jax.report import limit_plots

    limit_plots.polar(summary, out / "limit.png")
    return summary


def _tested(records: list, d: int) -> list:
    """[(impulse, verified)] of direction ``d``: a failure of a round cut by the time limit is no
    evidence (its optimisation stopped early), so only its verified candidates count."""
    return [
        (x["impulse_ns"], x["verified"])
        for x in records
        if x["direction"] == d and (x["verified"] or not x.get("time_cut", False))
    ]


def summarize(cfg: limit.LimitConfig, search: Search, records: list, wall_s: float) -> dict:
    """Per direction: the limit (largest verified impulse), its bracket, the LIP bound, the
    envelopes given as fractions of the limit and the witness's replay metrics; the targets."""
    directions = {}
    for d, az in enumerate(search.azimuths):
        mine = [x for x in records if x["direction"] == d]
        evidence = _tested(records, d)
        if not evidence:  # every candidate's optimisation was cut by the time limit: nothing measured
            directions[az] = {
                "limit_ns": None,
                "bracket_ns": [None, None],
                "at_cap": False,
                "measured": False,
                "lip_bound_ns": search.lip[az]["impulse_bound_ns"],
                "fraction_of_lip": None,
                "limit_at_least_envelopes": False,
                "witness": None,
                "envelopes": {k: {"impulse_ns": e[az], "fraction_of_limit": None} for k, e in search.envelopes.items()},
            }
            continue
        lo, hi = limit.bracket(evidence)
        bound = search.lip[az]["impulse_bound_ns"]
        witness = max((x for x in mine if x["verified"]), key=lambda x: x["impulse_ns"], default=None)
        envs = {
            k: {"impulse_ns": e[az], "fraction_of_limit": e[az] / lo if lo > 0 else None}
            for k, e in search.envelopes.items()
        }
        directions[az] = {
            "limit_ns": lo,
            "bracket_ns": [lo, None if np.isinf(hi) else hi],
            "at_cap": bool(np.isinf(hi)),
            "lip_bound_ns": bound,
            "fraction_of_lip": lo / bound,
            "envelopes": envs,
            "measured": True,
            "limit_at_least_envelopes": all(e[az] <= lo + 1e-9 for e in search.envelopes.values()),
            "witness": None
            if witness is None
            else {
                k: witness[k] for k in witness if k.startswith("replay_") or k in ("round", "passed_step", "impulse_ns")
            },
        }
    fractions = [v["fraction_of_lip"] for v in directions.values() if v["measured"]]
    B = len(search.azimuths) * cfg.candidates
    return {
        "directions": directions,
        "median_fraction_of_lip": float(np.median(fractions)) if fractions else None,
        # A target is met only where every direction was measured.
        "targets": {
            "limit_at_least_every_envelope": all(v["limit_at_least_envelopes"] for v in directions.values()),
            "every_limit_replayed_in_c_mujoco": all(
                v["measured"] and (v["witness"] is not None or v["limit_ns"] == 0) for v in directions.values()
            ),
        },
        "rounds": cfg.rounds,
        "rounds_done": 1 + max((x["round"] for x in records), default=-1),
        "time_cut": any(x.get("time_cut", False) for x in records),
        "candidates": records,
        "batch": B,
        "optimiser_steps": search.steps,
        "physics_steps_optimiser": search.steps * B * search.physics_steps_per_candidate_step,
        "wall_s": round(wall_s, 1),
        **{k: round(v, 1) for k, v in search.timing.items()},
        "survival_criterion": constants.SURVIVAL_CRITERION,
        "device": provenance.device_label(),
        "devices": sorted({x.get("device", "?") for x in records}),
        "dtype": str(search.dtype),
        "config": dataclasses.asdict(cfg),
        "gains": gains_to_dict(search.base),
        "provenance": provenance.record(
            {"gains": cfg.gains, **{f"envelope_{i}": p for i, p in enumerate(cfg.envelopes)}}
        ),
    }
