"""Run folders under hostile use (issue 41, classes 3, 4, 7 and 8): results changed after they were
written are never merged nor shown, jobs claim nothing they did not measure, broken output paths and
SIGINT end in one line, and a run is resumed wherever its inputs and outputs are the same.

One finished push sweep (module scope, the C MuJoCo engine, two envs of five ticks: the shape
tests/test_cli.py compiles) serves every resume and tamper test; each works on a copy of it."""

import dataclasses
import json
import os
import pathlib
import re
import shutil
import signal
import subprocess
import sys
import time
import types

import jax
import numpy as np
import pandas as pd
import pytest

from wbc_jax import cli
from wbc_jax.control.gains import default_gains, gains_to_dict
from wbc_jax.jobs import balance, limit, limit_rounds, runs, sweep_config
from wbc_jax.robot.icub import DESCRIPTION as ICUB
from wbc_jax.sim import physics
from wbc_jax.tuning.algorithms import gradient  # noqa: F401  (before a tripwire: optax applies jax.jit when imported)

ROOT = pathlib.Path(__file__).resolve().parents[1]
SWEEP = [
    "push-sweep",
    "--magnitudes",
    "20",
    "40",
    "2",
    "--directions",
    "1",
    "--horizon",
    "0.05",
    "--push-onset",
    "0",
    "--push-duration",
    "0.02",
    "--chunk-size",
    "1",
    "--quiet",
]


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """(folder of a finished sweep run with --gains GAINS, the gains file)."""
    base = tmp_path_factory.mktemp("finished")
    gains = base / "g.json"
    gains.write_text(json.dumps(gains_to_dict(default_gains(ICUB))))
    out = base / "sw"
    assert cli.main([*SWEEP, "--gains", str(gains), "--out", str(out)]) == 0
    return out, gains


@pytest.fixture
def tripwire(monkeypatch):
    """Any jax.jit after this point: something was (re)computed that should not have been."""

    def late(*args, **kwargs):
        raise AssertionError("reached jax.jit (compilation)")

    monkeypatch.setattr(jax, "jit", late)


def _copy(finished, tmp_path) -> tuple[pathlib.Path, pathlib.Path]:
    out, gains = finished
    shutil.copytree(out, tmp_path / "sw")
    shutil.copy(gains, tmp_path / "g.json")
    return tmp_path / "sw", tmp_path / "g.json"


def _error(capsys) -> str:
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


# ---- class 3: results changed after they were written ------------------------------------------


def test_an_edited_part_is_recomputed_never_merged(finished, tmp_path, capsys):
    """A part whose values were edited is not the run's own (its sha256 differs from run.json): the
    resumed run (in a copied folder, the gains file under another name) recomputes it, names it, and
    the table holds the simulated values again."""
    out, gains = _copy(finished, tmp_path)
    first = pd.read_parquet(out / "results.parquet")
    part = out / "parts" / "part-00001.parquet"
    edited = pd.read_parquet(part)
    edited["survived"], edited["com_rmse_m"] = ~edited["survived"], 99.0
    edited.to_parquet(part, index=False)
    assert runs.output_changed(part) is not None
    assert cli.main([*SWEEP, "--gains", str(gains), "--out", str(out)]) == 0
    assert "1 part file(s) not the run's own" in capsys.readouterr().err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["recomputed_parts"] == ["part-00001.parquet"] and summary["resumed_envs"] == 1
    again = pd.read_parquet(out / "results.parquet")
    assert again["survived"].tolist() == first["survived"].tolist()
    np.testing.assert_allclose(again["com_rmse_m"], first["com_rmse_m"], rtol=1e-9)
    assert runs.output_changed(part) is None and runs.output_changed(out / "results.parquet") is None


