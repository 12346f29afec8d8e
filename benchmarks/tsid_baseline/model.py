"""The TSID peer's models and tasks: the packages it needs (:func:`tsid_problem`), the plant's C model
and its contacts, the copies of wbc_jax's numbers it keeps to stay JAX-free, and the task references
(:func:`make_schedule`)."""

from __future__ import annotations

import dataclasses
import importlib.util
import math
import pathlib
import sys
import warnings

import mujoco
import numpy as np

from wbc_jax.robot.robots import DEFAULT_ROBOT, describe

ROOT = pathlib.Path(__file__).resolve().parents[2]


def _load_by_path(name: str, path: pathlib.Path):
    """A module of this repository loaded from its file, or a package from its folder (``benchmarks/``
    and ``assets/`` are not packages, and ``wbc_jax`` imports JAX on import), registered in
    ``sys.modules`` once."""
    module = sys.modules.get(name)
    if module is None:
        if path.is_dir():
            spec = importlib.util.spec_from_file_location(
                name, path / "__init__.py", submodule_search_locations=[str(path)]
            )
        else:
            spec = importlib.util.spec_from_file_location(name, path)
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module  # dataclasses look their module up by name
        spec.loader.exec_module(module)
    return module


bc = _load_by_path("baseline_cpu", ROOT / "benchmarks" / "baseline_cpu")
constants = bc.constants

# The default robot's (the iCub's) names; another robot's come from its description (``--robot``).
DEFAULT = describe(DEFAULT_ROBOT)
MODEL_XML = DEFAULT.model_path
DRIVEN_JOINTS: tuple[str, ...] = DEFAULT.joints
FEET = DEFAULT.feet
FOOT_SIZE = DEFAULT.sole_cop  # the CoP rectangle (m, sole frame): robot.contacts.ContactParams().foot_size
TASKS = ("stand", "sinusoid")
# Copies of wbc_jax names (modules that import JAX), checked in tests/test_tsid_baseline.py:
FZ_MIN = 10.0  # robot.contacts.ContactParams().fz_min (N, per foot)
TASK_DURATION = {"stand": 10.0, "sinusoid": 20.0}  # control.references.make_schedule's defaults (s)
SINE_AMPLITUDE, SINE_FREQUENCY, SINE_AXIS = 0.02, 0.2, (0.0, 1.0, 0.0)  # its sinusoid (m, Hz)
FZ_MAX = 1e4  # N per foot: no WBC counterpart (TSID needs one); ~30 x the robot's weight
# TSID wheels are built against one Pinocchio: another version's Model crashes TSID's RobotWrapper
# (tsid 1.10.0 with pin 4.1.0: MemoryError or "free(): invalid pointer"). tsid -> pin version.
TSID_PINOCCHIO = {"1.10.0": "4.0.0"}


def tsid_problem() -> str | None:
    """Why TSID cannot run here (a sentence), or None. Reads package metadata only: importing a
    TSID built against another Pinocchio works, constructing its RobotWrapper crashes the process."""
    from importlib import metadata

    try:
        tsid_version = metadata.version("tsid")
    except metadata.PackageNotFoundError:
        return "tsid is not installed (python3 .ci/install_libtsid.py && pip install -e '.[dev]')"
    try:
        pin_version = metadata.version("pin")
    except metadata.PackageNotFoundError:
        return "pinocchio (pip package 'pin') is not installed"
    wanted = TSID_PINOCCHIO.get(tsid_version)
    if wanted is not None and pin_version != wanted:
        return (
            f"tsid {tsid_version} is built against Pinocchio {wanted}, found pin {pin_version} "
            f"(its RobotWrapper would crash): pip install pin=={wanted}"
        )
    return None


def import_tsid():
    """The ``tsid`` module, after :func:`tsid_problem` (raises ImportError with its sentence)."""
    problem = tsid_problem()
    if problem is not None:
        raise ImportError(problem)
    with warnings.catch_warnings():
        # Its bindings register one shared_ptr converter twice (a RuntimeWarning, harmless).
        warnings.simplefilter("ignore", RuntimeWarning)
        import tsid
    return tsid


def load_mj_model(path: pathlib.Path | str | None = None, robot: str = DEFAULT_ROBOT) -> mujoco.MjModel:
    """The C MuJoCo model as :func:`wbc_jax.robot.model.load_mj_model` (``visual=False``) compiles it: the
    MJCF without its visual mesh geoms and meshes (they never collide), no auto-reset either way.
    path: None: the robot's model file (its description's).

    Raises FileNotFoundError (missing model file)."""
    path = describe(robot).model_path if path is None else pathlib.Path(path)
    if not path.exists():
        raise FileNotFoundError(f"model file {path} is missing; regenerate it with 'python {describe(robot).builder}'")
    spec = mujoco.MjSpec.from_file(str(path))
    for geom in list(spec.geoms):
        if geom.type == mujoco.mjtGeom.mjGEOM_MESH:
            spec.delete(geom)
    for mesh in list(spec.meshes):
        spec.delete(mesh)
    return spec.compile()


