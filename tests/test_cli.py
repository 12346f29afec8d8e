"""The command line: flags generated from the job configs, and bad input named in one line before
anything is compiled or written (a tripwire on jax.jit fails any case that gets that far); run
directories bound to their inputs (no mixed or dropped results)."""

import json
import os
import re

import jax
import numpy as np
import pytest

from wbc_jax import cli
from wbc_jax.control.gains import default_gains, gains_to_dict
from wbc_jax.jobs import balance, sweep_config
from wbc_jax.tuning import config as tune_config


def test_flags_are_generated_from_the_configs(capsys):
    heldout = tune_config.heldout_default_config()
    for command, configs in (("balance", [balance.default_config()]), ("push-sweep", [sweep_config.default_config()]),
                             ("tune", [tune_config.default_config(), heldout]), ("heldout", [heldout])):  # fmt: skip
        with pytest.raises(SystemExit):
            cli.main([command, "--help"])
        text = capsys.readouterr().out
        for config in configs:
            for field in config.__dataclass_fields__:
                assert f"--{field.replace('_', '-')}" in text, (command, field)
    # tune and heldout: the held-out flags from one config, with the same names and defaults.
    parser = cli.build_parser()
    for command in ("tune", "heldout"):
        hc = cli.config_from_args(parser.parse_args([command, "--grid-magnitudes", "10", "30", "3",
                                                     "--grid-directions", "4", "--chunk-size", "7"]), heldout)  # fmt: skip
        assert hc.grid_magnitudes == (10.0, 20.0, 30.0) and hc.grid_directions == (0.0, 90.0, 180.0, 270.0)
        assert hc.chunk_size == 7 and hc.sinusoid_s == heldout.sinusoid_s
    assert cli.config_from_args(parser.parse_args(["tune", "--tasks", "t.yaml"]), heldout).tasks == "t.yaml"
    # Defaults shown as they are given on the command line; values parsed into the config.
    parser = cli.build_parser()
    args = parser.parse_args(["push-sweep", "--magnitudes", "10", "30", "3", "--directions", "8"])
    cfg = cli.config_from_args(args, sweep_config.default_config())
    assert cfg.magnitudes == (10.0, 20.0, 30.0) and len(cfg.directions) == 8 and cfg.directions[2] == 90.0
    assert (
        cli.config_from_args(parser.parse_args(["push-sweep"]), sweep_config.default_config())
        == sweep_config.default_config()
    )


@pytest.fixture
def tripwire(monkeypatch):
    """Any jax.jit after this point means the input check came too late."""

    def late(*args, **kwargs):
        raise AssertionError("late failure: the bad input reached jax.jit (compilation)")

    monkeypatch.setattr(jax, "jit", late)


def _write(path, text):
    path.write_text(text)
    return str(path)


