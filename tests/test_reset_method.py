"""experiments/campaigns/reset_method.py: a method's sets leave a tuning run (files, provenance entries, recorded
outputs), the other methods' stay byte for byte; a folder without the method, or another kind of run, is refused."""

import importlib.util
import json
import pathlib

import pytest

from wbc_jax.jobs import runs

ROOT = pathlib.Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("reset_method", ROOT / "experiments" / "campaigns" / "reset_method.py")
reset_method = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(reset_method)


def _run(tmp_path, kind="tune"):
    run = tmp_path / "run"
    (run / "gains").mkdir(parents=True)
    (run / runs.MANIFEST).write_text(json.dumps({"kind": kind, "fingerprint": {}, "outputs": {}}))
    index = {}
    for name in ("cmaes_t60", "cmaes", "hybrid_t120", "hybrid", "hybrid_extra"):
        (run / "gains" / f"{name}.json").write_text(json.dumps({"name": name}))
        index[name] = {"sha256": name}
    (run / "gains" / "provenance.json").write_text(json.dumps(index))
    for method in ("hybrid", "cmaes"):
        (run / method / "t120").mkdir(parents=True)
        part = run / method / "t120" / "history.csv"
        part.write_text("step,loss\n0,1.0\n")
        runs.record_output(part)
    return run


def test_reset_removes_only_the_method(tmp_path, capsys):
    run = _run(tmp_path)
    before = {p: p.read_bytes() for p in (run / "cmaes").rglob("*") if p.is_file()}
    assert reset_method.main([str(run), "--method", "hybrid"]) == 0
    assert sorted(p.name for p in (run / "gains").iterdir()) == [
        "cmaes.json",
        "cmaes_t60.json",
        "hybrid_extra.json",
        "provenance.json",
    ]
    assert sorted(json.loads((run / "gains" / "provenance.json").read_text())) == ["cmaes", "cmaes_t60", "hybrid_extra"]
    assert not (run / "hybrid").exists()
    assert list(json.loads((run / runs.MANIFEST).read_text())["outputs"]) == ["cmaes/t120/history.csv"]
    assert {p: p.read_bytes() for p in (run / "cmaes").rglob("*") if p.is_file()} == before
    assert "sets hybrid, hybrid_t120" in capsys.readouterr().out
    # nothing of the method left: refused, in one line
    assert reset_method.main([str(run), "--method", "hybrid"]) == 1
    assert capsys.readouterr().err.strip().endswith("holds no results of hybrid")


def test_reset_dry_run_and_refusals(tmp_path, capsys):
    run = _run(tmp_path)
    listing = sorted(str(p) for p in run.rglob("*"))
    assert reset_method.main([str(run), "--method", "hybrid", "--dry-run"]) == 0
    assert sorted(str(p) for p in run.rglob("*")) == listing
    with pytest.raises(ValueError, match="not a race method; valid: gradient, cmaes, random, hybrid"):
        reset_method.reset(run, "hybrids")
    other = _run(tmp_path / "x", kind="push-sweep")
    with pytest.raises(ValueError, match="not a tuning run"):
        reset_method.reset(other, "hybrid")