def test_a_part_copied_from_another_run_is_not_its_own(tmp_path):
    """Two runs of the same kind: a file of one copied into the other is refused whether the other
    recorded a file there (sha256 differs) or not (never recorded); the same bytes written by the run
    itself are its own."""
    fp = sweep_config.SweepConfig(out=None).fingerprint()
    a, b = tmp_path / "a", tmp_path / "b"
    for run, value in ((a, 1.0), (b, 2.0)):
        runs.claim_output_dir(run, "sweep", fp, resume=True)
        (run / "parts").mkdir()
        pd.DataFrame({"env": [0], "x": [value]}).to_parquet(run / "parts" / "part-00000.parquet", index=False)
        runs.record_output(run / "parts" / "part-00000.parquet")
    shutil.copy(a / "parts" / "part-00000.parquet", b / "parts" / "part-00000.parquet")
    assert "changed since the run wrote it" in runs.output_changed(b / "parts" / "part-00000.parquet")
    shutil.copy(a / "parts" / "part-00000.parquet", b / "parts" / "part-00001.parquet")
    assert "is not recorded" in runs.output_changed(b / "parts" / "part-00001.parquet")
    assert runs.output_changed(a / "parts" / "part-00000.parquet") is None


def test_a_finished_rerun_leaves_its_summary_alone(finished, tmp_path, monkeypatch, capsys, tripwire):
    """The same command again, spelt with a trailing slash and then as a relative path, from a copy
    of the folder: nothing compiles (the tripwire), summary.json keeps its bytes (its timings)."""
    out, gains = _copy(finished, tmp_path)
    before = (out / "summary.json").read_bytes()
    measured = {k: json.loads(before)[k] for k in ("compile_s", "run_s", "started_s", "physics_steps_per_s")}
    assert None not in measured.values() and measured["physics_steps_per_s"] > 0, measured
    assert cli.main([*SWEEP, "--gains", str(gains), "--out", f"{out}/"]) == 0, capsys.readouterr().err
    monkeypatch.chdir(tmp_path)
    assert cli.main([*SWEEP, "--gains", "g.json", "--out", "sw"]) == 0, capsys.readouterr().err
    assert (out / "summary.json").read_bytes() == before
    printed = json.loads(capsys.readouterr().out.splitlines()[-1])
    assert {k: printed[k] for k in measured} == measured
    # From Python too: the summary as the run wrote it, its envelope keyed by azimuth (a float) as a fresh run's.
    from wbc_jax.jobs import sweep

    cfg = cli.config_from_args(
        cli.build_parser().parse_args([*SWEEP, "--gains", "g.json", "--out", "sw"]), sweep_config.default_config()
    )
    again = sweep.run_sweep(cfg, progress=False)
    assert list(again["envelope"]) == [0.0] and again["run_s"] == measured["run_s"]


def test_view_refuses_a_changed_run_and_writes_none_of_its_files(finished, tmp_path, capsys):
    """view reads a sweep only as it was written: an edited results table or summary, or a gains file
    changed since the run, is refused in one line; --out naming one of the run's files is refused
    (view writes .rrd files only); the folder is left as it was."""
    out, gains = _copy(finished, tmp_path)
    for target in ("summary.json", "results.parquet", "run.json"):
        assert cli.main(["view", str(out), "--env", "0", "--out", str(out / target)]) == 2
        assert "give a .rrd file name" in _error(capsys)
    # Resumed with the copy's gains file (nothing to compute), the run now names that file as its input.
    assert cli.main([*SWEEP, "--gains", str(gains), "--out", str(out)]) == 0
    capsys.readouterr()
    values = json.loads(gains.read_text())
    gains.write_text(json.dumps({**values, "kp_com": [60.0, 60.0, 10.0]}))
    assert cli.main(["view", str(out), "--env", "0", "--out", str(tmp_path / "e.rrd")]) == 2
    line = _error(capsys)
    assert "its input files changed since it ran" in line and f"{gains.resolve()} has changed" in line, line
    gains.write_text(json.dumps(values))
    listing = sorted((p.name, p.stat().st_mtime_ns) for p in out.iterdir())
    table = pd.read_parquet(out / "results.parquet")
    table.loc[0, "survived"] = not table.loc[0, "survived"]
    table.to_parquet(out / "results.parquet", index=False)
    assert cli.main(["view", str(out), "--env", "0", "--out", str(tmp_path / "e.rrd")]) == 2
    assert "results.parquet changed since the run wrote it" in _error(capsys)
    assert sorted((p.name, p.stat().st_mtime_ns) for p in out.iterdir() if p.name != "results.parquet") == [
        x for x in listing if x[0] != "results.parquet"
    ]
    assert not (tmp_path / "e.rrd").exists()


