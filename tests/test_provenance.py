"""Results name their inputs (wbc_jax.core.provenance): every result JSON of results/ that names a gains file of the
repository records its sha256, and the file still has it; every gains file is in experiments/gains/index.json, exists,
parses and has the sha256 listed there. JSON only: no JAX."""

import json
import math
import pathlib

import pytest

from wbc_jax.core import constants, io, loader, provenance
from wbc_jax.robot.icub import DESCRIPTION as ICUB
from wbc_jax.robot.robots import DESCRIPTIONS

ROOT = pathlib.Path(__file__).resolve().parent.parent
INDEX = ROOT / "experiments" / "gains" / "index.json"
RESULTS = sorted(p for p in (ROOT / "results").rglob("*.json") if "runs" not in p.parts)
STATUSES = ("current", "record")


def gains_problems(path: pathlib.Path, root: pathlib.Path = ROOT) -> list[str]:
    """What is wrong with a result of results/ as a record of its gains files (empty: nothing)."""
    result = json.loads(path.read_text())
    problems = provenance.check_inputs(result, root) if isinstance(result, dict) else []
    recorded = {}
    if isinstance(result, dict):
        # A run's gains/provenance.json (tuning/store.py) records each set's inputs in that set's own provenance.
        records = [result] if "provenance" in result else [e for e in result.values() if isinstance(e, dict)]
        recorded = {
            provenance.current_path(e["path"]): e["sha256"]
            for r in records
            for e in ((r.get("provenance") or {}).get("inputs") or {}).values()
        }
    for name in sorted(provenance.mentioned_files(result)):
        if loader.is_gains_file(root / name) and name not in recorded:
            problems.append(f"names the gains file {name} without its sha256 (provenance.inputs)")
    return problems


@pytest.mark.parametrize("path", RESULTS, ids=lambda p: p.relative_to(ROOT / "results").as_posix())
def test_result_records_the_gains_it_names_and_they_are_unchanged(path):
    problems = gains_problems(path)
    assert not problems, f"{path.relative_to(ROOT)}: " + "; ".join(problems)


def test_a_result_whose_gains_file_changed_or_is_unrecorded_fails(tmp_path):
    """The check bites: an overwritten gains file, a gains file named without its sha256, a missing one."""
    gains = {k: v.tolist() for k, v in ICUB.default_gain_values().items()}
    (tmp_path / "experiments" / "gains").mkdir(parents=True)
    (tmp_path / "results").mkdir()
    target = tmp_path / "experiments" / "gains" / "g.json"
    target.write_text(json.dumps(gains))
    record = {"inputs": {"gains": {"path": "experiments/gains/g.json", "sha256": provenance.sha256(target)}}}
    result = {"command": "wbc-jax push-sweep --gains experiments/gains/g.json", "provenance": record}
    doc = tmp_path / "results" / "r.json"
    doc.write_text(json.dumps(result))
    assert gains_problems(doc, tmp_path) == []
    target.write_text(json.dumps({**gains, "kp_com": [1.0, 1.0, 1.0]}))  # overwritten by a later campaign
    assert len(gains_problems(doc, tmp_path)) == 1 and "has changed" in gains_problems(doc, tmp_path)[0]
    doc.write_text(json.dumps({"command": result["command"]}))  # named, not recorded
    assert len(gains_problems(doc, tmp_path)) == 1 and "without its sha256" in gains_problems(doc, tmp_path)[0]
    target.unlink()
    doc.write_text(json.dumps(result))
    assert len(gains_problems(doc, tmp_path)) == 1 and "missing" in gains_problems(doc, tmp_path)[0]


def test_inputs_outside_the_repository_are_not_checked():
    result = {
        "provenance": {
            "inputs": {
                "gains": {"path": "runs/tune/gains/gradient.json", "sha256": "0" * 64},
                "tasks": {"path": "/tmp/x.yaml", "sha256": "0" * 64},
            }
        }
    }
    assert provenance.check_inputs(result) == []
    assert not provenance.in_repository("runs/x.json") and provenance.in_repository("experiments/gains/x.json")


def test_mentioned_files_finds_relative_and_absolute_spellings():
    result = {
        "command": "python x.py --sets g=/work/main/experiments/gains/a.json c=experiments/gains/b.json.",
        "runs": ["(results/tuning/heldout.json)", "runs/experiments/c.json", "results/reliability_soak_chunks.jsonl"],
        "before_issue_44": "--out docs/limit/limit.json, as docs/limit/README.md says",  # results were under docs/
    }
    assert provenance.mentioned_files(result) == {
        "experiments/gains/a.json",
        "experiments/gains/b.json",
        "results/tuning/heldout.json",
        "results/limit/limit.json",
    }


