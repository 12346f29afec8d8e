"""Hostile but realistic input to every job, each case run as a subprocess (issue 34: reliability,
second pass).

    python experiments/checks/bad_input.py                    # run every case, print a table
    python experiments/checks/bad_input.py --record           # and write the cases into results/reliability.json

A case passes when the command fails fast and clearly: exit code 2, within --max-seconds (30 s on
the 2-core CPU machine: the check comes before anything compiles), no traceback, one error line
that matches the case's pattern (it names the flag or file and the valid values), and nothing
written. Each case records its command, exit code, the first line of stderr and its seconds;
bad_input.json goes into --out.

The check (:func:`failures`): every case passes; exit status 1 otherwise (exit 0: a result written
for nonsense; a traceback, a hang or a slow failure, another message).

tests/test_cli.py runs the same cases in one process with a tripwire on jax.jit (a check that
comes after a compilation fails there), from :func:`cases`.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import pathlib
import re
import subprocess
import sys
import tempfile
import time

from wbc_jax.core import checks, io, provenance
from wbc_jax.robot.icub import DESCRIPTION as ICUB

ROOT = pathlib.Path(__file__).resolve().parents[2]
# Issue 41, classes 3, 4 and 7 (their cases: integrity_cases, at the end of the file).
INTEGRITY_CLASSES = ("results changed after written", "claims not measured", "broken paths, foreign files")
CLASSES = (
    "nonsense accepted",
    "contact geometry",
    "silent overwrite",
    "memory",
    "traceback or late failure",
    "reporting",
    "several processes",
    *INTEGRITY_CLASSES,
)
# Issue 41, classes 1, 2 and 6 (their cases: issue41_cases).
INPUT_CLASSES = ("physical set-up", "push timing", "parser attack")
CLASSES = (*CLASSES, *INPUT_CLASSES)


def _write(path: pathlib.Path, data) -> str:
    path.write_bytes(data if isinstance(data, bytes) else data.encode())
    return str(path)


def _run_dir(path: pathlib.Path, kind: str, fingerprint: dict | None = None, files=()) -> str:
    path.mkdir()
    (path / "run.json").write_text(json.dumps({"kind": kind, "fingerprint": fingerprint or {}}))
    for name in files:
        (path / name).write_text("{}")
    return str(path)


def cases(tmp: pathlib.Path) -> list[tuple[str, list[str], str]]:
    """(class, argv, pattern of the error line) of every case; its input files are written into
    ``tmp``. A job with an ``--out`` flag gets its own ``--out`` unless the case gives one."""
    from wbc_jax.control.gains import default_gains, gains_to_dict
    from wbc_jax.jobs import balance, envelope

    gains = gains_to_dict(default_gains(ICUB))
    rank = {**gains, "kp_com": [[50.0, 50.0, 10.0], [50.0, 50.0, 10.0]]}
    huge = {**gains, "kp_com": [1e30, 50.0, 10.0]}
    text = {**gains, "kd_postural": "high"}
    feet = (
        "contacts:\n  - {name: l, frame: l_sole, normal: [0, 0, %s]}\n  - {name: r, frame: r_sole, normal: [0, 0, 1]}\n"
    )
    task = "tasks: [{name: hand, kind: position, frame: r_hand, %s}, {name: posture, kind: postural}]\n"
    f = {
        "dir": tmp / "a_dir",
        "file": _write(tmp / "a_file", "x"),
        "rank": _write(tmp / "rank.json", json.dumps(rank)),
        "huge": _write(tmp / "huge.json", json.dumps(huge)),
        "high": _write(tmp / "high.json", json.dumps({**gains, "kp_com": [5000.0, 5000.0, 10.0]})),
        "text": _write(tmp / "text.json", json.dumps(text)),
        "not_json": _write(tmp / "not.json", "{kp_com: 1"),
        "latin1_json": _write(tmp / "latin1.json", '{"kp_com": "\xe9"}'.encode("latin-1")),
        "latin1_yaml": _write(tmp / "latin1.yaml", "# caf\xe9\n".encode("latin-1") + (feet % "1").encode()),
        "not_yaml": _write(tmp / "bad.yaml", "contacts: [\n  - {name: l"),
        "txt": _write(tmp / "tasks.txt", feet % "1"),
        "sole_down": _write(tmp / "sole_down.yaml", feet % "-1"),
        "sole_side": _write(
            tmp / "sole_side.yaml", (feet % "1").replace("[0, 0, 1]}\n  - {name: r", "[1, 0, 0.2]}\n  - {name: r")
        ),
        "friction": _write(
            tmp / "friction.yaml",
            feet % "1" + "scene:\n  - {name: box, size: [0.1, 0.1, 0.1], pos: [1, 0, 0.1], friction: high}\n",
        ),
        "normal_force": _write(
            tmp / "normal_force.yaml",
            (feet % "1") + "  - {name: h, frame: l_hand, type: point, "
            "normal: [0, 0, 1], touches: floor, normal_force: [1, 2]}\n",
        ),
        "mu_huge": _write(
            tmp / "mu.yaml", (feet % "1").replace("normal: [0, 0, 1]}", "normal: [0, 0, 1], mu: 1e30}", 1)
        ),
        "kp_text": _write(tmp / "kp.yaml", task % "kp: high"),
        "circle_inf": _write(tmp / "circle.yaml", task % "reference: {kind: circle, radius: .inf, frequency: 0.2}"),
    }
    f["dir"].mkdir()
    other = dict(out=str(tmp / "other_flags"))
    runs_ = {
        "sweep": _run_dir(tmp / "a_sweep", "sweep"),
        "balance": _run_dir(tmp / "a_balance", "balance", balance.BalanceConfig(duration=5.0, **other).fingerprint()),
        "envelope": _run_dir(
            tmp / "an_envelope",
            "envelope",
            envelope.EnvelopeConfig(directions=(0.0,), **other).fingerprint(),
            ["summary.json"],
        ),
        "tune": _run_dir(tmp / "a_tune", "tune", None, ["eval.json"]),
        "corrupt": tmp / "corrupt",
        "unfinished": _run_dir(tmp / "unfinished", "sweep", None, ["summary.json"]),
    }
    runs_["corrupt"].mkdir()
    (runs_["corrupt"] / "run.json").write_text("{\n")
    N, C, W, M, T, R = CLASSES[:6]
    grid = ["--magnitudes", "10", "20", "2", "--directions", "1"]
    return (
        [
            # Nonsense accepted: every value outside its physical range, the same in every job.
            (N, ["push-sweep", "--body", "world"], r"--body 'world' is not a valid name here; valid: \['root_link'"),
            (N, ["envelope", "--body", "world"], r"--body 'world' is not a valid name"),
            (N, ["tune", "--train-bodies", "chest", "world"], r"--train-bodies 'world' is not a valid name"),
            (N, ["push-sweep", "--body", "nose"], r"--body 'nose' is not a valid name"),
            (N, ["push-sweep", "--elevation", "400"], r"--elevation must be a number in \[-90, 90\] deg, got 400"),
            (N, ["envelope", "--elevation", "-91"], r"--elevation must be a number in \[-90, 90\] deg"),
            (
                N,
                ["balance", "--push-force", "10", "0", "0", "--push-onset", "20", "--duration", "1"],
                r"the push \(--push-onset 20 \+ --push-duration 0.1 s\) must end inside the run \(--duration 1 s\)",
            ),
            (N, ["balance", "--push-force", "10", "0", "0", "--push-onset", "9.95"], r"must end inside the run"),
            (N, ["push-sweep", "--push-duration", "0"], r"--push-duration must be a number in \[0.001, 60\] s, got 0"),
            (N, ["envelope", "--push-duration", "0"], r"--push-duration must be a number in \[0.001, 60\] s"),
            (N, ["balance", "--push-force", "10", "0", "0", "--push-duration", "0"], r"--push-duration must be"),
            (N, ["push-sweep", "--horizon", "1e7"], r"--horizon must be a number in \(0, 600\] s, got 1e\+07"),
            (N, ["envelope", "--horizon", "1e7"], r"--horizon must be a number in \(0, 600\] s"),
            (N, ["balance", "--duration", "1e7"], r"--duration must be a number in \(0, 600\] s"),
            (N, ["tune", "--horizon", "1e7"], r"--horizon must be a number in \(0, 600\] s"),
            (N, ["tune", "--eval-horizon", "inf"], r"--eval-horizon must be a number in \(0, 600\] s, got inf"),
            (N, ["envelope", "--resolution", "1e-300"], r"--resolution must be a number in \[0.001, 1000\] N s"),
            (N, ["envelope", "--resolution", "nan"], r"--resolution must be a number"),
            (
                N,
                [
                    "envelope",
                    "--magnitudes",
                    "5000",
                    "5000",
                    "1",
                    "--push-duration",
                    "0.5",
                    "--horizon",
                    "2",
                    "--resolution",
                    "0.001",
                ],
                r"--resolution 0.001 N s needs 22 bisection rounds inside a grid step",
            ),
            (N, ["envelope", "--queue", "2", "--backend", "mujoco"], r"--queue 2 .* needs an MJX backend"),
            (N, ["push-sweep", "--queue", "2", "--backend", "mujoco"], r"--queue 2 .* needs an MJX backend"),
            (N, ["push-sweep", "--queue", "1e6"], r"--queue must be a whole number in \[1, 1024\]"),
            (N, ["push-sweep", "--magnitudes", "0", "1e9", "3"], r"--magnitudes must be a number in \[0, 5000\] N"),
            (N, ["push-sweep", "--magnitudes", "-10", "10", "3"], r"--magnitudes must be a number in \[0, 5000\] N"),
            (
                N,
                ["envelope", "--magnitudes", "0", "100", "3"],
                r"--magnitudes must be a number in \(0, 5000\] N, got 0",
            ),
            (N, ["push-sweep", "--friction", "0", "1"], r"--friction must be a number in \[0.01, 10\], got 0"),
            (N, ["push-sweep", "--mass-scale", "1", "1e9"], r"--mass-scale must be a number in \[0.1, 10\]"),
            (N, ["push-sweep", "--joint-noise", "10"], r"--joint-noise must be a number in \[0, 0.5\] rad"),
            (
                N,
                ["push-sweep", "--gain-scale-range", "0", "2"],
                r"--gain-scale-range must be a number in \[0.01, 100\]",
            ),
            (N, ["push-sweep", "--friction", "1", "0.5"], r"--friction LO HI must be ordered"),
            (
                N,
                ["push-sweep", "--gains", f["high"], "--gain-sets", "4", "--gain-scale-range", "2", "4"],
                r"--gain-scale-range \[2.0, 4.0\]: gain set 1: gain kp_com has entries above its range \[0, 10000\]",
            ),
            (N, ["push-sweep", "--seed", "1e20"], r"--seed must be a whole number in \[0, 4,294,967,295\]"),
            (N, ["push-sweep", "--seed", "-1"], r"--seed must be a whole number in \[0, "),
            (
                N,
                ["push-sweep", "--solver-iterations", "1e9"],
                r"--solver-iterations must be a whole number in \[1, 1000\]",
            ),
            (
                N,
                ["push-sweep", "--angular-weight-soft", "0"],
                r"--angular-weight-soft must be a number in \(0, 10000\]",
            ),
            (N, ["balance", "--angular-weight-soft", "nan"], r"--angular-weight-soft must be a number in \(0, 10000\]"),
            (N, ["balance", "--control-dt", "1"], r"--control-dt must be a number in \[0.001, 0.1\] s"),
            (
                N,
                ["balance", "--push-force", "nan", "0", "0"],
                r"--push-force must be a number in \[-5000, 5000\] N, got nan",
            ),
            (N, ["balance", "--push-onset", "-1"], r"--push-onset must be a number in \[0, 600\) s"),
            (N, ["balance", "--solver-iterations", "0"], r"--solver-iterations must be a whole number in \[1, 1000\]"),
            (N, ["balance", "--duration", "0.001"], r"shorter than one control tick"),
            (N, ["push-sweep", "--horizon", "0.5"], r"--horizon 0.5 s must end after the push"),
            (N, ["push-sweep", "--task", "one-foot"], r"one-foot sweeps push during the single-support phase"),
            (N, ["tune", "--lr", "1e9"], r"--lr must be a number in \(0, 10\]"),
            (N, ["tune", "--population", "1"], r"--population must be a whole number in \[2, "),
            (N, ["tune", "--bound-factor", "1"], r"--bound-factor must be a number in \(1, 1000\]"),
            (N, ["tune", "--zeta-range", "0.5", "inf"], r"--zeta-range must be a number in \(0, 100\], got inf"),
            (N, ["tune", "--batch", "0"], r"--batch must be a whole number in \[1, "),
            (N, ["tune", "--phases", "train", "pso"], r"invalid choice: 'pso'"),
            (
                N,
                ["tune", "--estimator", "smoothed", "--batch", "3", "--quality-pushes", "3"],
                r"--estimator smoothed pairs antithetic rollouts: --batch must be even",
            ),
            (
                N,
                ["tune", "--window-s", "5"],
                r"--window-s 5(\.0)? must be at least one tick \(0.01 s\) and shorter than --horizon",
            ),
            (N, ["tune", "--snapshots-s", "-1"], r"--snapshots-s must be a number in \(0, "),
            (N, ["heldout", "--sets", "bogus"], r"--sets entries are 'default', 'critical' or NAME=FILE"),
            (N, ["heldout", "--grid-horizon", "0.5"], r"held-out horizon 0.5 s ends before the pushes"),
            (N, ["heldout", "--grid-onset", "-1"], r"--grid-onset must be a number in \[0, 600\) s"),
            (N, ["tune", "--horizon", "0.1"], r"--horizon 0.1 s must end after the push"),
            (N, ["view", runs_["sweep"], "--env", "-1"], r"--env must be a whole number in \[0, "),
            (N, ["info", "--robot", "nao"], r"invalid choice: 'nao'"),
            # Contact geometry: the soles' normals are checked against the floor, as other contacts'.
            (C, ["balance", "--tasks", f["sole_down"]], r"contact 'l': normal \[0.0, 0.0, -1.0\] points into 'floor'"),
            (C, ["push-sweep", "--tasks", f["sole_down"]], r"points into 'floor'"),
            (
                C,
                ["balance", "--tasks", f["sole_side"]],
                r"contact 'l': normal .* points into 'floor' or along its surface",
            ),
            # Silent overwrite: a folder holding a run with other settings, or of another kind.
            (
                W,
                ["envelope", *grid, "--out", runs_["envelope"]],
                r"holds an envelope run made with other inputs \(config",
            ),
            (
                W,
                ["balance", "--out", runs_["balance"]],
                r"holds a balance run made with other inputs \(config.duration",
            ),
            (W, ["balance", "--out", runs_["sweep"]], r"holds a sweep run; a balance run needs its own folder"),
            (W, ["envelope", "--out", runs_["balance"]], r"holds a balance run; an envelope run needs its own folder"),
            (W, ["push-sweep", "--out", runs_["envelope"]], r"holds an envelope run"),
            (W, ["balance", "--out", str(runs_["corrupt"])], r"run.json is unreadable"),
            (W, ["push-sweep", "--out", f["file"]], r"--out .*a_file is a file"),
            (W, ["tune", "--out", f["file"]], r"--out .*a_file is a file"),
            (W, ["heldout", "--out", f["file"]], r"--out .*a_file is a file"),
            # Memory: refused before anything is allocated, with the estimate.
            (M, ["push-sweep", "--chunk-size", "1e9"], r"--chunk-size must be a whole number in \[1, 10,000,000\]"),
            (M, ["push-sweep", "--chunk-size", "inf"], r"--chunk-size expects a whole number, got 'inf'"),
            (M, ["push-sweep", "--directions", "1e9"], r"--directions must be a whole number in \[1, 100,000\]"),
            (M, ["push-sweep", "--magnitudes", "10", "100", "1e9"], r"N must be a whole number in \[1, 100,000\]"),
            (M, ["push-sweep", "--magnitudes", "0", "100", "100000", "--directions", "1000"], r"more than 10,000,000"),
            (
                M,
                ["push-sweep", "--magnitudes", "0", "100", "100000", "--directions", "100", "--chunk-size", "1e7"],
                r"--chunk-size 10,000,000: a batch of 10,000,000 environments needs about [\d,.]+ GB .* free; use "
                r"(--chunk-size|a smaller grid)",
            ),  # the hint depends on the memory free: both name what is valid
            # Tracebacks and late failures: every file problem names the file, before compiling.
            (T, ["balance", "--tasks", f["friction"]], r"scene object 'box': friction must be a number, got 'high'"),
            (T, ["push-sweep", "--tasks", f["normal_force"]], r"contact 'h': normal_force must be a number or null"),
            (T, ["balance", "--tasks", f["mu_huge"]], r"contact 'l': mu must be a number in \(0, 10\], got 1e\+30"),
            (T, ["balance", "--tasks", f["kp_text"]], r"kp must be a number or a list of numbers, got 'high'"),
            (T, ["balance", "--tasks", f["circle_inf"]], r"circle needs radius in \(0, 1\] m"),
            (T, ["balance", "--tasks", f["latin1_yaml"]], r"--tasks file .*latin1.yaml is not UTF-8 text"),
            (T, ["push-sweep", "--gains", f["latin1_json"]], r"--gains file .*latin1.json is not UTF-8 text"),
            (T, ["tune", "--envelope", f["latin1_json"]], r"--envelope file .*latin1.json is not UTF-8 text"),
            (T, ["balance", "--tasks", f["not_yaml"]], r"--tasks file .*bad.yaml is not valid YAML \(line"),
            (T, ["balance", "--tasks", f["txt"]], r"unknown format '.txt'; valid: .json, .yaml, .yml"),
            (T, ["balance", "--gains", f["rank"]], r"gain kp_com must be a list of 3 numbers, got shape \(2, 3\)"),
            (T, ["push-sweep", "--gains", f["rank"]], r"gain kp_com must be a list of 3 numbers, got shape \(2, 3\)"),
            (T, ["envelope", "--gains", f["text"]], r"gain kd_postural must be a list of 23 numbers, got 'high'"),
            (T, ["balance", "--gains", f["huge"]], r"kp_com has entries above its range \[0, 10000\]"),
            (T, ["balance", "--gains", f["not_json"]], r"gains file .*not.json is not valid JSON"),
            (T, ["balance", "--gains", str(f["dir"])], r"--gains .*a_dir is not a file"),
            (
                T,
                ["tune", "--init-gains", str(tmp / "missing.json")],
                r"--init-gains file .*missing.json does not exist",
            ),
            (T, ["tune", "--sets", "mine=/nowhere.json"], r"--sets mine file /nowhere.json does not exist"),
            (T, ["heldout", "--tasks", f["latin1_yaml"]], r"--tasks file .*latin1.yaml is not UTF-8 text"),
            (T, ["balance", "--duration", "abc"], r"--duration expects a number, got 'abc'"),
            (T, ["balance", "--solver-iterations", "1.5"], r"--solver-iterations expects a whole number"),
            (
                T,
                ["view", runs_["envelope"]],
                r"holds an envelope run, which keeps no trajectories; view shows a balance",
            ),
            (T, ["view", runs_["tune"]], r"holds a tune run, which keeps no trajectories"),
            (T, ["view", runs_["unfinished"]], r"results.parquet is missing: the sweep has not finished"),
            (T, ["view", f["file"]], r"is a file; give the output folder"),
            (T, ["view", str(tmp / "nowhere")], r"does not exist"),
            (T, ["view", runs_["sweep"], "--out", str(tmp), "--env", "0"], r"--out .* is a folder; give a .rrd file"),
            # Reporting: a vertical push has no azimuth (nor a horizontal LIP bound).
            (
                R,
                ["push-sweep", "--elevation", "90", "--directions", "8"],
                r"--elevation 90 is a vertical push, the same at "
                r"every azimuth: use --directions 1 \(got 8\)",
            ),
            (R, ["envelope", "--elevation", "-90"], r"--elevation -90 is a vertical push"),
        ]
        + several_processes_cases()
        + integrity_cases(tmp)
        + issue41_cases(tmp)
    )


# ---- Issue 41, class 9: several processes (jax.distributed) ------------------------------------
# Flags that cannot join processes, refused before JAX starts. (A process whose peers never come
# is tests/test_reliability_paths.py's: it exits within --initialization-timeout naming the
# coordinator.)


def several_processes_cases() -> list[tuple[str, list[str], str]]:
    """(class, argv, pattern) of the flags of several processes."""
    P = CLASSES[6]
    join = ["--distributed", "--coordinator", "localhost:4321", "--num-processes", "2", "--process-id"]
    return [
        (
            P,
            ["--num-processes", "2", "push-sweep"],
            r"--num-processes needs --distributed \(they say how processes "
            r"join; without it the job runs in this process alone\)",
        ),
        (
            P,
            ["--coordinator", "localhost:4321", "--num-processes", "2", "--process-id", "1", "push-sweep"],
            r"--coordinator --num-processes --process-id need --distributed",
        ),
        (
            P,
            ["--distributed", "--num-processes", "2", "push-sweep"],
            r"--coordinator, --num-processes and "
            r"--process-id go together \(or none: from SLURM/MPI\); got only --num-processes",
        ),
        (
            P,
            [*join[:2], "localhost", *join[3:], "0", "push-sweep"],
            r"--coordinator must be HOST:PORT with a port "
            r"in 1\.\.65535, got 'localhost'",
        ),
        (P, [*join, "2", "push-sweep"], r"--process-id must be in 0\.\.1, got 2"),
        (P, [*join[:4], "0", "--process-id", "0", "push-sweep"], r"--num-processes must be a whole number in \[1, "),
        (
            P,
            ["--distributed", "--initialization-timeout", "-1", "push-sweep"],
            r"--initialization-timeout must be a number in \(0, 3600\] s, got -1",
        ),
        (
            P,
            ["--distributed", "--initialization-timeout", "inf", "push-sweep"],
            r"--initialization-timeout must be a number in \(0, 3600\] s, got inf",
        ),
    ]


# ---- issue 41, classes 3, 4 and 7: results changed after they were written, claims of what was not
# measured, broken paths (each refused in one line before anything compiles) -----------------------


def _fake_sweep(path: pathlib.Path, outputs: dict | None = None, inputs: dict | None = None) -> str:
    """A finished-looking sweep folder (results.parquet of envs 0..1, a sweep's summary.json) whose
    run.json records the sha256 ``outputs`` (default: the files' own) and input files ``inputs``."""
    import pandas as pd

    from wbc_jax.control.gains import default_gains, gains_to_dict
    from wbc_jax.jobs import sweep_config

    path.mkdir()
    pd.DataFrame({"env": [0, 1], "survived": [True, False]}).to_parquet(path / "results.parquet", index=False)
    config = {
        k: list(v) if isinstance(v, tuple) else v
        for k, v in dataclasses.asdict(sweep_config.SweepConfig(out=None)).items()
    }
    _write(
        path / "summary.json",
        json.dumps({"config": config, "gains": gains_to_dict(default_gains(ICUB)), "backend": "mujoco"}),
    )
    own = {name: provenance.sha256(path / name) for name in ("results.parquet", "summary.json")}
    manifest = {"kind": "sweep", "fingerprint": {"inputs": inputs or {}}, "outputs": {**own, **(outputs or {})}}
    (path / "run.json").write_text(json.dumps(manifest))
    return str(path)


def _fake_envelope_run(path: pathlib.Path, summary: dict) -> str:
    """An envelope run folder whose summary.json was edited after the run recorded it."""
    path.mkdir()
    _write(path / "summary.json", json.dumps(summary))
    manifest = {"kind": "envelope", "fingerprint": {}, "outputs": {"summary.json": "0" * 64}}
    (path / "run.json").write_text(json.dumps(manifest))
    return str(path / "summary.json")


def integrity_cases(tmp: pathlib.Path) -> list[tuple[str, list[str], str]]:
    """(class, argv, pattern) of issue 41's classes 3, 4 and 7."""
    D, U, P = INTEGRITY_CLASSES
    gains = _write(tmp / "int_gains.json", "{}")
    envelope = {
        "config": {"body": "chest", "push_duration": 0.1, "push_onset": 0.5, "elevation": 0.0},
        "envelope": {"0": {str(a): {"impulse_ns": 10.0} for a in (0.0, 90.0, 180.0, 270.0)}},
    }
    bad_envelopes = {}
    for name, value in (("nan", float("nan")), ("inf", float("inf")), ("neg", -3.0)):
        doc = json.loads(json.dumps(envelope))
        doc["envelope"]["0"]["90.0"]["impulse_ns"] = value
        bad_envelopes[name] = _write(tmp / f"env_{name}.json", json.dumps(doc))
    (tmp / "int_dangling").symlink_to(tmp / "int_nowhere" / "x")
    (tmp / "int_loop").symlink_to(tmp / "int_loop")
    regular = _write(tmp / "int_regular", "x")
    foreign = tmp / "int_foreign"
    _fake_sweep(foreign)
    (foreign / "summary.json").write_text(json.dumps({"envelope": {"0": {}}, "config": {}}))
    (foreign / "run.json").unlink()
    good = _fake_sweep(tmp / "int_good")
    return [
        # Results changed after they were written: a table edited, an input file changed since the run.
        (
            D,
            ["view", _fake_sweep(tmp / "int_edited", {"results.parquet": "0" * 64}), "--env", "0"],
            r"results.parquet changed since the run wrote it \(its sha256 differs from .*run.json\); rerun the sweep",
        ),
        (
            D,
            ["view", _fake_sweep(tmp / "int_unrecorded", {"summary.json": None}), "--env", "0"],
            r"summary.json is not recorded in .*run.json \(copied in",
        ),
        (
            D,
            ["view", _fake_sweep(tmp / "int_inputs", inputs={gains: "sha256:" + "0" * 64}), "--env", "1"],
            r"its input files changed since it ran \(.*int_gains.json has changed since the run\)",
        ),
        (D, ["view", good, "--env", "0", "--out", f"{good}/summary.json"], r"give a .rrd file name \(view writes"),
        (
            D,
            ["limit", "--envelopes", _fake_envelope_run(tmp / "int_envelope", envelope)],
            r"--envelopes .*int_envelope/summary.json changed since the run wrote it .*; rerun that envelope",
        ),
        # Claims of what was not measured: no round, envelopes that are no impulse, no gain set.
        (U, ["limit", "--time-limit", "0"], r"--time-limit 0 summarises the rounds on disk, and --out .* holds none"),
        (
            U,
            ["limit", "--envelopes", bad_envelopes["nan"]],
            r"envelope at azimuth 90 deg is nan N s; an envelope is "
            r"a finite impulse >= 0 N s",
        ),
        (U, ["limit", "--envelopes", bad_envelopes["inf"]], r"azimuth 90 deg is inf N s; an envelope is a finite"),
        (U, ["limit", "--envelopes", bad_envelopes["neg"]], r"azimuth 90 deg is -3.0 N s; an envelope is a finite"),
        (U, ["heldout", "--sets"], r"--sets: give at least one gain set \('default', 'critical' or NAME=FILE\)"),
        # Broken paths: --out through a symlink to nothing or a loop, too long a name, under a file.
        (P, ["push-sweep", "--out", str(tmp / "int_dangling")], r"--out .*int_dangling is a symlink to a missing"),
        (
            P,
            ["balance", "--out", str(tmp / "int_loop" / "x")],
            r"int_loop is a symlink to a missing target or in a "
            r"loop",
        ),
        (P, ["envelope", "--out", str(tmp / ("n" * 300))], r"a name of 300 bytes; names are at most 255 bytes"),
        (P, ["tune", "--out", f"{regular}/run"], r"--out .*int_regular/run: .*int_regular is a file, not a folder"),
        (P, ["view", good, "--env", "0", "--out", "/proc/e.rrd"], r"--out /proc/e.rrd: cannot write in /proc"),
        (P, ["view", good, "--env", "0", "--out", f"{regular}/e.rrd"], r"int_regular is a file, not a folder"),
        (P, ["view", str(foreign), "--env", "0"], r"summary.json is not the summary of a push sweep"),
        (
            P,
            ["tune", "--envelope", f"{foreign}/summary.json"],
            r"envelope file .*int_foreign/summary.json: needs "
            r"matching azimuth_deg and positive impulse_ns lists, or the summary.json of wbc-jax envelope",
        ),
        (P, ["tune", "--envelope", _write(tmp / "int_list.json", "[1, 2]")], r"envelope file .*int_list.json: needs"),
        (
            P,
            [
                "limit",
                "--envelopes",
                _write(tmp / "int_ints.json", json.dumps({**envelope, "envelope": {"0": {"0": 5}}})),
            ],
            r"--envelopes .*int_ints.json: not the summary.json of wbc-jax envelope",
        ),
    ]


# ---- Issue 41, classes 1, 2 and 6: physical set-ups, push timing, files that attack the parser ----------


def issue41_cases(tmp: pathlib.Path) -> list[tuple[str, list[str], str]]:
    """Task files that cannot be physical (class 1: each refusal names the file, the contact and what
    was measured), pushes shorter than one physics step in every job that takes one (class 2), and
    files built to exhaust the parser (class 6: alias bombs, deep nesting, oversized)."""
    feet = "contacts:\n  - {name: l, frame: l_sole, normal: [0, 0, 1]%s}\n  - {name: r, frame: r_sole, normal: [0, 0, 1]}\n"
    laughs = ['a: &a ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]']
    for prev, name in zip("abcdefgh", "bcdefghi"):
        laughs.append(f"{name}: &{name} [{', '.join([f'*{prev}'] * 9)}]")
    f = {
        "lifted": _write(
            tmp / "lifted.yaml", feet % "" + "initial_posture_deg: {l_hip_pitch: 36, l_knee: -46, l_ankle_pitch: -10}\n"
        ),
        "tilted": _write(tmp / "tilted.yaml", feet % "" + "initial_posture_deg: {l_ankle_roll: 8}\n"),
        "normal": _write(
            tmp / "normal.yaml", (feet % "").replace("[0, 0, 1]}\n  - {name: r", "[0, 0.1, 1]}\n  - {name: r")
        ),
        "cop": _write(tmp / "cop.yaml", feet % ", cop: [[-0.3, 0.3], [-0.1, 0.1]]"),
        "crate": _write(
            tmp / "crate.yaml", feet % "" + "scene:\n  - {name: crate, size: [0.1, 0.1, 0.1], pos: [0, 0, 0.5]}\n"
        ),
        "default_tilt": _write(
            tmp / "default_tilt.yaml",
            "tasks: [{name: posture, kind: postural}]\ninitial_posture_deg: {r_ankle_pitch: 15}\n",
        ),
        "bomb": _write(tmp / "bomb.yaml", "\n".join(laughs) + "\ncontacts: *i\n"),
        "recursive": _write(tmp / "recursive.yaml", "contacts: &r [*r]\n"),
        "deep_yaml": _write(tmp / "deep.yaml", "contacts: " + "[" * 50000 + "]" * 50000 + "\n"),
        "deep_json": _write(tmp / "deep.json", '{"kp_com": ' + "[" * 100000 + "]" * 100000 + "}"),
        "big_json": _write(tmp / "big.json", '{"kp_com": [' + "0, " * (2 * 2**20) + "0]}"),
        "long_value": _write(tmp / "long.yaml", (feet % ", mu: [%s]") % ", ".join(["1"] * 5000)),
    }
    P, S, A = INPUT_CLASSES
    push = ["--push-force", "10", "0", "0"]
    step = r"must be a number in \[0.001, 60\] s, got 0.0005"  # at least one physics step (1 ms)
    return [
        (P, ["balance", "--tasks", f["lifted"]], r"lifted.yaml: contact 'l': sole l_sole is 4.1 cm above the floor"),
        (P, ["push-sweep", "--tasks", f["tilted"]], r"tilted.yaml: contact 'l': sole l_sole is tilted 8.0 deg against"),
        (P, ["balance", "--tasks", f["normal"]], r"normal.yaml: contact 'l': normal .* is 5.7 deg from the normal"),
        (P, ["envelope", "--tasks", f["cop"]], r"cop.yaml: contact 'l': CoP rectangle .* is larger than the foot"),
        (P, ["balance", "--tasks", f["crate"]], r"crate.yaml: scene object 'crate' intersects the robot .* cm inside"),
        (P, ["tune", "--tasks", f["default_tilt"]], r"default_tilt.yaml: contact 'r_sole': sole r_sole is tilted 25.0"),
        (S, ["balance", *push, "--push-duration", "0.0005"], r"--push-duration " + step),
        (S, ["push-sweep", "--push-duration", "0.0005"], r"--push-duration " + step),
        (S, ["envelope", "--push-duration", "0.0005"], r"--push-duration " + step),
        (S, ["limit", "--push-duration", "0.0005"], r"--push-duration " + step),
        (S, ["tune", "--duration-range", "0.0005", "0.1"], r"--duration-range " + step),
        (S, ["heldout", "--grid-duration", "0.0005"], r"--grid-duration " + step),
        (A, ["balance", "--tasks", f["bomb"]], r"bomb.yaml expands to more than 200,000 values"),
        (A, ["push-sweep", "--tasks", f["recursive"]], r"recursive.yaml: a YAML alias refers to a value that contains"),
        (A, ["balance", "--tasks", f["deep_yaml"]], r"deep.yaml nests 33 levels deep; at most 32 are read"),
        (A, ["balance", "--gains", f["deep_json"]], r"--gains file .*deep.json nests 100001 levels deep; at most 32"),
        (A, ["tune", "--init-gains", f["big_json"]], r"--init-gains file .*big.json is larger than 4 MiB"),
        (
            A,
            ["balance", "--tasks", f["long_value"]],
            r"contact 'l': mu must be a number, got \(1, 1, 1, 1, 1, 1, 1, 1, \.\.\.\)$",
        ),
    ]


def argv_with_out(argv: list[str], out: pathlib.Path) -> list[str]:
    """``argv`` with ``--out OUT`` where its job has that flag and the case gives none."""
    if argv[0] in ("info", "view") or "--out" in argv:
        return list(argv)
    return [*argv, "--out", str(out)]


def judge(rc: int, err: str, seconds: float, pattern: str, wrote: bool, max_seconds: float) -> list[str]:
    """What went wrong with one case (empty: it passed)."""
    problems = []
    lines = [line for line in err.splitlines() if line.strip() and not line.startswith("usage")]
    if rc != 2:
        problems.append(f"exit code {rc}")
    if "Traceback" in err:
        problems.append("traceback")
    if len(lines) != 1:
        problems.append(f"{len(lines)} error lines")
    if not re.search(pattern, err):
        problems.append("message does not match")
    if seconds > max_seconds:
        problems.append(f"{seconds:.1f} s > {max_seconds:g} s")
    if wrote:
        problems.append("wrote --out")
    return problems


BAR = (
    "every case exits with status 2 within --max-seconds, in one error line matching its pattern (the flag or "
    "file and its valid values), without a traceback and without writing its --out"
)


def failures(result: dict) -> list[str]:
    """One line per case that misbehaved; none run is a failure too."""
    if not result.get("cases_run"):
        return ["no case was run"]
    return [f"{r['command']}: {', '.join(r['problems'])}" for r in result["cases_run"] if r["problems"]]


def run_case(
    cmd: list[str], pattern: str, out: pathlib.Path, cwd: pathlib.Path, env: dict, timeout: float, max_seconds: float
) -> dict:
    """One case as a subprocess: its exit code, first error line, seconds and problems."""
    t0 = time.time()
    try:
        proc = subprocess.run(
            [sys.executable, "-m", "wbc_jax.cli", *cmd],
            capture_output=True,
            text=True,
            env=env,
            timeout=timeout,
            cwd=cwd,
        )
        rc, err = proc.returncode, proc.stderr
    except subprocess.TimeoutExpired:
        rc, err = None, ""
    seconds = time.time() - t0
    problems = ["hang"] if rc is None else judge(rc, err, seconds, pattern, out.exists(), max_seconds)
    first = next((line for line in err.splitlines() if line.strip() and not line.startswith("usage")), "")
    return {
        "exit_code": rc,
        "stderr_first_line": first,
        "seconds": round(seconds, 2),
        "ok": not problems,
        "problems": problems,
    }


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0], epilog=f"Check: {BAR}; exit status 1 otherwise.")
    p.add_argument("--max-seconds", type=float, default=30.0, help="slowest acceptable failure (s)")
    p.add_argument("--timeout", type=float, default=120.0, help="a case still running after this is a hang (s)")
    p.add_argument("-k", default=None, help="only cases whose command contains this text")
    p.add_argument("--out", default="runs/bad_input", help="folder of bad_input.json")
    p.add_argument("--record", action="store_true", help="also write the cases into results/reliability.json")
    args = p.parse_args(argv)
    env = {**os.environ, "JAX_PLATFORMS": os.environ.get("JAX_PLATFORMS", "cpu")}
    rows = []
    with tempfile.TemporaryDirectory() as d:
        tmp = pathlib.Path(d)
        for k, (klass, case, pattern) in enumerate(cases(tmp)):
            out = tmp / f"out_{k}"  # a case's own: one that writes cannot spoil the next
            cmd = argv_with_out(case, out)
            if args.k and args.k not in " ".join(cmd):
                continue
            row = run_case(cmd, pattern, out, tmp, env, args.timeout, args.max_seconds)
            shown = " ".join(a.replace(str(out), "$OUT").replace(str(tmp), "$TMP") for a in cmd)
            row = {
                "class": klass,
                "command": f"wbc-jax {shown}",
                **row,
                "stderr_first_line": row["stderr_first_line"].replace(str(tmp), "$TMP"),
            }
            rows.append(row)
            print(
                f"{'ok ' if row['ok'] else 'BAD'} {row['seconds']:5.1f} s rc={row['exit_code']} {shown[:90]}"
                f"{'' if row['ok'] else '  <- ' + ', '.join(row['problems'])}",
                flush=True,
            )
    passed = sum(r["ok"] for r in rows)
    print(f"{passed}/{len(rows)} cases fail fast and clearly")
    result = {
        "cases": len(rows),
        "passed": passed,
        "max_seconds": args.max_seconds,
        "slowest_s": max((r["seconds"] for r in rows), default=None),
        "by_class": {c: sum(r["class"] == c for r in rows) for c in CLASSES},
        "device": provenance.device_label(),
        "date": time.strftime("%Y-%m-%d"),
        "command": "python experiments/checks/bad_input.py " + " ".join(sys.argv[1:] if argv is None else argv),
        "cases_run": rows,
        "provenance": provenance.record(),
    }
    result["check"] = checks.verdict(failures(result), BAR)
    io.atomic_write_json(pathlib.Path(args.out) / "bad_input.json", result)
    if args.record:
        path = ROOT / "results" / "reliability.json"
        doc = json.loads(path.read_text()) if path.exists() else {}
        doc.pop("bad_input_pass2", None)  # the second pass's cases are in git history
        doc["bad_input_pass3"] = {k: v for k, v in result.items() if k != "provenance"}
        io.atomic_write_bytes(path, (json.dumps(doc, indent=1) + "\n").encode())  # the file's own layout
    return result


if __name__ == "__main__":
    sys.exit(checks.exit_status(main()))