# ---- class 4: jobs that claim what they did not measure ----------------------------------------


def _envelope_summary(path: pathlib.Path, impulse) -> str:
    """An envelope summary.json of the default limit search's push (chest, 0.1 s at 0.5 s)."""
    path.write_text(
        json.dumps(
            {
                "config": {"body": "chest", "push_duration": 0.1, "push_onset": 0.5, "elevation": 0.0},
                "envelope": {"0": {str(a): {"impulse_ns": impulse} for a in (0.0, 90.0, 180.0, 270.0)}},
            },
            allow_nan=True,
        )
    )
    return str(path)


@pytest.mark.parametrize("impulse", [float("nan"), float("inf"), -float("inf"), -1.0])
def test_limit_refuses_envelopes_that_are_not_finite_impulses(impulse, tmp_path, capsys, tripwire):
    path = _envelope_summary(tmp_path / "summary.json", impulse)
    assert cli.main(["limit", "--envelopes", path, "--out", str(tmp_path / "lim")]) == 2
    line = _error(capsys)
    assert f"--envelopes {path}: the envelope at azimuth 0 deg is {impulse!r} N s" in line
    assert "a finite impulse >= 0 N s" in line and not (tmp_path / "lim").exists()


def test_limit_with_no_round_claims_nothing(tmp_path, capsys, tripwire, monkeypatch):
    """--time-limit 0 on a folder with no round is refused before anything compiles; a time limit that
    runs out before round 1 ends without a summary; a direction whose every candidate was cut by the
    time limit has no limit and fails the targets (no 0 N s 'limit' with its targets met)."""
    out = tmp_path / "lim"
    assert cli.main(["limit", "--time-limit", "0", "--out", str(out)]) == 2
    assert "--time-limit 0 summarises the rounds on disk" in _error(capsys) and not out.exists()

    lip = {0.0: {"impulse_bound_ns": 20.0}, 90.0: {"impulse_bound_ns": 15.0}}
    fake = types.SimpleNamespace(
        azimuths=[0.0, 90.0],
        lip=lip,
        envelopes={},
        base=default_gains(ICUB),
        steps=0,
        timing={},
        dtype=np.float32,
        physics_steps_per_candidate_step=1,
    )
    monkeypatch.setattr(limit_rounds, "Search", lambda cfg: fake)
    cfg = limit.LimitConfig(directions=(0.0, 90.0), time_limit=1e-9, out=str(out))
    with pytest.raises(ValueError, match=r"ran out before round 1 finished: nothing was measured"):
        limit_rounds.run(cfg, progress=False)
    assert not (out / "summary.json").exists()

    cut = {"round": 0, "verified": False, "time_cut": True}
    records = [
        {**cut, "direction": 0, "impulse_ns": 5.0},
        {**cut, "direction": 1, "impulse_ns": 5.0, "verified": True, "time_cut": True},
    ]
    summary = limit_rounds.summarize(dataclasses.replace(cfg, time_limit=None), fake, records, 1.0)
    assert summary["directions"][0.0]["limit_ns"] is None and not summary["directions"][0.0]["measured"]
    assert summary["directions"][90.0]["limit_ns"] == 5.0
    assert summary["median_fraction_of_lip"] == pytest.approx(5.0 / 15.0)
    assert summary["targets"] == {"limit_at_least_every_envelope": False, "every_limit_replayed_in_c_mujoco": False}


def test_heldout_with_no_sets_writes_nothing(tmp_path, capsys, tripwire):
    out = tmp_path / "held"
    assert cli.main(["heldout", "--sets", "--out", str(out)]) == 2
    assert _error(capsys) == (
        "wbc-jax heldout: error: --sets: give at least one gain set ('default', 'critical' or NAME=FILE)"
    )
    assert not out.exists()


