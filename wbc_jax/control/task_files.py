"""Task/contact specification files (JSON or YAML): motion tasks, contacts, scene objects and the
initial posture, read and checked before anything compiles (:mod:`wbc_jax.control.tasks` resolves
the tasks against the robot; :mod:`wbc_jax.robot.scene` builds the contacts' scene)."""

from __future__ import annotations

import math
import pathlib

import numpy as np

from wbc_jax.control.tasks import MotionTask, task_from_dict
from wbc_jax.core import loader
from wbc_jax.core.loader import echo
from wbc_jax.robot.model import Robot

SPEC_KEYS = ("tasks", "contacts", "scene", "initial_posture_deg")


def load_spec_file(path) -> dict:
    """Read a task/contact specification file (``.json``, ``.yaml``/``.yml``).

    A mapping with any of: ``tasks`` (a list of task mappings, highest priority first, the postural
    task last), ``contacts`` (a list of contact mappings, :class:`wbc_jax.robot.contacts.Contact`; None:
    the two feet), ``scene`` (a list of objects, :class:`wbc_jax.robot.contacts.SceneObject`) and
    ``initial_posture_deg`` (joint name -> angle in degrees, replacing the home posture's). A bare
    list is a list of tasks.

    Returns a dict with those keys (``tasks`` as :class:`MotionTask` list or None).
    """
    path = pathlib.Path(path)
    data = loader.read_data(path, "task")
    if isinstance(data, list):
        data = {"tasks": data}
    if not isinstance(data, dict) or not set(data) & {"tasks", "contacts"}:
        raise ValueError(f"task file {path} must hold a mapping with 'tasks' and/or 'contacts' lists")
    unknown = sorted(set(data) - set(SPEC_KEYS))
    if unknown:
        raise ValueError(f"task file {path}: unknown keys {unknown}; valid: {list(SPEC_KEYS)}")
    entries = data.get("tasks")
    if entries is not None and (not isinstance(entries, list) or not all(isinstance(e, dict) for e in entries)):
        raise ValueError(f"task file {path} must hold a list of task mappings (under 'tasks')")
    for key in ("contacts", "scene"):
        value = data.get(key)
        if value is not None and (not isinstance(value, list) or not all(isinstance(e, dict) for e in value)):
            raise ValueError(f"task file {path}: '{key}' must be a list of mappings")
    posture = data.get("initial_posture_deg") or {}
    if not isinstance(posture, dict):
        raise ValueError(f"task file {path}: 'initial_posture_deg' must map joint names to degrees")
    return {
        "tasks": None if entries is None else [task_from_dict(e) for e in entries],
        "contacts": data.get("contacts"),
        "scene": data.get("scene") or [],
        "initial_posture_deg": posture,
    }


def load_stack_file(path) -> list[MotionTask]:
    """The task list of a specification file (:func:`load_spec_file`)."""
    tasks = load_spec_file(path)["tasks"]
    if tasks is None:
        raise ValueError(f"task file {path} has no 'tasks' list")
    return tasks


def initial_qpos(robot: Robot, posture_deg: dict) -> np.ndarray:
    """The home keyframe's qpos with the joints of ``posture_deg`` (name -> degrees) replaced."""
    qpos = robot.home_qpos()
    for name, deg in posture_deg.items():
        if name not in robot.index.joints:
            raise ValueError(
                f"initial_posture_deg: unknown joint {echo(name)}; valid joints: {list(robot.index.joints)}"
            )
        if isinstance(deg, bool) or not isinstance(deg, (int, float)) or not math.isfinite(deg):
            raise ValueError(f"initial_posture_deg: {name} must be a finite number of degrees, got {echo(deg)}")
        k = robot.index.joints.index(name)
        lo, hi = np.degrees(robot.mj_model.jnt_range[robot.mj_model.dof_jntid[robot.index.dof_joints[k]]])
        if not lo - 1e-9 <= deg <= hi + 1e-9:
            raise ValueError(
                f"initial_posture_deg: {name} = {deg} deg is outside its joint range [{lo:.1f}, {hi:.1f}] deg"
            )
        qpos[robot.index.qpos_joints[k]] = math.radians(deg)
    return qpos
