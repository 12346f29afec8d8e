"""Shared fixtures. Tests run in float64 on the CPU (x64 is never switched on at import)."""

import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")
if os.environ["JAX_PLATFORMS"] == "cpu":
    # Compile-time flags only (XLA's own optimisation level; the values agree to rounding, within every tolerance):
    # compiling is most of the suite's time, and the C MuJoCo closed loop compiled in 31 CPU s with them against
    # 42 without on the 2-core machine. Subprocesses inherit them (tests/test_distributed.py uses the same).
    _FAST_COMPILE = "--xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true"
    os.environ["XLA_FLAGS"] = f"{_FAST_COMPILE} {os.environ.get('XLA_FLAGS', '')}".strip()

import jax

jax.config.update("jax_enable_x64", True)
# One on-disk compilation cache for the session's workers and subprocesses: modules that build the
# same program (a closed loop of the same shape) compile it once. Keyed by the program's hash.
_CACHE = os.environ.setdefault("WBC_JAX_CACHE", os.path.join(os.path.expanduser("~"), ".cache", "wbc_jax", "test-xla"))
os.makedirs(_CACHE, exist_ok=True)
jax.config.update("jax_compilation_cache_dir", _CACHE)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)

import mujoco  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from mujoco import mjx  # noqa: E402

from wbc_jax.robot import model  # noqa: E402


def pytest_configure(config):
    config.addinivalue_line("markers", "gpu: needs a GPU (skipped on the CPU); `.ci/nightly gpu` runs them on one")
    config.addinivalue_line("markers", "slow: over the default suite's time; `.ci/nightly` runs it (`pytest -m slow`)")


# pytest-xdist (`-n 2 --dist loadgroup`, pyproject's addopts): each test module is one unit of work,
# so module-scoped fixtures (compiled programs) are built once; each notebook is a unit of its own.
# Units start longest first, so that the two workers finish together (xdist hands each worker the next unit when it
# has fewer than two). The default suite's order: CPU seconds per unit, measured one module at a time on the 2-core
# machine with a cold compilation cache (the ci branch, 2026-11-26): test_rollout 82 (it compiles the 1 s stand loop
# first: test_baseline_cpu, test_tune and test_wheel start later and load it), test_viz 79, test_forces 74,
# test_contacts 58, test_limit 44, test_hierarchy 36, test_reliability_paths 31, test_baseline_cpu 55 (25 with the
# loop loaded), test_controller 27, test_tune 23 (the loop loaded), test_race 17. test_reliability_runs compiles the
# short sweep that test_cli's resume test then loads. The MJX modules were measured only by wall time on the loaded
# machine (test_mjx_physics the longest): its 256-environment subprocess is a unit of its own (_OWN_UNITS).
# The ci56 branch (2026-11-27, two workers, wall seconds per unit in the suite): test_rollout 100, test_forces 78,
# test_viz 57, test_limit 35, test_sweep 33, test_hierarchy 32, test_tune 32, test_reliability_paths 28,
# test_mjx_physics ~25 (its iCub gradient, 117, is nightly now), test_contacts 23 (its compiled ticks nightly), the
# 256 environments 21, test_tune_devices 20, test_profile_tick 16. Units not listed start last, in file order
# (test_profile_tick, test_tune_devices and test_qp_slowest, 39 s together, were among them). 2026-11-27 (s59):
# test_viz's sweep and replay (109 s) went nightly; its balance run loads the shared loop (14 s), so it starts late,
# as test_wheel does, when test_rollout has compiled that loop.
_LONGEST_FIRST = [
    "test_rollout",
    "test_forces",
    "test_reliability_runs",
    "test_limit",
    "test_sweep",
    "test_hierarchy",
    "test_reliability_paths",
    "test_mjx_physics",
    "test_contacts",
    "test_vmapped_rollout_of_256_envs_completes_on_cpu",
    "test_baseline_cpu",
    "test_profile_tick",
    "test_tune_devices",
    "test_cli",
    "test_controller",
    "test_tune",
    "test_dynamics",
    "test_wheel",
    "test_viz",
    "test_race",
    "test_qp_slowest",
    "04_gain_tuning",
    "test_tsid_baseline",
    "test_watchdog",
    "test_distributed",
]
# `-m slow` (the nightly set): the race's end-to-end runs start first (_OWN_UNITS_FIRST), then test_tune's closed-loop
# gradient check and notebook 04's pipeline, then the modules whose slow tests compile MJX loops.
_LONGEST_FIRST_SLOW = [
    "test_tune",
    "04_gain_tuning-run_tuning",
    "test_distributed",
    "test_rollout",
    "test_contacts",
    "test_viz",
    "test_dynamics",
    "test_forces",
    "test_controller",
    "test_sweep",
    "test_mjx_physics",
    "02_balancing",
    "03_push_recovery",
    "test_cli",
    "test_baseline_cpu",
    "01_dynamics",
]