# ---- class 7: one line where a traceback was ---------------------------------------------------


def test_broken_out_paths_fail_in_one_line(tmp_path, capsys, tripwire):
    """--out through a symlink to nothing, a symlink loop (itself or a folder above), a 300-character
    name, under a regular file or under /proc (not writable, even for root: os.access says yes there
    to root, so the check writes): one line naming --out, nothing written."""
    (tmp_path / "dangling").symlink_to(tmp_path / "nowhere" / "x")
    (tmp_path / "loop").symlink_to(tmp_path / "loop")
    (tmp_path / "file").write_text("x")
    cases = [
        (tmp_path / "dangling", "is a symlink to a missing target or in a loop"),
        (tmp_path / "loop", "is a symlink to a missing target or in a loop"),
        (tmp_path / "loop" / "sub", "is a symlink to a missing target or in a loop"),
        (tmp_path / ("n" * 300), "a name of 300 bytes; names are at most 255 bytes"),
        (tmp_path / "file" / "sub", "is a file, not a folder"),
        (pathlib.Path("/proc/wbc_jax_run"), "cannot write in /proc"),
    ]
    for out, message in cases:
        for job in (SWEEP, ["balance", "--duration", "0.1"]):
            assert cli.main([*job, "--out", str(out)]) == 2
            line = _error(capsys)
            assert line.startswith(f"wbc-jax {job[0]}: error: --out ") and message in line, (out, line)
    assert not (tmp_path / "nowhere").exists()


def test_view_into_an_unwritable_place_or_of_a_foreign_summary(finished, tmp_path, capsys):
    out, _ = finished
    (tmp_path / "file").write_text("x")
    for rrd, message in (
        (tmp_path / "file" / "e.rrd", "is a file, not a folder"),
        (pathlib.Path("/proc/e.rrd"), "cannot write in /proc"),
        (tmp_path / ("n" * 300 + ".rrd"), "names are at most 255 bytes"),
    ):
        assert cli.main(["view", str(out), "--env", "1", "--out", str(rrd)]) == 2
        assert message in _error(capsys)
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    shutil.copy(out / "results.parquet", foreign / "results.parquet")
    for text in (
        '{"envelope": {}}',
        "[1, 2]",
        json.dumps({"config": {"horizon": "long"}, "gains": {}, "backend": "mujoco"}),
    ):
        (foreign / "summary.json").write_text(text)
        assert cli.main(["view", str(foreign), "--env", "0", "--out", str(tmp_path / "f.rrd")]) == 2
        assert f"{foreign / 'summary.json'} is not the summary of a push sweep" in _error(capsys)


def test_sigint_prints_one_line_and_the_same_command_resumes(finished, tmp_path):
    """SIGINT while a sweep runs (after its first part): one line, exit status 130, the parts done
    kept; the same command then finishes the run from them."""
    out = tmp_path / "sw"
    # 200 one-push parts of the fixture's program: enough work left after the first part for the signal to land
    # mid-run on a loaded machine (with 40 the run once finished before the signal: exit status 0).
    cmd = [sys.executable, "-m", "wbc_jax.cli", *SWEEP[:2], "10", "60", "200", *SWEEP[5:], "--out", str(out)]
    env = {**os.environ, "JAX_ENABLE_X64": "1", "PYTHONPATH": str(ROOT)}  # the float64 program the fixture compiled
    # The job as a shell starts it: SIGINT at its default disposition. A test worker may ignore SIGINT (a library
    # loaded by an earlier test in the same process), and a child inherits an ignored signal: Python then never
    # raises KeyboardInterrupt and the run finishes (exit status 0 in the full suite, 130 alone).
    inherited = signal.getsignal(signal.SIGINT)
    proc = subprocess.Popen(
        cmd,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        cwd=tmp_path,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    deadline = time.time() + 300
    while "parts/part-00000.parquet" not in _recorded(out):  # the first part written and recorded
        assert proc.poll() is None and time.time() < deadline, proc.communicate()
        time.sleep(0.02)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, f"SIGINT in the test process: {inherited}\n{err}"
    # XLA's own log lines (absl: "E1126 02:29:16.75 ...", on loading cached programs) are not the job's.
    lines = [line for line in err.splitlines() if line.strip() and not re.match(r"[IWEF]\d{4} ", line)]
    assert lines == ["wbc-jax push-sweep: interrupted; resume with the same command"] and "Traceback" not in err, err
    # The parts kept: written and recorded (a part written as the signal came, before its record, is
    # not the run's own yet: recomputed).
    kept = [name for name in _recorded(out) if runs.output_changed(out / name) is None]
    assert 1 <= len(kept) < 200 and not (out / "results.parquet").exists()
    done = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=tmp_path, timeout=300)
    assert done.returncode == 0, done.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["n_envs"] == 200 and summary["resumed_envs"] == len(kept)