def test_a_result_recorded_under_docs_is_read_from_results():
    """Records written before issue 44 name docs/<path>: the file now at results/<path> is the one checked."""
    assert provenance.current_path("docs/tuning/issue5/tuned_gains.json") == "results/tuning/issue5/tuned_gains.json"
    assert provenance.current_path("docs/tuning/README.md") == "docs/tuning/README.md"  # a written page stays
    assert provenance.current_path("experiments/gains/tuned_gradient.json") == "experiments/gains/tuned_gradient.json"
    gains = "results/tuning/issue5/tuned_gains.json"
    legacy = {"provenance": {"inputs": {"gains": {"path": "docs/tuning/issue5/tuned_gains.json", "sha256": ""}}}}
    legacy["provenance"]["inputs"]["gains"]["sha256"] = provenance.sha256(ROOT / gains)
    assert provenance.check_inputs(legacy) == []
    legacy["provenance"]["inputs"]["gains"]["sha256"] = "0" * 64
    assert provenance.check_inputs(legacy) == [
        f"gains: docs/tuning/issue5/tuned_gains.json has changed since (sha256 {'0' * 12}...)"
    ]
    assert provenance.spellings("--gains /work/main/docs/tuning/issue5/tuned_gains.json", gains) == {
        "/work/main/docs/tuning/issue5/tuned_gains.json"
    }


def test_record_names_its_inputs_by_sha256(tmp_path):
    f = tmp_path / "g.json"
    f.write_text("{}")
    rec = provenance.record(
        {"gains": f, "tasks": None, "gone": tmp_path / "none.json"},
        argv=[str(ROOT / "experiments" / "x.py"), "--a", "b c"],
        with_device=False,
    )
    assert rec["command"] == "python experiments/x.py --a 'b c'"  # relative to the repository, as typed again
    assert rec["inputs"] == {"gains": {"path": f.as_posix(), "sha256": provenance.sha256(f)}}
    assert provenance.script_argv("s.py", ["--x"]) == ["s.py", "--x"]


def test_write_new_json_never_overwrites_other_contents(tmp_path):
    path = tmp_path / "g.json"
    io.write_new_json(path, {"a": 1})
    io.write_new_json(path, {"a": 1})  # the same contents: nothing to do
    with pytest.raises(FileExistsError, match="never overwritten"):
        io.write_new_json(path, {"a": 2})
    assert json.loads(path.read_text()) == {"a": 1}


# ---------------------------------------------------------------------------------------------
# The index of gain sets


def _index() -> dict:
    return json.loads(INDEX.read_text())


def _repository_gains_files() -> set[str]:
    return {
        provenance.display_path(p)
        for folder in ("experiments", "results", "assets")
        for p in (ROOT / folder).rglob("*.json")
        if loader.is_gains_file(p)
    }


def test_every_gains_file_is_indexed_and_every_indexed_one_is_there():
    listed = set(_index()["files"])
    assert _repository_gains_files() == listed, (
        f"not in experiments/gains/index.json: {sorted(_repository_gains_files() - listed)}; "
        f"listed but not a gains file: {sorted(listed - _repository_gains_files())}"
    )


@pytest.mark.parametrize("name", sorted(json.loads(INDEX.read_text())["files"]))
def test_indexed_gains_file_parses_and_is_unchanged(name):
    entry = _index()["files"][name]
    values = json.loads((ROOT / name).read_text())
    # A robot's own files lie in assets/<robot>/ (Talos's); every other gains file is the iCub's.
    folder = pathlib.PurePosixPath(name).parts[1]
    n = len((DESCRIPTIONS[folder] if folder in DESCRIPTIONS else ICUB).gains.kp_postural)
    for k in constants.GAIN_FIELDS:
        assert len(values[k]) == (n if k.endswith("postural") else 3), (name, k)
        assert all(math.isfinite(v) and (v > 0 or (k in constants.NON_NEGATIVE_GAINS and v == 0)) for v in values[k])
    assert entry["status"] in STATUSES, (name, entry["status"])
    assert provenance.sha256(ROOT / name) == entry["sha256"], f"{name} differs from its sha256 in index.json"
    assert (ROOT / entry["results"]).exists(), (name, entry["results"])


def test_the_sets_to_use_are_current():
    index = _index()
    for purpose, name in index["use"].items():
        assert name is None or index["files"][name]["status"] == "current", purpose