def _cases(tmp):
    gains_dir = tmp / "gains_dir"
    gains_dir.mkdir()
    huge = gains_to_dict(default_gains())
    huge["kp_com"] = [1e30, 50.0, 10.0]
    huge_gains = _write(tmp / "huge.json", json.dumps(huge))
    task = "tasks: [{name: hand, kind: position, frame: r_hand, %s}, {name: posture, kind: postural}]\n"
    a_file = _write(tmp / "a_file", "x")
    sweep_run = tmp / "a_sweep"
    sweep_run.mkdir()
    (sweep_run / "run.json").write_text(json.dumps({"kind": "sweep", "fingerprint": {}}))
    balance_run = tmp / "a_balance"
    balance_run.mkdir()
    (balance_run / "run.json").write_text(json.dumps({"kind": "balance", "fingerprint": {}}))
    corrupt = tmp / "corrupt"
    corrupt.mkdir()
    (corrupt / "run.json").write_text("{\n")
    out = str(tmp / "out")
    return [
        (["balance", "--push-force", "nan", "0", "0"], r"push force must be 3 finite numbers"),
        (["balance", "--duration", "inf"], r"--duration must be a positive finite"),
        (["balance", "--duration", "abc"], r"--duration expects a number, got 'abc'"),
        (["balance", "--push-onset", "-1"], r"--push-onset must be a finite number of seconds >= 0"),
        (["balance", "--solver-iterations", "0"], r"solver_iterations must be a positive integer"),
        (["balance", "--solver-iterations", "1.5"], r"--solver-iterations expects a whole number"),
        (["balance", "--control-dt", "0"], r"--control-dt must be a positive"),
        (["balance", "--angular-weight-soft", "nan"], r"--angular-weight-soft must be positive and finite"),
        (["balance", "--out", a_file], r"is a file"),
        (["balance", "--out", str(sweep_run)], r"holds a sweep run"),
        (["balance", "--out", str(corrupt)], r"run.json is unreadable"),
        (["balance", "--gains", str(gains_dir)], r"is not a file"),
        (["balance", "--gains", str(tmp / "missing.json")], r"does not exist"),
        (["balance", "--gains", huge_gains], r"kp_com has entries above its range \[0, 10000\]"),
        (["balance", "--duration", "0.001"], r"shorter than one control tick"),
        (
            ["balance", "--backend", "warp"]
            if not any(d.platform == "gpu" for d in jax.devices())
            else ["balance", "--backend", "nope"],
            r"needs a CUDA GPU|invalid choice",
        ),  # fmt: skip
        (["balance", "--tasks", _write(tmp / "w.yaml", task % "weight: heavy")], r"weight must be a positive number"),
        (
            [
                "balance",
                "--tasks",
                _write(tmp / "j.yaml", task.replace("kind: position, frame: r_hand", "kind: joints") % "joints: 5"),
            ],
            r"joints must be joint names",
        ),  # fmt: skip
        (["balance", "--tasks", _write(tmp / "p.yaml", task % "priority: high")], r"priority must be a whole number"),
        (
            [
                "balance",
                "--tasks",
                _write(
                    tmp / "q.yaml",
                    "contacts: [{name: l, frame: l_sole, normal: [0, 0, 1]}, "
                    "{name: r, frame: r_sole, normal: [0, 0, 1]}]\ninitial_posture_deg: {l_knee: 200}\n",
                ),
            ],
            r"l_knee = 200 deg is outside its joint range",
        ),  # fmt: skip
        (["push-sweep", "--magnitudes", "20", "40", "2.9"], r"N must be a whole number >= 1, got 2.9"),
        (["push-sweep", "--magnitudes", "20", "40", "nan"], r"--magnitudes LO HI N needs finite numbers"),
        (["push-sweep", "--magnitudes", "0", "100", "100000", "--directions", "1000"], r"more than 10,000,000"),
        (["push-sweep", "--directions", "0"], r"--directions must be a whole number >= 1"),
        (["push-sweep", "--seed", "-1"], r"--seed must be a whole number >= 0"),
        (["push-sweep", "--chunk-size", "0"], r"--chunk-size must be a whole number >= 1"),
        (["push-sweep", "--horizon", "0.5"], r"--horizon 0.5 s must end after the push"),
        (["push-sweep", "--friction", "1", "0.5"], r"--friction range must be positive and ordered"),
        (["push-sweep", "--angular-weight-soft", "0"], r"--angular-weight-soft must be positive and finite"),
        (["push-sweep", "--body", "nose", "--out", out], r"unknown body 'nose'; valid bodies"),
        (["push-sweep", "--out", a_file], r"is a file"),
        (["push-sweep", "--out", str(balance_run)], r"holds a balance run"),
        (["push-sweep", "--gains", str(gains_dir)], r"is not a file"),
        (["view", a_file], r"is a file"),
        (["view", str(tmp / "nowhere")], r"does not exist"),
        (["tune", "--out", a_file], r"is a file"),
        (["tune", "--batch", "0"], r"--batch must be a whole number >= 1"),
        (["tune", "--horizon", "0.1"], r"--horizon 0.1 s must end after the push"),
        (["tune", "--lr", "nan"], r"--lr must be positive and finite"),
        (
            ["tune", "--estimator", "smoothed", "--batch", "3", "--quality-pushes", "3"],
            r"--estimator smoothed pairs antithetic rollouts: --batch must be even",
        ),
        (["tune", "--window-s", "5"], r"--window-s 5 must be at least one tick \(0.01 s\) and shorter than --horizon"),
        (["tune", "--phases", "train", "sweep"], r"invalid choice: 'sweep'"),
        (["tune", "--sets", "mine=/nowhere.json"], r"--sets mine=/nowhere.json: /nowhere.json is not a file"),
        (["heldout", "--sets", "bogus"], r"--sets entries are 'default', 'critical' or NAME=FILE"),
        (["heldout", "--grid-horizon", "0.5"], r"held-out horizon 0.5 s ends before the pushes"),
        (["heldout", "--out", a_file], r"is a file"),
    ]