def _recorded(out: pathlib.Path) -> list[str]:
    """The result files a run's manifest records (none before it exists)."""
    try:
        return list(json.loads((out / runs.MANIFEST).read_text()).get(runs.OUTPUTS, {}))
    except (OSError, ValueError):
        return []


# ---- class 8: resume wherever inputs and outputs are the same ----------------------------------


def test_fingerprints_compare_inputs_by_content_not_by_spelling(tmp_path, capsys, tripwire):
    """A balance folder is bound to its run whatever the --out spelling (trailing slash, relative,
    a copy), --plots/--no-plots, --backend auto or the engine it resolves to, or the path of its
    gains file (another name, a symlink, ../): the same fingerprint; other gains contents are still
    refused, named."""
    gains = tmp_path / "g.json"
    gains.write_text(json.dumps(gains_to_dict(default_gains(ICUB))))
    (tmp_path / "d").mkdir()
    (tmp_path / "link.json").symlink_to(gains)
    first = balance.BalanceConfig(duration=0.1, gains=str(gains), out=str(tmp_path / "b"))
    runs.claim_output_dir(first.out, "balance", first.fingerprint())
    same = [
        dataclasses.replace(first, out=f"{first.out}/", plots=False),
        dataclasses.replace(first, backend=physics.resolve_backend("auto")),  # what auto runs here
        dataclasses.replace(first, gains=str(tmp_path / "d" / ".." / "g.json")),
        dataclasses.replace(first, gains=str(tmp_path / "link.json")),
    ]
    for cfg in same:
        assert runs.differences(runs._compared(first.fingerprint()), runs._compared(cfg.fingerprint())) == []
        cfg.check()  # the folder is accepted
    shutil.copytree(tmp_path / "b", tmp_path / "copy")
    dataclasses.replace(first, out=str(tmp_path / "copy")).check()
    values = gains_to_dict(default_gains(ICUB))
    (tmp_path / "other.json").write_text(json.dumps({**values, "kp_com": [60.0, 60.0, 10.0]}))
    assert (
        cli.main(
            ["balance", "--duration", "0.1", "--gains", str(tmp_path / "other.json"), "--out", str(tmp_path / "b")]
        )
        == 2
    )
    assert f"made with other inputs (config.gains ({(tmp_path / 'other.json').resolve()}): contents changed)" in _error(
        capsys
    )


# ---- issue 45: a stalled device is an error; where each chunk's time went ----------------------


