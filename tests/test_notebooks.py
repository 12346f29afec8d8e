"""Every notebook under notebooks/ runs top to bottom within its time budget, and is committed without outputs."""

import os
import pathlib
import time

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")

NOTEBOOKS = sorted((pathlib.Path(__file__).resolve().parent.parent / "notebooks").glob("*.ipynb"))
# Issue target: a notebook runs in 90 s on a 2-core CPU (C MuJoCo forward runs, tiny sizes); the budget leaves room
# for a machine busy with other tests. A notebook over it fails: it got slower, or too big for a laptop.
NOTEBOOK_TIMEOUT_S = 150
# Notebook 04 with RUN_TUNING (its environment switch below) compiles a reverse-mode program through the whole closed
# loop (MJX physics + controller) and two forward ones (CMA-ES's population, the held-out pushes): 335 s alone on the
# 2-core CPU, at any size. That run is over the default suite's time: the nightly command runs it (`python3 -m pytest
# -m slow`, docs/usage.md), as it does tests/test_tune.py's closed-loop gradient check.
VARIANTS = {"04_gain_tuning.ipynb": ("run_tuning", {"WBC_JAX_NB_RUN_TUNING": "1"}, 900)}
# Notebooks the nightly set runs, for CI's 8 minutes: what they show, the default suite checks in tests of its own
# (the dynamics terms against C MuJoCo and Pinocchio: tests/test_dynamics.py; balancing: tests/test_controller.py and
# tests/test_rollout.py; the push sweep: tests/test_sweep.py). Notebook 04 runs in both sets.
NIGHTLY_ONLY = {"01_dynamics.ipynb", "02_balancing.ipynb", "03_push_recovery.ipynb"}
MARGIN_S = 30  # past the budget, pytest-timeout stops a hung run (the assertion below reports a slow one)


def _runs() -> list:
    """(path, environment, budget) per notebook run: each notebook as committed, and its slow variant if any."""
    runs = [
        pytest.param(
            p,
            {},
            NOTEBOOK_TIMEOUT_S,
            id=p.stem,
            marks=[pytest.mark.timeout(NOTEBOOK_TIMEOUT_S + MARGIN_S)]
            + ([pytest.mark.slow] if p.name in NIGHTLY_ONLY else []),
        )
        for p in NOTEBOOKS
    ]
    for p in NOTEBOOKS:
        if p.name in VARIANTS:
            name, env, budget = VARIANTS[p.name]
            marks = [pytest.mark.timeout(budget + MARGIN_S), pytest.mark.slow]
            runs.append(pytest.param(p, env, budget, id=f"{p.stem}-{name}", marks=marks))
    return runs


def test_there_are_notebooks():
    names = {p.name for p in NOTEBOOKS}
    expected = {"01_dynamics.ipynb", "02_balancing.ipynb", "03_push_recovery.ipynb", "04_gain_tuning.ipynb"}
    assert expected <= names, names
    assert set(VARIANTS) <= names, f"variants of notebooks that do not exist: {set(VARIANTS) - names}"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_committed_without_outputs(path):
    nb = nbformat.read(path, as_version=4)
    dirty = [
        i for i, c in enumerate(nb.cells) if c.cell_type == "code" and (c.outputs or c.execution_count is not None)
    ]
    assert not dirty, f"{path.name}: cells {dirty} have outputs; clear them before committing"


@pytest.mark.parametrize(("path", "env", "budget"), _runs())
def test_notebook_runs(path, env, budget, tmp_path, monkeypatch):
    nb = nbformat.read(path, as_version=4)
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    # The kernel inherits this environment: CPU, and temporary outputs under tmp_path.
    monkeypatch.setenv("JAX_PLATFORMS", "cpu")
    monkeypatch.setenv("TMPDIR", str(tmp_path))
    monkeypatch.setenv("MPLBACKEND", "module://matplotlib_inline.backend_inline")
    client = nbclient.NotebookClient(
        nb,
        timeout=budget,
        kernel_name="python3",  # per cell; the whole notebook is checked below
        resources={"metadata": {"path": str(path.parent)}},  # cwd: relative paths as in Jupyter
    )
    start = time.perf_counter()
    client.execute()  # raises CellExecutionError, naming the cell, on any error
    elapsed = time.perf_counter() - start
    print(f"{path.name}: {elapsed:.0f} s (budget {budget} s)")
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs if o.output_type == "error"]
    assert not errors
    images = sum("image/png" in o.get("data", {}) for c in nb.cells if c.cell_type == "code" for o in c.outputs)
    assert images >= 1, f"{path.name} shows no plot"
    assert os.listdir(tmp_path) or path.name != "03_push_recovery.ipynb"  # the sweep wrote to TMPDIR
    assert elapsed <= budget, f"{path.name} ran {elapsed:.0f} s, over its budget of {budget} s"
