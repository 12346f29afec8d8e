"""Scenes and set-ups: what a run simulates, checked before anything compiles.

    load_scene(robot, tasks file) -> Scene        robot model, motion tasks, contact set, posture
    setup(task, ..., scene)       -> Setup        checked inputs, controller, schedule, closed loop
    single(setup), make_push(...) -> Scenario     a batch of one nominal scenario, a checked push

Every check that needs no compilation happens in :func:`setup`. :func:`wbc_jax.sim.runner.run`
then runs a setup over a batch of scenarios on its physics engine.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from wbc_jax.control import references, task_files
from wbc_jax.control import tasks as tasks_lib
from wbc_jax.control.controller import ControllerConfig, make_controller
from wbc_jax.control.gains import Gains, default_gains, validate_gains
from wbc_jax.robot import contacts as contacts_lib
from wbc_jax.robot import model as model_lib
from wbc_jax.robot import scene as contact_scene
from wbc_jax.robot.robots import DEFAULT_ROBOT
from wbc_jax.sim import loop as loop_lib
from wbc_jax.sim.state import Push, Scenario, SimConfig, no_push


@dataclasses.dataclass(frozen=True, eq=False)
class Scene:
    """The robot and what a task/contact file adds: motion tasks (unresolved), the contact set
    (the two soles by default), the initial posture (nq,)."""

    robot: model_lib.Robot
    tasks: list | None
    contact_set: contacts_lib.ContactSet
    qpos: np.ndarray
    tasks_file: str | None = None


def load_scene(robot_name: str = DEFAULT_ROBOT, tasks_file=None) -> Scene:
    """Robot, motion tasks, contact set and initial posture of a specification file (None: the
    plain robot on both feet at the home posture). With ``contacts`` in the file the robot is the
    scene of :func:`wbc_jax.robot.scene.build_scene` (objects, collision spheres, pairs)."""
    robot = model_lib.load_robot(robot_name)
    if not tasks_file:
        return Scene(robot, None, contacts_lib.feet_contact_set(robot), robot.home_qpos())
    try:
        spec = task_files.load_spec_file(tasks_file)
        qpos = task_files.initial_qpos(robot, spec["initial_posture_deg"])
        contact_set = contacts_lib.feet_contact_set(robot)
        if spec["contacts"] is not None:
            robot, contact_set = contact_scene.build_scene(robot_name, spec["contacts"], spec["scene"], qpos)
        elif spec["scene"]:
            raise ValueError("scene objects need a 'contacts' list (what touches them)")
        else:  # the default soles must stand on the floor at the file's initial posture
            contact_scene.check_feet(robot, qpos)
    except ValueError as err:  # every problem of the file names the file
        raise ValueError(str(err) if str(tasks_file) in str(err) else f"task file {tasks_file}: {err}") from None
    return Scene(robot, spec["tasks"], contact_set, qpos, str(tasks_file))


@dataclasses.dataclass(frozen=True, eq=False)
class Setup:
    """Everything a run needs, checked: the robot, the closed loop, the nominal gains, the initial
    posture (nq,) and the float dtype of the controller."""

    scene: Scene
    loop: loop_lib.ClosedLoop
    gains: Gains
    qpos0: np.ndarray
    dtype: np.dtype
    task: str

    @property
    def robot(self) -> model_lib.Robot:
        return self.scene.robot

    @property
    def backend(self) -> str:
        return self.loop.backend


def float_dtype() -> np.dtype:
    """float32, or float64 when JAX's x64 mode is on."""
    return np.dtype(jnp.zeros(()).dtype)