CASE_COUNT = 46


def test_every_bad_input_case_is_listed(tmp_path):
    assert len(_cases(tmp_path)) == CASE_COUNT


@pytest.mark.parametrize("k", range(CASE_COUNT))
def test_bad_input_is_one_clear_early_line(k, tmp_path, capsys, tripwire):
    argv, message = _cases(tmp_path)[k]
    argv = [*argv] if "--out" in argv or argv[0] == "view" else [*argv, "--out", str(tmp_path / "out")]
    try:
        rc = cli.main(argv)
    except SystemExit as exc:  # argparse: usage + one error line
        rc = exc.code
    err = capsys.readouterr().err
    assert rc == 2, (argv, err)
    assert "Traceback" not in err, err
    assert re.search(message, err), (argv, err)
    lines = [line for line in err.splitlines() if line.strip() and not line.startswith("usage")]
    assert len(lines) <= 2, err
    assert not (tmp_path / "out").exists(), "nothing is written for bad input"


def test_result_files_have_the_users_permissions(tmp_path):
    from wbc_jax.core import io

    old = os.umask(0o022)
    try:
        io.atomic_write_json(tmp_path / "x.json", {"a": 1})
    finally:
        os.umask(old)
    assert (tmp_path / "x.json").stat().st_mode & 0o777 == 0o644


def test_resume_binds_the_run_to_its_inputs(tmp_path, capsys):
    """A finished sweep re-run with another gains file (same path, other contents) is refused and
    names the difference; a part file replaced by another chunk's is recomputed; the results hold
    each env once."""
    gains = tmp_path / "g.json"
    gains.write_text(json.dumps(gains_to_dict(default_gains())))
    out = tmp_path / "sw"
    argv = ["push-sweep", "--magnitudes", "20", "40", "2", "--directions", "1", "--horizon", "0.05",
            "--push-onset", "0", "--push-duration", "0.02", "--chunk-size", "1", "--gains", str(gains),
            "--out", str(out), "--quiet"]  # fmt: skip
    assert cli.main(argv) == 0, capsys.readouterr().err
    import pandas as pd

    first = pd.read_parquet(out / "results.parquet")
    assert first["env"].tolist() == [0, 1]
    # A part overwritten with a copy of the other: detected by its env range and recomputed.
    (out / "parts" / "part-00000.parquet").write_bytes((out / "parts" / "part-00001.parquet").read_bytes())
    assert cli.main(argv) == 0, capsys.readouterr().err
    again = pd.read_parquet(out / "results.parquet")
    assert again["env"].tolist() == [0, 1]
    np.testing.assert_allclose(again["com_rmse_m"], first["com_rmse_m"], rtol=1e-6)
    # Other gains in the same file: refused, naming the file.
    values = gains_to_dict(default_gains())
    values["kp_com"] = [60.0, 60.0, 10.0]
    gains.write_text(json.dumps(values))
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert "made with other inputs" in err and "g.json" in err and "contents changed" in err
