"""experiments/campaigns/upgrade_run.py: a run folder of the old record (inputs by path) resumes once upgraded,
with its inputs moved; other inputs are still refused."""

import importlib.util
import json
import pathlib

import pytest

from wbc_jax.jobs import runs

ROOT = pathlib.Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("upgrade_run", ROOT / "experiments" / "campaigns" / "upgrade_run.py")
upgrade_run = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(upgrade_run)


def _old_run(tmp_path, gains_text: str):
    """An old-kind run folder whose config names ``old/gains.json``; returns (run dir, the file's new path)."""
    old = tmp_path / "old" / "gains.json"
    old.parent.mkdir()
    old.write_text(gains_text)
    config = {"tune": {"init_gains": str(old), "lr": 0.1}}
    fp = runs.fingerprint(config, [old], "icub")
    legacy = {
        "config": json.loads(json.dumps(config)),
        "files": {str(old): fp[runs.INPUT_PATHS][str(old.resolve())].removeprefix("sha256:")},
        "model": fp["model"],
        "version": fp["version"],
    }
    run = tmp_path / "run"
    (run / "cmaes").mkdir(parents=True)
    (run / "cmaes" / "history.csv").write_text("generation,loss\n0,1.0\n")
    (run / runs.MANIFEST).write_text(json.dumps({"kind": "tune", "fingerprint": legacy}))
    new = tmp_path / "assets" / "gains.json"
    new.parent.mkdir()
    old.rename(new)  # the input moved, as the hand-set gains did
    return run, new


def test_old_run_resumes_after_upgrade_and_still_refuses_other_inputs(tmp_path):
    run, new = _old_run(tmp_path, '{"kp_com": 1.0}')
    fp = runs.fingerprint({"tune": {"init_gains": str(new), "lr": 0.1}}, [new], "icub")
    with pytest.raises(ValueError, match="made with other inputs"):  # the old record: refused once moved
        runs.check_output_dir(run, "tune", fp)
    assert upgrade_run.main([str(run)]) == 0
    assert runs.claim_output_dir(run, "tune", fp, resume=True) is True  # same content by another path: resumes
    assert runs.output_changed(run / "cmaes" / "history.csv") is None  # adopted as the run's own
    other = tmp_path / "other.json"
    other.write_text('{"kp_com": 2.0}')
    with pytest.raises(ValueError, match="init_gains"):
        runs.check_output_dir(
            run, "tune", runs.fingerprint({"tune": {"init_gains": str(other), "lr": 0.1}}, [other], "icub")
        )
    with pytest.raises(ValueError, match="made with other inputs"):
        runs.check_output_dir(
            run, "tune", runs.fingerprint({"tune": {"init_gains": str(new), "lr": 0.2}}, [new], "icub")
        )
    assert upgrade_run.main([str(run)]) == 1  # already of today's kind: nothing to do, said so
