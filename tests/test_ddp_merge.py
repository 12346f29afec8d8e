"""experiments/acceptance/ddp_merge.py: crocoddyl cross-check files of one optimiser run in parallel merge into
one (issue 43): the union of the directions, the wall times summed beside the parts that ran them, the witnesses
merged; another setting, a direction or witness of other content, or a file of another kind is refused in one
line naming the file and the field, and nothing is written."""

import json

import numpy as np
import pytest
from conftest import load_script

from wbc_jax.jobs import limit_ddp

WHAT = "crocoddyl BoxFDDP ... (synthetic)"


def _ddp_file(path, azimuths, *, wall_s, cores, witness=None, **config):
    """A file as ddp_limit.py writes it, for ``azimuths`` (limit 10 + azimuth / 90 N s each)."""
    cfg = {k: getattr(limit_ddp.DdpConfig(), k) for k in limit_ddp.DdpConfig.__dataclass_fields__}
    cfg.pop("robot")  # written before the field existed: its default
    cfg.update(directions=list(azimuths), body="chest", cop_scale=0.8, tests=3, **config)
    rows = {
        str(a): {"limit_ns": 10.0 + a / 90, "bracket_ns": [10.0 + a / 90, 12.0], "tests": [{"impulse_ns": 10.0}]}
        for a in azimuths
    }
    label = f"CPU, {cores} cores (cpu)"
    doc = {
        "what": WHAT,
        "commands": [f"python experiments/acceptance/ddp_limit.py --directions {' '.join(map(str, azimuths))}"],
        "config": cfg,
        "directions": rows,
        "wall_s": wall_s,
        "provenance": {
            "command": "x",
            "device": {"label": label},
            "inputs": {"gains": {"path": "experiments/gains/tuned_gradient.json", "sha256": "ab" * 32}},
        },
    }
    path.write_text(json.dumps(doc))
    if witness is not None:
        np.savez_compressed(limit_ddp.witness_path(path), **witness)
    return path


@pytest.fixture
def files(tmp_path):
    merge = load_script("experiments/acceptance/ddp_merge.py")
    torques = np.arange(6.0).reshape(2, 3)
    into = _ddp_file(tmp_path / "ddp.json", [0.0], wall_s=100.0, cores=2, witness={"0.0:10.0": torques})
    a = _ddp_file(tmp_path / "a.json", [90.0], wall_s=10.0, cores=64, witness={"90.0:11.0": torques + 1})
    b = _ddp_file(tmp_path / "b.json", [180.0, 0.0], wall_s=12.0, cores=64, witness={"0.0:10.0": torques})
    return merge, into, a, b, torques


def test_merge_unions_directions_sums_wall_time_beside_the_parts(files):
    merge, into, a, b, torques = files
    merge.main(["--into", str(into), str(a), str(b)])
    doc = json.loads(into.read_text())
    assert list(doc["directions"]) == ["0.0", "90.0", "180.0"]
    assert doc["directions"]["180.0"]["limit_ns"] == 12.0
    assert doc["config"]["directions"] == [0.0, 90.0, 180.0] and doc["config"]["robot"] == "icub"
    assert len(doc["commands"]) == 3 and "--directions 180.0 0.0" in doc["commands"][2]
    assert doc["wall_s"] == 122.0
    parts = [(p["file"], p["wall_s"], p["device"]) for p in doc["parts"]]
    big = "CPU, 64 cores (cpu)"
    assert parts == [("ddp.json", 100.0, "CPU, 2 cores (cpu)"), ("a.json", 10.0, big), ("b.json", 12.0, big)]
    assert all(p["provenance"]["command"] == "x" for p in doc["parts"])
    assert doc["provenance"]["inputs"]["gains"]["sha256"] == "ab" * 32
    assert "ddp_merge.py --into" in doc["provenance"]["command"]
    with np.load(limit_ddp.witness_path(into)) as w:
        assert sorted(w.files) == ["0.0:10.0", "90.0:11.0"]
        np.testing.assert_array_equal(w["90.0:11.0"], torques + 1)
    merge.main(["--into", str(into), str(a)])  # already merged: nothing added, the time not counted twice
    again = json.loads(into.read_text())
    assert again["wall_s"] == 122.0 and len(again["parts"]) == 3 and again["directions"] == doc["directions"]


def _edit(path, edit):
    doc = json.loads(path.read_text())
    edit(doc)
    path.write_text(json.dumps(doc))


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda d: d["config"].update(cop_scale=0.7), r"a\.json: config\.cop_scale is 0\.7, .*ddp\.json has 0\.8"),
        (lambda d: d["config"].update(robot="talos"), r"a\.json: config\.robot is 'talos', .*ddp\.json has 'icub'"),
        (lambda d: d["config"].update(tests=4), r"a\.json: config\.tests is 4, .* only config\.directions may differ"),
        (
            lambda d: d["directions"].update({"0.0": {**d["directions"]["90.0"], "limit_ns": 9.0}}),
            r"a\.json: directions\.0\.0\.limit_ns differs from .*ddp\.json's",
        ),
        (lambda d: d.update(what="another optimiser"), r"a\.json: field 'what' differs"),
        (lambda d: d.pop("config"), r"a\.json: not a crocoddyl cross-check file \(no field 'config'"),
        (
            lambda d: d["provenance"]["inputs"]["gains"].update(sha256="cd" * 32),
            r"a\.json: provenance\.inputs\.gains has sha256 cdcdcdcdcdcd\.\.\., another part ababababab",
        ),
    ],
    ids=["config", "robot", "tests", "direction", "what", "kind", "gains"],
)
def test_merge_refuses_another_setting_or_content_and_writes_nothing(files, edit, message, capsys):
    merge, into, a, b, _ = files
    _edit(a, edit)
    before = into.read_bytes(), limit_ddp.witness_path(into).read_bytes()
    with pytest.raises(SystemExit, match=message) as err:
        merge.main(["--into", str(into), str(b), str(a)])
    assert "\n" not in str(err.value)
    assert (into.read_bytes(), limit_ddp.witness_path(into).read_bytes()) == before


def test_merge_refuses_a_witness_of_other_torques(files):
    merge, into, a, b, torques = files
    np.savez_compressed(limit_ddp.witness_path(b), **{"0.0:10.0": torques * 2})
    with pytest.raises(SystemExit, match=r"b_witness\.npz: witness 0\.0:10\.0 holds other torques than .*ddp_witness"):
        merge.main(["--into", str(into), str(a), str(b)])
    assert "parts" not in json.loads(into.read_text())
    with pytest.raises(SystemExit, match=r"ddp\.json: is --into itself"):
        merge.main(["--into", str(into), str(into)])


def test_merge_into_a_new_file_takes_the_first_source_as_its_setting(files, tmp_path):
    merge, _, a, b, _ = files
    new = tmp_path / "new.json"
    merge.main(["--into", str(new), str(b), str(a)])
    doc = json.loads(new.read_text())
    assert list(doc["directions"]) == ["0.0", "90.0", "180.0"] and doc["wall_s"] == 22.0
    assert [p["file"] for p in doc["parts"]] == ["b.json", "a.json"]
