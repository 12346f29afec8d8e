"""`pip install .` works outside the checkout (issue 41): the wheel holds every module, the robot model and the
default files the jobs read; installed where the checkout cannot shadow it, `wbc-jax info` and a short `balance` run
from another folder and write nothing into the installed package (the native step and the compiled programs go to
the user's cache, here the test session's WBC_JAX_CACHE)."""

import hashlib
import json
import os
import pathlib
import shutil
import subprocess
import sys
import zipfile

import pytest
from conftest import SHARED_BALANCE

from wbc_jax.core import provenance
from wbc_jax.core.assets import ASSETS
from wbc_jax.robot.robots import DESCRIPTIONS

ROOT = pathlib.Path(__file__).resolve().parent.parent
# What the build reads: the pyproject's packages, package-dir (assets/) and readme.
BUILD_INPUTS = ("pyproject.toml", "README.md", "wbc_jax", "assets")
PIP = [sys.executable, "-m", "pip", "--disable-pip-version-check", "--no-input"]


def _run(cmd, **kw) -> subprocess.CompletedProcess:
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=900, **kw)
    assert proc.returncode == 0, f"{' '.join(map(str, cmd))} failed:\n{proc.stdout[-2000:]}\n{proc.stderr[-3000:]}"
    return proc


def _files(folder: pathlib.Path) -> dict[str, str]:
    """{relative path: sha256} of the files under a folder, bytecode caches left out."""
    return {
        p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and "__pycache__" not in p.parts
    }


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> pathlib.Path:
    """The wheel built from a copy of the build's inputs (the build leaves nothing in the checkout)."""
    tmp = tmp_path_factory.mktemp("wheel")
    src = tmp / "src"
    src.mkdir()
    for name in BUILD_INPUTS:
        if (ROOT / name).is_dir():
            shutil.copytree(ROOT / name, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
        else:
            shutil.copy2(ROOT / name, src / name)
    _run([*PIP, "wheel", "--no-deps", "--no-build-isolation", "--no-index", "-q", "-w", str(tmp / "dist"), str(src)])
    (built,) = (tmp / "dist").glob("wbc_jax-*.whl")
    return built


@pytest.fixture(scope="module")
def installed(wheel, tmp_path_factory) -> dict:
    """The wheel installed into its own folder (``pip install --target``), the environment that imports it
    and not the checkout (PYTHONPATH is that folder alone; the editable install's finder comes after it),
    and an empty working folder outside the checkout."""
    tmp = tmp_path_factory.mktemp("installed")
    site = tmp / "site"
    _run([*PIP, "install", "--no-deps", "--no-index", "-q", "--target", str(site), str(wheel)])
    work = tmp / "work"
    work.mkdir()
    env = {**os.environ, "PYTHONPATH": str(site), "WBC_JAX_CACHE": os.environ["WBC_JAX_CACHE"], "JAX_ENABLE_X64": "1"}
    return {"site": site, "work": work, "env": env, "script": site / "bin" / "wbc-jax"}


def test_wheel_holds_every_module_the_model_and_the_default_files(wheel):
    with zipfile.ZipFile(wheel) as z:
        names = set(z.namelist())
        packaged = {n: hashlib.sha256(z.read(n)).hexdigest() for n in names if n.startswith("wbc_jax/assets/")}
    modules = {p.relative_to(ROOT).as_posix() for p in (ROOT / "wbc_jax").rglob("*") if p.suffix in (".py", ".cc")}
    assert not modules - names, f"modules missing from the wheel (pyproject's packages): {sorted(modules - names)}"
    # Every file the code reads by default is package data, byte for byte the checkout's.
    defaults = [d.model_path for d in DESCRIPTIONS.values()]
    defaults += [d.asset_path(f) for d in DESCRIPTIONS.values() for f in (d.hand_set_gains, d.default_envelope) if f]
    for path in defaults:
        name = f"wbc_jax/assets/{path.relative_to(ASSETS).as_posix()}"
        assert packaged.get(name) == hashlib.sha256(path.read_bytes()).hexdigest(), f"{name}: not in the wheel as is"
    assert not [n for n in names if n.lower().endswith((".stl", ".obj", ".dae"))], "meshes come from icub-models"
    assert wheel.stat().st_size < 1_000_000, f"wheel of {wheel.stat().st_size} bytes"


def test_installed_package_runs_info_and_balance_from_another_folder(installed):
    site, work, env = installed["site"], installed["work"], installed["env"]
    before = _files(site)
    # The native C MuJoCo step built from the installed source into a fresh cache folder (the user's cache in a job).
    native_cache = work.parent / "native_cache"
    where = (
        f"import json, jax, wbc_jax; jax.config.update('jax_compilation_cache_dir', {str(native_cache)!r}); "
        "from wbc_jax.core import assets, provenance; from wbc_jax.sim import native; "
        "from wbc_jax.robot.robots import describe; d = describe('icub'); g = d.asset_path(d.hand_set_gains); "
        "why_not = native.available(); "
        "record = {'provenance': provenance.record({'gains': g}, with_device=False)}; "
        "print(json.dumps([why_not, record, sorted(provenance.mentioned_files(str(g))), "
        "provenance.check_inputs(record), wbc_jax.__file__, str(assets.ASSETS), str(native.SOURCE)]))"
    )
    why_not, record, mentioned, changed, *paths = json.loads(
        _run([sys.executable, "-c", where], cwd=work, env=env).stdout
    )
    for path in map(pathlib.Path, paths):
        assert path.is_relative_to(site), f"{path} is not the installed copy under {site}"
    assert why_not is None, why_not
    assert len(list((native_cache / "wbc_native").glob("libwbc_mujoco_ffi_*.so"))) == 1
    # Results name package data as in a checkout (assets/...), and the installed copy checks against the record.
    gains = "assets/gains/com_critical_100.json"
    assert record["provenance"]["inputs"]["gains"]["path"] == gains and mentioned == [gains] and changed == []
    assert provenance.check_inputs(record) == []  # and the checkout's copy: the same file
    record["provenance"]["inputs"]["gains"]["sha256"] = "0" * 64
    assert [line.split(" since")[0] for line in provenance.check_inputs(record)] == [f"gains: {gains} has changed"]

    info = json.loads(_run([str(installed["script"]), "info"], cwd=work, env=env).stdout)
    assert (info["nq"], info["nv"], info["nu"]) == (30, 29, 23)
    assert info["mass"] == pytest.approx(33.0617, abs=1e-3)  # the iCubGazeboV2_5 model's total mass, kg

    _run([str(installed["script"]), *SHARED_BALANCE, "--no-plots", "--quiet", "--out", "bal"], cwd=work, env=env)
    metrics = json.loads((work / "bal" / "metrics.json").read_text())
    assert metrics["duration_s"] == 1.0 and metrics["host_loop"] == "compiled"  # the native C MuJoCo step built
    assert metrics["upright"] and not metrics["fell"] and not metrics["nan"]
    assert metrics["min_com_height_m"] > 0.5  # standing: the CoM starts at 0.55 m
    # The native library, the compiled programs and every log went to the cache or the run's folder.
    assert _files(site) == before, "the jobs wrote into the installed package"
