"""A re-run of a finished run leaves its summary's timings alone (issue 41, class 3), for the resumable
jobs that write timings besides push-sweep (tests/test_reliability_runs.py): tune's timings.json, the
heldout job's heldout.json and limit's summary.json. (balance and envelope resume nothing: a re-run
computes every figure again, its timings with them.) The expensive work of each is a stand-in that takes a
known time on its first call only, so a re-run that measured again would show another time; nothing
compiles (the tripwire)."""

import json
import time
import types

import jax
import numpy as np
import pytest

from wbc_jax.control.gains import default_gains
from wbc_jax.core import io
from wbc_jax.jobs import limit, limit_rounds
from wbc_jax.robot.icub import DESCRIPTION as ICUB
from wbc_jax.tuning import config
from wbc_jax.tuning.heldout_config import HeldoutConfig
from wbc_jax.tuning.orchestration import campaign, prediction
from wbc_jax.tuning.orchestration import heldout as tuning_eval
from wbc_jax.tuning.orchestration.timings import INTERRUPTED

TINY = dict(horizon=0.1, push_onset=0.0, duration_range=(0.02, 0.05), eval_horizon=0.1, eval_pushes=2)
FIRST_S = 0.3  # the stand-ins' first call; later calls take ~0 s


@pytest.fixture
def tripwire(monkeypatch):
    def late(*args, **kwargs):
        raise AssertionError("reached jax.jit (compilation)")

    monkeypatch.setattr(jax, "jit", late)


def _prediction_stand_in(calls: list, interrupt_first: bool = False):
    """prediction.survival_prediction's shape: writes prediction.json, returns its figures."""

    def predict(problem, n, out):
        calls.append(n)
        time.sleep(FIRST_S if len(calls) == 1 else 0.0)
        if interrupt_first and len(calls) == 1:
            raise KeyboardInterrupt
        res = {"n": n, "survival_rate": 0.5, "spearman_train_horizon": -0.4, "auc_train_horizon": 0.7 + len(calls)}
        io.atomic_write_json(out / "prediction.json", res)
        return res

    return predict


def test_a_finished_tune_rerun_keeps_each_phases_time(tmp_path, monkeypatch, tripwire):
    """The same tune again: the finished phase's result is read from its file (not computed again) and
    timings.json keeps its bytes; a result file edited since is computed again and timed again."""
    calls: list = []
    monkeypatch.setattr(prediction, "survival_prediction", _prediction_stand_in(calls))
    tc = config.TuneConfig(phases=("predict",), out=str(tmp_path / "t"), **TINY)
    first = campaign.run(tc, progress=False)
    timings = tmp_path / "t" / "timings.json"
    before = timings.read_bytes()
    assert json.loads(before)["predict"] >= FIRST_S and first["predict"]["auc_train_horizon"] == 1.7
    again = campaign.run(tc, progress=False)
    assert calls == [2] and timings.read_bytes() == before and again == first
    # prediction.json edited since the run wrote it: not the run's own, so computed again (and its time is that run's).
    (tmp_path / "t" / "prediction.json").write_text(json.dumps({"n": 2, "survival_rate": 1.0}))
    edited = campaign.run(tc, progress=False)
    assert calls == [2, 2] and edited["predict"]["auc_train_horizon"] == 2.7
    assert json.loads(timings.read_text())["predict"] < FIRST_S


def test_an_interrupted_tune_phase_adds_the_time_it_spent(tmp_path, monkeypatch, tripwire):
    """Ctrl-C inside a phase, then the same command: the phase's time is both invocations' (the first one's
    kept under interrupted_s until it finishes)."""
    calls: list = []
    monkeypatch.setattr(prediction, "survival_prediction", _prediction_stand_in(calls, interrupt_first=True))
    tc = config.TuneConfig(phases=("predict",), out=str(tmp_path / "t"), **TINY)
    with pytest.raises(KeyboardInterrupt):
        campaign.run(tc, progress=False)
    timings = tmp_path / "t" / "timings.json"
    assert json.loads(timings.read_text()) == {INTERRUPTED: {"predict": pytest.approx(FIRST_S, abs=0.15)}}
    campaign.run(tc, progress=False)
    assert calls == [2, 2] and set(json.loads(timings.read_text())) == {"predict"}
    assert json.loads(timings.read_text())["predict"] >= FIRST_S