def test_a_stalled_chunk_is_one_line_naming_the_device_and_the_chunk_and_the_run_resumes(finished, tmp_path, capsys):
    """Chunk 1 blocked on its device (--simulate-stall 1 0) with --stall-timeout-s 2: exit status 3
    within the bound and one line naming the chunk and the device; chunk 0's part kept, the timeline
    of both written; the command without the test hook (another --stall-timeout-s: no part of the
    fingerprint) resumes and simulates chunk 1 alone."""
    out, gains = finished
    argv = [*SWEEP, "--gains", str(gains), "--out", str(tmp_path / "sw")]
    started = time.perf_counter()
    assert cli.main([*argv, "--stall-timeout-s", "2", "--simulate-stall", "1", "0"]) == 3
    assert time.perf_counter() - started < 60  # chunk 0 (compiled by the fixture), then the 2 s bound
    assert _error(capsys) == (
        "wbc-jax push-sweep: error: chunk 1: device cpu:0 (C MuJoCo) did not finish its run "
        "within 2 s (0 of 1 device(s) did; bound: --stall-timeout-s); the chunks finished "
        "before are kept: rerun the same command to resume"
    )
    parts = tmp_path / "sw" / "parts"
    assert sorted(p.name for p in parts.iterdir()) == ["part-00000.parquet"]
    rows = json.loads((tmp_path / "sw" / "timeline.json").read_text())["rows"]
    assert [(r["chunk"], r["finished"]) for r in rows] == [(0, True), (1, False)]
    assert rows[1]["wall_s"] >= 2.0
    assert cli.main([*argv, "--stall-timeout-s", "600"]) == 0, capsys.readouterr().err
    summary = json.loads((tmp_path / "sw" / "summary.json").read_text())
    assert summary["resumed_envs"] == 1 and summary["n_envs"] == 2
    timeline = json.loads((tmp_path / "sw" / "timeline.json").read_text())
    assert timeline["chunks_on_disk"] == [0] and [r["chunk"] for r in timeline["rows"]] == [1]


def test_the_timeline_has_a_row_per_chunk_and_device_within_its_wall_time(finished):
    """timeline.json of the fixture's run (two chunks on C MuJoCo's host device): one row per chunk,
    every time non-negative, each row's compile, thread, dispatch, run, transfer and host seconds
    summing to at most the chunk's wall time; the totals are the rows' sums."""
    out, _ = finished
    timeline = json.loads((out / "timeline.json").read_text())
    assert timeline["backend"] == "mujoco" and timeline["devices"] == ["cpu:0"]
    rows = timeline["rows"]
    assert [(r["chunk"], r["device"], r["finished"]) for r in rows] == [(c, "cpu:0 (C MuJoCo)", True) for c in (0, 1)]
    timed = ("compile_s", "thread_start_s", "dispatch_s", "wait_s", "transfer_s", "host_s")
    for row in rows:
        assert min(row[k] for k in timed) >= 0.0 and row["wait_s"] > 0.0, row
        assert sum(row[k] for k in timed) <= row["wall_s"] + 1e-3, row
    totals = timeline["totals_by_device"]["cpu:0 (C MuJoCo)"]
    assert totals["wait_s"] == pytest.approx(sum(r["wait_s"] for r in rows), abs=1e-3)


SCALING = [
    sys.executable,
    str(ROOT / "benchmarks" / "scaling.py"),
    "--gpus",
    "1",
    "--backends",
    "mujoco",
    "--repeats",
    "2",
]


def test_scaling_refuses_a_scaling_json_it_did_not_write_before_running(tmp_path):
    """The default suite's sibling of the next test (20-30 s here, two calls: nightly): a --out whose
    scaling.json another tool wrote is refused in one line, nothing run, nothing written."""
    (tmp_path / "scaling.json").write_text(json.dumps({"rows": []}))
    proc = subprocess.run(
        [*SCALING, "--out", str(tmp_path), "--", *SWEEP[1:-1]],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        timeout=120,
    )
    assert proc.returncode == 1 and proc.stderr.strip() == (
        f"scaling.py: error: --out {tmp_path}: its scaling.json was not written by scaling.py (no 'calls'); "
        "give another --out"
    ), proc.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scaling.json"]