def body_id(m: mujoco.MjModel, name: str) -> int:
    """Body id by name; ValueError listing the valid names."""
    i = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, name)
    if i < 0:
        valid = sorted(mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b) for b in range(1, m.nbody))
        raise ValueError(f"unknown body {name!r}; valid bodies: {valid}")
    return i


def floor_friction(m: mujoco.MjModel) -> float:
    """The sliding friction of the model's foot-floor contact pairs (one value; ValueError if they
    differ or the model has none)."""
    mu = np.unique(np.asarray(m.pair_friction)[:, 0])
    if mu.size != 1:
        raise ValueError(f"expected one floor friction over the contact pairs, got {mu.tolist()}")
    return float(mu[0])


def sole_contact_rectangle(m: mujoco.MjModel, qpos: np.ndarray | None = None, robot: str = DEFAULT_ROBOT) -> tuple:
    """The largest rectangle ((x_min, x_max), (y_min, y_max)) m, in sole-frame coordinates, inside
    the contact spheres' centres of both soles (the robot's feet: 4 spheres per sole, geoms named
    by its description's ``foot_contact_prefixes``), at qpos (nq,) (None: the nominal keyframe)."""
    desc = describe(robot)
    d = mujoco.MjData(m)
    d.qpos[:] = m.key(desc.nominal_keyframe).qpos if qpos is None else qpos
    mujoco.mj_kinematics(m, d)
    lo, hi = np.full(2, -np.inf), np.full(2, np.inf)
    for site, prefix in zip(desc.feet, desc.foot_contact_prefixes):
        s = m.site(site).id
        R, p = d.site_xmat[s].reshape(3, 3), d.site_xpos[s]
        geoms = [g for g in range(m.ngeom) if m.geom(g).name.startswith(prefix)]
        if not geoms:
            raise ValueError(f"the model has no contact geoms {prefix}*")
        local = (d.geom_xpos[geoms] - p) @ R
        lo, hi = np.maximum(lo, local[:, :2].min(0)), np.minimum(hi, local[:, :2].max(0))
    return ((float(lo[0]), float(hi[0])), (float(lo[1]), float(hi[1])))


def non_foot_bodies(m: mujoco.MjModel, feet: tuple[str, str] = FEET) -> np.ndarray:
    """Bodies that must stay off the floor (wbc_jax.sim.loop.ClosedLoop): all but the world, the soles'
    bodies (of the sole sites ``feet``) and their parents (the ankles). (k,) int."""
    feet = np.array([m.site_bodyid[m.site(s).id] for s in feet])
    excluded = set(feet.tolist()) | set(m.body_parentid[feet].tolist())
    return np.array([b for b in range(1, m.nbody) if b not in excluded])


@dataclasses.dataclass(frozen=True, eq=False)
class TaskSchedule:
    """The fields of :class:`wbc_jax.control.references.Schedule` that ``baseline_cpu.schedule_table``
    reads, for the stand and sinusoid tasks: com0 (3,), s0 (n,) (joints order), no minimum-jerk
    segments, an optional CoM sinusoid (m, Hz, world axis)."""

    name: str
    duration: float
    com0: np.ndarray
    s0: np.ndarray
    com_segments: tuple = ((), (), np.zeros((0, 3)))
    posture_segments: tuple = ((), (), None)
    activation_segments: tuple = ((), (), np.zeros((0, 2)))
    sine_amplitude: float = 0.0
    sine_frequency: float = 0.0
    sine_axis: tuple = SINE_AXIS


def make_schedule(task: str, com0: np.ndarray, s0: np.ndarray, duration: float | None = None) -> TaskSchedule:
    """The references of ``task`` as :func:`wbc_jax.control.references.make_schedule` builds them:
    ``stand`` (CoM held at com0 (3,), default 10 s) or ``sinusoid`` (com0 + 2 cm sin(2 pi 0.2 t)
    along world y, default 20 s); posture s0 (n,). Raises ValueError (other tasks, bad sizes)."""
    if task not in TASKS:
        raise ValueError(f"unknown task {task!r}; the TSID peer runs {list(TASKS)}")
    com0, s0 = np.asarray(com0, float), np.asarray(s0, float)
    if com0.shape != (3,) or s0.ndim != 1:
        raise ValueError(f"com0 must be (3,) and s0 (n,), got {com0.shape} and {s0.shape}")
    if duration is not None and not (math.isfinite(duration) and duration > 0):
        raise ValueError(f"duration must be a positive number of seconds, got {duration}")
    duration = float(duration or TASK_DURATION[task])
    if task == "stand":
        return TaskSchedule("stand", duration, com0, s0)
    return TaskSchedule("sinusoid", duration, com0, s0, sine_amplitude=SINE_AMPLITUDE, sine_frequency=SINE_FREQUENCY)