def test_a_finished_heldout_rerun_leaves_heldout_json_alone(tmp_path, monkeypatch, tripwire):
    """wbc-jax heldout again on its finished folder: nothing is evaluated again and heldout.json (its
    timing block) keeps its bytes."""
    calls: list = []

    def evaluate(sets, hc, out, *, progress=True):
        calls.append(sorted(sets))
        grid = {
            "envelope_fraction_median": 0.5,
            "envelope_fraction_min": 0.4,
            "survival_rate": 0.3,
            "upright_rate": 0.3,
            "peak_torque_nm_median": 30.0,
            "envelope": {"0.0": {"impulse_ns": 10.0, "fraction": 0.5, "bound_impulse_ns": 20.0}},
            "envelope_fraction_monotone_median": 0.5,
            "envelope_fraction_monotone_min": 0.4,
        }
        run_s = FIRST_S if len(calls) == 1 else 0.0
        return {
            **{n: {"grid": grid, "variations": {}, "sinusoid_com_rmse_m": 1e-3} for n in sets},
            "_timing": {"stand_0": {"compile_s": 1.0, "run_s": run_s}},
        }

    monkeypatch.setattr(tuning_eval, "heldout", evaluate)
    hc = HeldoutConfig(sets=("default",), out=str(tmp_path / "h"))
    first = tuning_eval.run(hc, progress=False)
    written = (tmp_path / "h" / "heldout.json").read_bytes()
    assert json.loads(written)["timing"]["stand_0"]["run_s"] == FIRST_S
    assert tuning_eval.run(hc, progress=False) == first
    assert calls == [["default"]] and (tmp_path / "h" / "heldout.json").read_bytes() == written


class _LimitSearch:
    """limit_rounds.Search's shape for one direction: a round verifies the impulses below 10 N s and takes
    FIRST_S on the process's first round (its compile), ~0 s later."""

    azimuths, lip, envelopes = [0.0], {0.0: {"impulse_bound_ns": 20.0}}, {}
    lower, upper, Kn, n, k0 = [2.0], [16.0], 2, 3, 0
    dtype, physics_steps_per_candidate_step = np.float32, 1
    opt = types.SimpleNamespace(torques=lambda z: 2.0 * np.asarray(z))

    def __init__(self, cfg):
        self.base, self.steps, self.timing = default_gains(ICUB), 0, {"optimiser_s": 0.0}

    def round(self, impulses, warm, on_step, on_judge, deadline):
        seconds = FIRST_S if self.steps == 0 else 0.0
        time.sleep(seconds)
        self.steps += 1
        self.timing["optimiser_s"] += seconds
        J = np.asarray(impulses, float).ravel()
        columns = {"direction": np.zeros(J.size, int), "impulse_ns": J, "verified": J < 10.0}
        return columns, np.ones((J.size, self.Kn, self.n))


def test_a_finished_limit_rerun_leaves_its_summary_alone(tmp_path, monkeypatch, tripwire):
    """limit again on its finished folder: no round runs and summary.json (wall_s, optimiser_s) keeps its bytes."""
    monkeypatch.setattr(limit_rounds, "Search", _LimitSearch)
    cfg = limit.LimitConfig(directions=(0.0,), candidates=2, rounds=2, out=str(tmp_path / "lim"))
    first = limit_rounds.run(cfg, progress=False)
    written = (tmp_path / "lim" / "summary.json").read_bytes()
    assert first["rounds_done"] == 2 and first["optimiser_s"] == FIRST_S and first["wall_s"] >= FIRST_S
    again = limit_rounds.run(cfg, progress=False)
    assert again["optimiser_steps"] == 0 and (tmp_path / "lim" / "summary.json").read_bytes() == written