# Slow tests that share no module fixture and each take 20+ minutes on the loaded 2-core machine (a whole `tune` race
# in a subprocess): each parametrisation is a unit of its own and they start first, side by side on the two workers,
# so that `.ci/nightly slow` does not end with them run one after the other on one worker.
_OWN_UNITS_FIRST = ["test_race_pipeline_end_to_end"]
# Tests of the default suite that share no module fixture with their module and take a large part of it: a unit of
# their own, placed by _LONGEST_FIRST.
_OWN_UNITS = ["test_vmapped_rollout_of_256_envs_completes_on_cpu"]


def _work_unit(item) -> str:
    module = item.module.__name__.rsplit(".", 1)[-1]
    if module == "test_notebooks" and hasattr(item, "callspec"):
        return item.callspec.id  # the notebook's name
    if getattr(item, "originalname", "") in _OWN_UNITS_FIRST + _OWN_UNITS:
        return item.name  # the test with its parameters' id
    return module


def _is_slow_set(config) -> bool:
    """`-m slow` (the nightly set) rather than the default `-m 'not slow'`."""
    expression = config.option.markexpr or ""
    return "slow" in expression and "not slow" not in expression


@pytest.hookimpl(tryfirst=True)  # before xdist's own hook reads the xdist_group marks
def pytest_collection_modifyitems(config, items):
    for item in items:
        item.add_marker(pytest.mark.xdist_group(_work_unit(item)))
    order = _LONGEST_FIRST_SLOW if _is_slow_set(config) else _LONGEST_FIRST
    rank = {name: k for k, name in enumerate(order)}
    rank.update({name: k - len(_OWN_UNITS_FIRST) for k, name in enumerate(_OWN_UNITS_FIRST)})

    def _rank(item) -> int:
        return rank.get(getattr(item, "originalname", ""), rank.get(_work_unit(item), len(rank)))

    items.sort(key=_rank)  # stable: file order otherwise
    if any(d.platform == "gpu" for d in jax.devices()):
        return
    skip = pytest.mark.skip(reason="needs a GPU")
    for item in items:
        if "gpu" in item.keywords:
            item.add_marker(skip)


# `balance --duration 1 --backend mujoco` is the closed loop of tests/test_rollout.py and tests/test_baseline_cpu.py
# (1 s stand on C MuJoCo, the same structure key and shapes): the session compiles it once (30 CPU s) and the balance
# runs of tests/test_tune.py, tests/test_wheel.py and tests/test_viz.py load it (2 CPU s); gains and pushes are
# arguments, not part of the program.
SHARED_BALANCE = ["balance", "--duration", "1.0", "--backend", "mujoco"]


@pytest.fixture(scope="session")
def robot() -> model.Robot:
    return model.load_robot("icub")


@pytest.fixture(scope="session")
def mx(robot) -> mjx.Model:
    return robot.mjx_model


def random_state(robot: model.Robot, seed: int, joint_scale: float = 0.3):
    """A non-trivial state: random base orientation and velocity, joints around home."""
    rng = np.random.default_rng(seed)
    m = robot.mj_model
    qpos = robot.home_qpos()
    q = rng.normal(size=4)
    qpos[3:7] = q / np.linalg.norm(q)
    qpos[:3] += rng.normal(scale=0.1, size=3)
    qpos[robot.index.qpos_joints] += rng.uniform(-joint_scale, joint_scale, robot.index.n)
    qvel = rng.normal(size=m.nv)
    return qpos, qvel


