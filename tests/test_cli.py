"""The command line: flags generated from the job configs, and bad input named in one line before
anything is compiled or written (a tripwire on jax.jit fails any case that gets that far); run
directories bound to their inputs (no mixed or dropped results)."""

import importlib.util
import json
import math
import os
import pathlib
import tempfile

import jax
import numpy as np
import pytest

from wbc_jax import cli
from wbc_jax.control.gains import default_gains, gains_to_dict
from wbc_jax.core import options
from wbc_jax.jobs import sweep_config
from wbc_jax.robot.icub import DESCRIPTION as ICUB
from wbc_jax.tuning import heldout_config
from wbc_jax.tuning.algorithms import gradient  # noqa: F401  (before the tripwire: optax applies jax.jit when imported)

_spec = importlib.util.spec_from_file_location(
    "bad_input", pathlib.Path(__file__).resolve().parents[1] / "experiments" / "checks" / "bad_input.py"
)
bad_input = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bad_input)


def test_flags_are_generated_from_the_configs(capsys):
    for command, (config, _) in cli.job_configs().items():
        with pytest.raises(SystemExit):
            cli.main([command, "--help"])
        text = capsys.readouterr().out
        for field in options.flat_fields(config):
            assert options.flag_name(field) in text, (command, field.name)
    # Defaults shown as they are given on the command line; values parsed into the config.
    parser = cli.build_parser()
    args = parser.parse_args(["push-sweep", "--magnitudes", "10", "30", "3", "--directions", "8"])
    cfg = cli.config_from_args(args, sweep_config.default_config())
    assert cfg.magnitudes == (10.0, 20.0, 30.0) and len(cfg.directions) == 8 and cfg.directions[2] == 90.0
    assert (
        cli.config_from_args(parser.parse_args(["push-sweep"]), sweep_config.default_config())
        == sweep_config.default_config()
    )


def test_tune_and_heldout_share_the_held_out_flags(tmp_path):
    """tune and heldout: the held-out flags from one config, with the same names and defaults; tune's
    own --tasks is the held-out evaluation's."""
    heldout = heldout_config.heldout_default_config()
    parser = cli.build_parser()
    for command in ("tune", "heldout"):
        hc = cli.config_from_args(
            parser.parse_args(
                [command, "--grid-magnitudes", "10", "30", "3", "--grid-directions", "4", "--chunk-size", "7"]
            ),
            heldout,
        )
        assert hc.grid_magnitudes == (10.0, 20.0, 30.0) and hc.grid_directions == (0.0, 90.0, 180.0, 270.0)
        assert hc.chunk_size == 7 and hc.sinusoid_s == heldout.sinusoid_s
    tasks = str(tmp_path / "t.yaml")
    pathlib.Path(tasks).write_text("contacts: []\n")
    assert cli.config_from_args(parser.parse_args(["tune", "--tasks", tasks]), heldout).controller.tasks == tasks


def test_heldout_reeval_takes_the_heldout_jobs_flags():
    """experiments/campaigns/heldout_reeval.py declares no held-out flag of its own: wbc-jax heldout's,
    generated from the job's config (the job's defaults but its sets and folder), checked as the job
    checks them."""
    from conftest import load_script

    script = load_script("experiments/campaigns/heldout_reeval.py")
    hc, previous = script.parse(["--grid-directions", "4", "--chunk-size", "7", "--no-one-foot"])
    job = heldout_config.heldout_default_config()
    assert hc == options.replace(
        job,
        sets=script.DEFAULT_SETS,
        out="runs/heldout_reeval",
        grid_directions=(0.0, 90.0, 180.0, 270.0),
        chunk_size=7,
        one_foot=False,
    )
    assert previous.endswith("results/tuning/heldout.json")
    with pytest.raises(ValueError, match=r"--chunk-size must be a whole number in \[1, "):
        script.parse(["--chunk-size", "0"])


def _declared(config):
    """(flag, Valid, scalar type) of each number field of a job config."""
    for field in options.flat_fields(config):
        kind, _, _ = options.field_type(type(config), field)
        valid = field.metadata["valid"]
        if kind in (int, float) and valid.choices is None and "parse" not in field.metadata:
            yield field, valid, kind


def test_every_flag_has_a_declared_range():
    """One mechanism: every number flag of every job declares both bounds; every file flag is an
    input file; every other text flag has its choices or names (or is a path or a folder)."""
    paths = {"out", "run_dir", "tasks", "gains", "init_gains", "envelope", "envelopes"}
    for command, (config, _) in cli.job_configs().items():
        for field in options.flat_fields(config):
            valid = field.metadata["valid"]
            kind, _, _ = options.field_type(type(config), field)
            if kind in (int, float):
                bounded = (valid.ge, valid.gt) != (None, None) and (valid.le, valid.lt) != (None, None)
                assert bounded or valid.choices is not None, (command, field.name)
            elif kind is str:
                # --sets: 'default', 'critical' or NAME=FILE (each FILE checked as an input file).
                assert valid.choices or valid.names or field.name in paths | {"sets"}, (command, field.name)
                assert valid.input_file == (field.name in paths - {"out", "run_dir"}), (command, field.name)


