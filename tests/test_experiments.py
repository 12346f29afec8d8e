"""experiments/ (experiments/README.md): every script there is listed in the README's index, and none edits
sys.path (the scripts run against the installed package)."""

import pathlib
import re

import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
SCRIPTS = sorted(p for p in (ROOT / "experiments").rglob("*") if p.suffix in (".py", ".sh"))
SYS_PATH_EDIT = re.compile(r"sys\.path\s*(\.\s*(insert|append|extend)\s*\(|\[[^\]]*\]\s*=|\+=|=)")


@pytest.mark.parametrize("path", SCRIPTS, ids=lambda p: p.relative_to(ROOT / "experiments").as_posix())
def test_script_is_in_the_index(path):
    index = (ROOT / "experiments" / "README.md").read_text()
    assert f"`{path.relative_to(ROOT / 'experiments').as_posix()}`" in index, "not listed in experiments/README.md"


@pytest.mark.parametrize("path", [*SCRIPTS, *sorted((ROOT / "benchmarks").glob("*.py"))], ids=lambda p: p.name)
def test_script_does_not_edit_sys_path(path):
    assert not SYS_PATH_EDIT.search(path.read_text()), f"{path.relative_to(ROOT)} edits sys.path"


def test_the_sys_path_pattern_catches_edits():
    for edit in ("sys.path.insert(0, str(ROOT))", "sys.path.append(p)", "sys.path[:0] = [p]", "sys.path += [p]"):
        assert SYS_PATH_EDIT.search(edit), edit
    assert not SYS_PATH_EDIT.search("Python puts it first on sys.path when the script runs")