def moving_terms(robot: model.Robot, batch: int, seed: int = 0):
    """(DynamicsTerms batched over ``batch`` moving states near the standing posture: joint offsets of 0.1 rad,
    velocities of 0.3 (float32, MJX-JAX at the loop's matmul precision), the rng for more of the test's data)."""
    from wbc_jax.core import mjx as mjx_device
    from wbc_jax.robot import dynamics

    idx = robot.index
    rng = np.random.default_rng(seed)
    qpos = np.tile(robot.home_qpos(), (batch, 1)).astype(np.float32)
    qpos[:, idx.qpos_joints] += rng.normal(0.0, 0.1, (batch, len(idx.qpos_joints)))
    qvel = rng.normal(0.0, 0.3, (batch, idx.nv)).astype(np.float32)
    mx, d0 = mjx_device.put_model(robot.mj_model), mjx_device.make_data(robot.mj_model)
    with jax.default_matmul_precision("highest"):
        t = jax.jit(jax.vmap(lambda q, v: dynamics.terms(mx, d0.replace(qpos=q, qvel=v), idx)))(qpos, qvel)
    return t, rng


def assert_close(actual, expected, name: str, rtol: float, atol: float = 0.0):
    np.testing.assert_allclose(np.asarray(actual), np.asarray(expected), rtol=rtol, atol=atol, err_msg=name)


def stepping_inputs(rng, k: int, m: mujoco.MjModel, batch: int, n_sub: int, chest: int):
    """Tick ``k``'s (ctrl (B, nu), xfrc (B, n_sub, nbody, 6)) of the native-step tests (B >= 3): random
    torques, a chest push that changes inside the tick, env 2 blown up at tick 20 (restored and flagged
    after stepping), env 1 given a NaN torque at tick 25 (flagged before stepping)."""
    ctrl = rng.normal(scale=5.0, size=(batch, m.nu))
    xfrc = np.zeros((batch, n_sub, m.nbody, 6))
    xfrc[:, 3:, chest, 1] = 40.0 * (k % 2)
    if k == 20:
        xfrc[2, :, chest, 0] = 1e12
    if k == 25:
        ctrl[1, 4] = np.nan
    return ctrl, xfrc


def c_data(robot, qpos, qvel) -> mujoco.MjData:
    d = mujoco.MjData(robot.mj_model)
    d.qpos[:], d.qvel[:] = qpos, qvel
    mujoco.mj_forward(robot.mj_model, d)
    return d


class _ScriptSiblings:
    """Imports a loaded script's sibling module (``from loop_timing import ...`` in benchmarks/) as running the
    script does, where Python puts the script's folder first on sys.path: the sibling is itself loaded by
    load_script, so a test and the script share one module object. Last on sys.meta_path: installed names win."""

    folders: set = set()

    @classmethod
    def find_spec(cls, name, path=None, target=None):
        import importlib.machinery
        import pathlib

        if path is not None or "." in name:
            return None
        root = pathlib.Path(__file__).resolve().parent.parent
        for folder in sorted(cls.folders):
            if (root / folder / f"{name}.py").is_file():
                return importlib.machinery.ModuleSpec(name, cls(f"{folder}/{name}.py"))
        return None

    def __init__(self, relative: str):
        self.relative = relative

    def create_module(self, spec):
        return load_script(self.relative)

    def exec_module(self, module):
        pass  # load_script ran it


def load_script(relative: str):
    """A script of the repository (experiments/, benchmarks/: not a package) loaded from its file, once; its
    sibling modules import as they do when it runs (_ScriptSiblings)."""
    import importlib.util
    import pathlib
    import sys

    if _ScriptSiblings not in sys.meta_path:
        sys.meta_path.append(_ScriptSiblings)
    _ScriptSiblings.folders.add(str(pathlib.PurePosixPath(relative).parent))
    key = "script_" + relative.replace("/", "_").removesuffix(".py")
    if key not in sys.modules:
        spec = importlib.util.spec_from_file_location(key, pathlib.Path(__file__).resolve().parent.parent / relative)
        module = importlib.util.module_from_spec(spec)
        sys.modules[key] = module
        spec.loader.exec_module(module)
    return sys.modules[key]


def refused_in_one_line(main, argv: list[str], capsys) -> str:
    """Run a script's ``main(argv)``, which must refuse it as argparse does (exit status 2) with
    exactly one ``error:`` line on stderr; returns that line."""
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    errors = [line for line in capsys.readouterr().err.splitlines() if "error:" in line]
    assert len(errors) == 1, errors
    return errors[0]