def setup(
    task: str = "stand",
    *,
    duration: float | None = None,
    controller: ControllerConfig | None = None,
    sim: SimConfig | None = None,
    gains: Gains | None = None,
    scene: Scene | None = None,
    robot_name: str = DEFAULT_ROBOT,
    tasks_file=None,
) -> Setup:
    """Validate everything (before any compilation) and build the closed loop of a run.

    Args:
      task: ``stand``, ``sinusoid`` or ``one-foot`` (:func:`wbc_jax.control.references.make_schedule`).
      duration: seconds (None: the task's default); overrides ``sim.duration``.
      controller: controller settings. sim: rollout settings (duration set from the task).
      gains: nominal gains (None: the robot's defaults). scene: a loaded :class:`Scene` (None: from
        ``robot_name`` and ``tasks_file``).
    """
    if task not in references.TASKS:
        raise ValueError(f"unknown task {task!r}; valid tasks: {list(references.TASKS)}")
    if duration is not None and not (isinstance(duration, (int, float)) and math.isfinite(duration) and duration > 0):
        raise ValueError(f"duration must be a positive finite number of seconds, got {duration!r}")
    scene = load_scene(robot_name, tasks_file) if scene is None else scene
    robot = scene.robot
    config = ControllerConfig() if controller is None else controller
    sim = SimConfig() if sim is None else sim
    dtype = float_dtype()
    gains = default_gains(robot.description, dtype) if gains is None else gains
    validate_gains(gains, robot.index.n)
    robot.index.pushable_body_id(sim.push_body)  # unknown body: the valid names, before compiling
    stack = None if scene.tasks is None else tasks_lib.resolve(robot, scene.tasks, scene.qpos)
    # References from the initial posture (C MuJoCo: no compilation).
    m = robot.mj_model
    d = mujoco.MjData(m)
    d.qpos[:] = scene.qpos
    mujoco.mj_forward(m, d)
    schedule = references.make_schedule(
        task,
        com0=d.subtree_com[robot.index.base_body].copy(),
        s0=scene.qpos[robot.index.qpos_joints],
        left_sole=d.site_xpos[robot.index.foot_sites[0]].copy(),
        joints=robot.index.joints,
        foot_lift_deg=robot.description.foot_lift_deg,
        duration=duration,
    )
    sim = dataclasses.replace(sim, duration=schedule.duration)
    ctrl = make_controller(robot, config, contact_set=scene.contact_set, stack=stack, control_dt=sim.control_dt)
    loop = loop_lib.make_closed_loop(robot, schedule, ctrl, sim)
    return Setup(scene=scene, loop=loop, gains=gains, qpos0=np.asarray(scene.qpos, float), dtype=dtype, task=task)


def make_push(force, onset: float, duration: float, dtype=np.float32, body: int = -1) -> Push:
    """One push of ``force`` (3,) N from ``onset`` for ``duration`` s on body id ``body`` (-1: the
    setup's push body); checked."""
    force = np.asarray(force, float).reshape(-1)
    if force.shape != (3,) or not np.all(np.isfinite(force)):
        raise ValueError(f"push force must be 3 finite numbers (N), got {force.tolist()}")
    for name, value in (("push onset", onset), ("push duration", duration)):
        if not (math.isfinite(value) and value >= 0):
            raise ValueError(f"{name} must be a finite number of seconds >= 0, got {value}")
    return Push(
        force=force[None].astype(dtype),
        onset=np.array([onset], dtype),
        duration=np.array([duration], dtype),
        body=np.array([body], np.int32),
    )


def single(setup_: Setup, push: Push | None = None, gains: Gains | None = None) -> Scenario:
    """A batch of one nominal scenario (no joint offset, nominal plant)."""
    dtype = setup_.dtype
    push = no_push(dtype) if push is None else push
    gains = setup_.gains if gains is None else gains
    one = Scenario(
        push=push,
        gains=gains,
        joint_offset=np.zeros(setup_.robot.index.n, dtype),
        friction=np.asarray(1.0, dtype),
        mass_scale=np.asarray(1.0, dtype),
    )
    return jax.tree_util.tree_map(
        lambda x: np.asarray(x, dtype)[None] if np.asarray(x).dtype.kind == "f" else np.asarray(x)[None], one
    )