@pytest.mark.parametrize("value", ["0", "-1", "nan", "inf", "-inf", "1e30", "2.5"])
def test_every_number_flag_is_refused_outside_its_range(value, tmp_path, monkeypatch):
    """Each number flag of each job at 0, negative, NaN, inf, absurdly large, fractional: refused
    in one line naming the flag and its range exactly when the value is outside the declaration
    (or the job's cross-checks), never with another error."""
    monkeypatch.chdir(tmp_path)  # the jobs' default --out folders
    run = tmp_path / "run"
    run.mkdir()
    (run / "trajectory.npz").write_bytes(b"")
    checked = 0
    parser = cli.build_parser()
    for command, (config, _) in cli.job_configs().items():
        for field, valid, kind in _declared(config):
            flag = options.flag_name(field)
            nargs = field.metadata.get("nargs", 1)
            if value == "-inf" and nargs != 1:
                continue  # argparse takes "-inf" for a flag: "expected 2 arguments", its own one line
            count = nargs if isinstance(nargs, int) else 1  # "*" / "+": one value
            given = [f"{flag}={value}"] if nargs == 1 else [flag, *[value] * count]
            argv = [command, *([str(run)] if command == "view" else []), *given]
            try:
                args = parser.parse_args(argv)
            except SystemExit:  # argparse: not a whole number (its one line is tested below)
                number = float(value)
                assert kind is int and not (math.isfinite(number) and number == int(number)), (argv, value)
                continue
            inside = valid.contains(float(value)) and math.isfinite(float(value))
            try:
                cli.config_from_args(args, config).check()
                refused = None
            except (ValueError, FileNotFoundError) as err:
                refused = str(err)
            if not inside:
                assert refused is not None and refused.startswith(flag) and "must be" in refused, (argv, refused)
                assert valid.describe(kind is int) in refused, (argv, refused)
                checked += 1
            elif refused is not None:  # inside the range: only a cross-check may refuse it, naming it
                assert flag in refused or field.name.replace("_", "-") in refused or "push" in refused, (argv, refused)
    assert checked > 0


@pytest.fixture
def tripwire(monkeypatch):
    """Any jax.jit after this point means the input check came too late."""

    def late(*args, **kwargs):
        raise AssertionError("late failure: the bad input reached jax.jit (compilation)")

    monkeypatch.setattr(jax, "jit", late)


CASES = bad_input.cases(pathlib.Path(tempfile.mkdtemp()))


def test_every_class_of_the_issue_has_cases():
    assert {klass for klass, _, _ in CASES} == set(bad_input.CLASSES)
    assert len(CASES) >= 80


@pytest.mark.parametrize("k", range(len(CASES)))
def test_bad_input_is_one_clear_early_line(k, tmp_path, capsys, tripwire):
    """experiments/checks/bad_input.py's cases in one process: exit 2, one line naming the problem, no
    traceback, nothing written, before anything compiles (the tripwire)."""
    klass, argv, message = bad_input.cases(tmp_path)[k]
    argv = bad_input.argv_with_out(argv, tmp_path / "out")
    try:
        rc = cli.main(argv)
    except SystemExit as exc:  # argparse: usage + one error line
        rc = exc.code
    err = capsys.readouterr().err
    assert not bad_input.judge(rc, err, 0.0, message, (tmp_path / "out").exists(), 30.0), (klass, argv, err)


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
    gains.write_text(json.dumps(gains_to_dict(default_gains(ICUB))))
    out = tmp_path / "sw"
    argv = [
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
        "--gains",
        str(gains),
        "--out",
        str(out),
        "--quiet",
    ]
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
    # The resumed run simulated one env; the summary counts both (5 ticks of 10 physics steps each).
    summary = json.loads((out / "summary.json").read_text())
    assert summary["resumed_envs"] == 1
    assert summary["physics_steps_simulated"] == 2 * 5 * 10
    # Other gains in the same file: refused, naming the file.
    values = gains_to_dict(default_gains(ICUB))
    values["kp_com"] = [60.0, 60.0, 10.0]
    gains.write_text(json.dumps(values))
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert "made with other inputs" in err and "g.json" in err and "contents changed" in err


def test_memory_is_estimated_before_a_chunk_is_allocated(tmp_path, capsys, tripwire, monkeypatch):
    """A chunk that cannot fit is refused with the estimate and the largest chunk that fits, before
    anything compiles; a chunk larger than the sweep is cut to the sweep (never padded beyond it)."""
    from wbc_jax.sim import runner

    assert sweep_config.SweepConfig(chunk_size=100_000, out=None).batch_size == 12
    monkeypatch.setattr(runner, "available_memory", lambda: (200e6, "host"))
    argv = [
        "push-sweep",
        "--magnitudes",
        "10",
        "100",
        "100",
        "--directions",
        "4",
        "--chunk-size",
        "400",
        "--out",
        str(tmp_path / "out"),
    ]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    per_env = runner.HOST_ENV_BYTES  # at least: C MuJoCo on the CPU
    fits = int((200e6 - 400 * 400) // per_env)  # below it: the scenarios and MJX's share are counted too
    assert "--chunk-size 400: a batch of 400 environments needs about" in err and "host has 0.2 GB free" in err, err
    assert 0 < int(err.split("use --chunk-size ")[1].split()[0].replace(",", "")) <= fits, err
    assert not (tmp_path / "out").exists()
