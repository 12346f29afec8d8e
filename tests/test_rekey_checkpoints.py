"""experiments/campaigns/rekey_checkpoints.py: after --init-gains moved, a run's checkpoints carry the key the moved
config computes (tuning/config.config_key), stay the run's own outputs, and any other content or key is refused."""

import dataclasses
import importlib.util
import json
import pathlib

import numpy as np
import pytest

from wbc_jax.core import io, provenance
from wbc_jax.core.options import flat_dict
from wbc_jax.jobs import runs
from wbc_jax.tuning.algorithms import loss as tuning_loss
from wbc_jax.tuning.algorithms.baselines import NOT_SEARCH
from wbc_jax.tuning.config import NOT_TRAINING, TuneConfig, config_key

ROOT = pathlib.Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("rekey", ROOT / "experiments" / "campaigns" / "rekey_checkpoints.py")
rekey = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(rekey)


def test_rekey_matches_the_moved_config_key(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    old, new = pathlib.Path("old_gains.json"), pathlib.Path("assets_gains.json")
    for p in (old, new):
        p.write_text('{"kp_com": 1.0}')
    tc_old, tc_new, lc = TuneConfig(init_gains=str(old)), TuneConfig(init_gains=str(new)), tuning_loss.LossConfig()
    run = tmp_path / "run"
    (run / "cmaes").mkdir(parents=True)
    # config.json as the tuning job writes it (tuning/orchestration/campaign.py: flat_dict of each config)
    (run / "config.json").write_text(
        json.dumps({"tune": flat_dict(tc_old), "loss": dataclasses.asdict(lc)}, default=io.jsonable)
    )
    record = {"kind": "tune", "fingerprint": {"config": {"tune": {"init_gains": f"sha256:{provenance.sha256(new)}"}}}}
    (run / runs.MANIFEST).write_text(json.dumps(record))
    train_old = config_key(tc_old, lc, exclude=NOT_TRAINING)
    search_old = config_key(tc_old, exclude=NOT_SEARCH)
    ckpt = run / "cmaes" / "checkpoint.npz"
    io.atomic_save_npz(ckpt, key=np.asarray(f"{train_old}-9c9af26c-cmaes-{search_old}"), step=np.asarray(3))
    runs.record_output(ckpt)

    assert rekey.main([str(run), "--init-gains", str(new)]) == 0
    with np.load(ckpt) as z:
        assert str(z["key"]) == (
            f"{config_key(tc_new, lc, exclude=NOT_TRAINING)}-9c9af26c-cmaes-{config_key(tc_new, exclude=NOT_SEARCH)}"
        )
        assert int(z["step"]) == 3
    assert runs.output_changed(ckpt) is None  # still the run's own
    assert rekey.main([str(run), "--init-gains", str(new)]) == 1  # already re-keyed: refused, unchanged
    new.write_text('{"kp_com": 2.0}')
    with pytest.raises(ValueError, match="differs from the content the run recorded"):
        rekey.rekey(run, str(new))