@pytest.mark.slow
def test_scaling_writes_only_under_its_out_and_takes_a_second_call_with_other_flags(finished, tmp_path):
    """benchmarks/scaling.py on the CPU (C MuJoCo, the fixture's compiled program): its runs
    (with their timelines) and scaling.json under --out alone; a second call with other sweep flags
    keeps the first's rows."""
    out = tmp_path / "scaling"
    env = {**os.environ, "JAX_ENABLE_X64": "1", "PYTHONPATH": str(ROOT)}  # the float64 program the fixture compiled
    script = [*SCALING, "--out", str(out), "--"]
    flags = SWEEP[1:-1]  # the sweep's flags without the command and --quiet
    for grid in (flags, [*flags[:3], "3", *flags[4:]]):  # 2, then 3 magnitudes
        proc = subprocess.run([*script, *grid], capture_output=True, text=True, env=env, cwd=tmp_path, timeout=300)
        assert proc.returncode == 0, proc.stderr[-3000:]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scaling"]  # nothing beside --out (cwd is tmp_path)
    assert sorted(p.name for p in out.iterdir()) == ["runs", "scaling.json"]
    result = json.loads((out / "scaling.json").read_text())
    assert len(result["calls"]) == 2 and [(r["envs"], r["repeats"]) for r in result["rows"]] == [(2, 2), (3, 2)]
    for row in result["rows"]:
        assert row["repeat_flips"] == 0 and "error" not in row, row  # C MuJoCo repeats itself exactly
        assert (out / row["runs"] / "run1" / "timeline.json").is_file() and row["timeline_last_run"]


def _write_table(folder: pathlib.Path, survived) -> None:
    folder.mkdir(parents=True)
    survived = np.asarray(survived, bool)
    pd.DataFrame({"survived": survived, "upright": survived}).to_parquet(folder / "results.parquet")


def test_scaling_compares_rows_of_calls_that_ran_at_once_on_other_gpus(tmp_path, monkeypatch):
    """benchmarks/scaling.py split over calls on disjoint GPUs: a 2-GPU row written before its one-GPU
    row is compared once the one-GPU row is there (flips of the last tables, speed-up, the target),
    stale comparisons are dropped, and CUDA_VISIBLE_DEVICES picks the GPUs, too few refused."""
    from conftest import load_script

    scaling = load_script("benchmarks/scaling.py")
    one_runs = [[1, 1, 0, 0, 1, 0], [1, 1, 0, 1, 1, 0]]  # one flip between the one-GPU repeats
    for k, table in enumerate(one_runs):
        _write_table(tmp_path / "runs/x/warp_1gpu" / f"run{k}", table)
    for k, table in enumerate([[0, 0, 0, 0, 1, 0], [0, 1, 1, 1, 1, 0]]):  # last: 2 flips against [1,1,0,1,1,0]
        _write_table(tmp_path / "runs/x/warp_2gpu" / f"run{k}", table)
    two = {"backend": "warp", "gpus": 2, "runs": "runs/x/warp_2gpu", "repeats": 2, "run_s": 5.0, "repeat_flips": 4}
    one = {"backend": "warp", "gpus": 1, "runs": "runs/x/warp_1gpu", "repeats": 2, "run_s": 9.6, "repeat_flips": 1}
    alone = scaling.compare([{**two, "speed_up": 9.9, "flips_vs_one_gpu": 0}], tmp_path)
    assert alone == [two]  # no one-GPU row yet: no comparison, the stale one dropped
    assert scaling.check(alone) == ["warp on 2 GPUs: no one-GPU run in this --out to compare with"]
    rows = scaling.compare([one, two], tmp_path)
    assert rows[1] == {
        **two,
        "speed_up": 1.92,
        "repeat_floor_one_gpu": 1,
        "flips_vs_one_gpu": 2,
        "speed_up_target": 1.9,
        "speed_up_met": True,
    }
    assert rows[0]["flips_vs_one_gpu"] == 0 and rows[0]["speed_up"] == 1.0
    assert scaling.check(rows) == []  # 2 flips <= floor 1 + one cell of slack
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "2,3")
    assert scaling.visible_gpus(2) == ["2", "3"] and scaling.visible_gpus(1) == ["2"]
    with pytest.raises(SystemExit, match=r"--gpus 4: CUDA_VISIBLE_DEVICES=2,3 names 2 GPU\(s\); name 4 or more"):
        scaling.visible_gpus(4)
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES")
    assert scaling.visible_gpus(4) == ["0", "1", "2", "3"]
