"""The seed's lower-priority motion tasks, as data.

A motion task tracks a reference acceleration of a quantity x_i with Jacobian J_i:

    J_i nu_dot + Jdot_i nu = nu_dot*_i,    nu_dot*_i = a_d + K_D (v_d - v) + K_P (p_d - p)

(orientation: the error is vee(R R_d^T - R_d R^T) / 2, as the WBC orientation tasks). A stack is
a list of :class:`MotionTask` in priority order (highest first, all below the force task) whose
last entry is the postural task (``kind="postural"``, the controller's postural law). Tasks that
share a ``priority`` value form one level, their rows weighted by sqrt(weight).

:func:`resolve` checks a stack against the robot and turns names into indices before anything is
compiled; :func:`levels` evaluates the resolved stack at one state (pure, jit/vmap/grad-safe) into
the :class:`wbc_jax.control.hierarchy.TaskLevel` list that :func:`wbc_jax.control.hierarchy.solve` takes.
"""

from __future__ import annotations

import dataclasses
import math

import mujoco
import numpy as np

from wbc_jax.core.loader import echo
from wbc_jax.robot.dynamics import Frames
from wbc_jax.robot.model import Robot

TASK_KINDS = ("position", "orientation", "com", "base_orientation", "joints", "postural")
REFERENCE_KINDS = ("constant", "circle")
TASK_DIMENSIONS = {"position": 3, "orientation": 3, "com": 3, "base_orientation": 3}
AXES = {"x": 0, "y": 1, "z": 2}
# Ranges of a task file's numbers.
MAX_TASK_GAIN = 1e6  # kp, kd, weight
MAX_CIRCLE_RADIUS_M = 1.0  # beyond the arms' reach
MAX_CIRCLE_FREQUENCY_HZ = 10.0
MAX_RAMP_S = 600.0


@dataclasses.dataclass(frozen=True)
class TaskReference:
    """Reference of a task.

    Attributes:
      kind: ``"constant"``, or ``"circle"`` (position-like tasks): a circle through the start point,
        p(t) = p0 + r(t) [(cos wt - 1) e1 + sin wt e2], with the radius ramped in by a minimum-jerk
        profile over ``ramp`` seconds so that the reference starts at rest.
      target: the set-point (constant) or start point (circle); None: the value at the initial
        posture. Length: the task dimension (3; joints: the number of joints; orientation: a
        (w, x, y, z) quaternion).
      radius (m), frequency (Hz), plane (two world axes, e1 then e2, each optionally signed: the
        circle leaves p0 along e2 and its far point is p0 - 2 r e1), ramp (s): circle only.
    """

    kind: str = "constant"
    target: tuple[float, ...] | None = None
    radius: float = 0.0
    frequency: float = 0.0
    plane: tuple[str, str] = ("y", "z")
    ramp: float = 1.0


@dataclasses.dataclass(frozen=True)
class MotionTask:
    """One task of the stack (user-facing specification, names not yet resolved).

    Attributes:
      name: unique name.
      kind: one of ``TASK_KINDS``.
      frame: body, site or named point (the robot description's ``named_points``) for position / orientation tasks.
      offset: (3,) point in the body frame, added to the frame's own offset (position tasks).
      joints: joint names of a ``joints`` task (``("all",)``: every controlled joint).
      kp, kd: PD gains, a number or one per row; kd None: 2 sqrt(kp) (critical damping).
      priority: tasks with equal values share a level; None: the position in the list.
      weight: relative weight inside a level (> 0).
      reference: :class:`TaskReference`.
    """

    name: str
    kind: str
    frame: str | None = None
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    joints: tuple[str, ...] = ()
    kp: float | tuple[float, ...] = 100.0
    kd: float | tuple[float, ...] | None = None
    priority: int | None = None
    weight: float = 1.0
    reference: TaskReference = TaskReference()


@dataclasses.dataclass(frozen=True)
class ResolvedTask:
    """A task with indices instead of names (hashable: part of the static controller config).

    frame: index into the stack's frames (position / orientation), else -1; dofs: controller
    joint indices (joints); kp, kd: per row; target: resolved start point / set-point
    (orientation: a flattened 3x3 rotation matrix)."""

    name: str
    kind: str
    level: int
    frame: int
    dofs: tuple[int, ...]
    kp: tuple[float, ...]
    kd: tuple[float, ...]
    weight: float
    reference: TaskReference
    target: tuple[float, ...]


@dataclasses.dataclass(frozen=True)
class TaskStack:
    """A resolved stack: motion tasks (postural excluded: it is the implicit last level) and the
    task frames as (body id, offset) pairs. :attr:`frames` are appended to the contact frames
    of the dynamics terms (:func:`wbc_jax.robot.dynamics.terms`)."""

    tasks: tuple[ResolvedTask, ...] = ()
    bodies: tuple[int, ...] = ()
    offsets: tuple[tuple[float, float, float], ...] = ()

    @property
    def n_levels(self) -> int:
        return len({task.level for task in self.tasks})

    @property
    def frames(self) -> Frames:
        return Frames(tuple(self.bodies), tuple(self.offsets))


def task_dimension(task: MotionTask) -> int:
    return len(task.joints) if task.kind == "joints" else TASK_DIMENSIONS.get(task.kind, 0)


def _is_number(x) -> bool:
    return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, bool)


def _numbers(x) -> bool:
    return _is_number(x) or (isinstance(x, (tuple, list)) and len(x) > 0 and all(_is_number(v) for v in x))


def check_types(task: MotionTask) -> None:
    """Each field of a task (and of its reference) has the type it must have: a clear error
    naming the task, the field, the value and what was expected."""
    owner = f"task {echo(task.name)}"
    expected = {
        "name": (lambda v: isinstance(v, str) and v, "a non-empty string"),
        "kind": (lambda v: isinstance(v, str), f"one of {list(TASK_KINDS)}"),
        "frame": (lambda v: v is None or isinstance(v, str), "a body, site or named point"),
        "offset": (
            lambda v: isinstance(v, (tuple, list)) and len(v) == 3 and all(_is_number(x) for x in v),
            "3 numbers",
        ),
        "joints": (
            lambda v: isinstance(v, (tuple, list)) and all(isinstance(j, str) for j in v),
            "joint names, or 'all'",
        ),
        "kp": (_numbers, "a number or a list of numbers"),
        "kd": (lambda v: v is None or _numbers(v), "a number, a list of numbers or null"),
        "priority": (
            lambda v: v is None or (isinstance(v, (int, np.integer)) and not isinstance(v, bool)),
            "a whole number",
        ),
        "weight": (_is_number, "a positive number"),
    }
    for name, (ok, what) in expected.items():
        value = getattr(task, name)
        if not ok(value):
            raise ValueError(f"{owner}: {name} must be {what}, got {echo(value)}")
    ref = task.reference
    if not isinstance(ref, TaskReference):
        raise ValueError(
            f"{owner}: reference must be a mapping of {[f.name for f in dataclasses.fields(TaskReference)]}"
        )
    ref_expected = {
        "kind": (lambda v: isinstance(v, str), f"one of {list(REFERENCE_KINDS)}"),
        "target": (lambda v: v is None or _numbers(v), "a list of numbers or null"),
        "radius": (_is_number, "a number (m)"),
        "frequency": (_is_number, "a number (Hz)"),
        "ramp": (_is_number, "a number (s)"),
        "plane": (
            lambda v: isinstance(v, (tuple, list)) and len(v) == 2 and all(isinstance(a, str) for a in v),
            "two axis names, e.g. [y, z]",
        ),
    }
    for name, (ok, what) in ref_expected.items():
        value = getattr(ref, name)
        if not ok(value):
            raise ValueError(f"{owner}: reference {name} must be {what}, got {echo(value)}")


def _per_row(name: str, value, rows: int) -> tuple[float, ...]:
    arr = np.atleast_1d(np.asarray(value, dtype=float))
    if arr.shape not in ((1,), (rows,)):
        raise ValueError(f"task gain {name} must be a number or have {rows} entries, got {arr.shape}")
    if not np.all(np.isfinite(arr)) or np.any(arr < 0) or np.any(arr > MAX_TASK_GAIN):
        raise ValueError(f"task gain {name} must be in [0, {MAX_TASK_GAIN:g}], got {arr.tolist()}")
    return tuple(float(x) for x in np.broadcast_to(arr, (rows,)))


def _resolve_frame(robot: Robot, task: MotionTask) -> tuple[int, tuple[float, float, float]]:
    m, idx = robot.mj_model, robot.index
    offset = np.asarray(task.offset, dtype=float)
    if offset.shape != (3,) or not np.all(np.isfinite(offset)):
        raise ValueError(f"task {echo(task.name)}: offset must be 3 finite numbers, got {echo(task.offset)}")
    named_points = robot.description.named_points
    if task.frame in named_points:
        body, point = named_points[task.frame]
        return idx.body_id(body), tuple(float(x) for x in np.asarray(point) + offset)
    if task.frame in idx.body_names and task.frame:
        return idx.body_id(task.frame), tuple(float(x) for x in offset)
    if task.frame in idx.site_names and task.frame:
        sid = idx.site_id(task.frame)
        return int(m.site_bodyid[sid]), tuple(float(x) for x in m.site_pos[sid] + offset)
    valid = sorted(set(idx.body_names) | set(idx.site_names) | set(named_points) - {""})
    raise ValueError(f"task {echo(task.name)}: unknown frame {echo(task.frame)}; valid frames: {valid}")


def _initial_values(robot: Robot, qpos: np.ndarray, body: int, offset) -> tuple[np.ndarray, np.ndarray]:
    d = mujoco.MjData(robot.mj_model)
    d.qpos[:] = qpos
    mujoco.mj_forward(robot.mj_model, d)
    R = d.xmat[body].reshape(3, 3)
    return d.xpos[body] + R @ np.asarray(offset), R


def resolve(robot: Robot, stack, qpos: np.ndarray | None = None) -> TaskStack:
    """Check a stack and resolve its names (before any compilation).

    Args:
      robot: the robot. stack: sequence of :class:`MotionTask` (or dicts with its fields), highest
        priority first, the postural task last.
      qpos: (nq,) posture where ``target=None`` references are read (default: the home keyframe).

    Raises:
      ValueError: naming the problem (unknown kind, frame or joint, wrong reference shape,
        duplicate names, no postural task at the bottom, bad gains or weights).
    """
    tasks = [task_from_dict(t) if isinstance(t, dict) else t for t in stack]
    for t in tasks:
        if not isinstance(t, MotionTask):
            raise ValueError(f"a task must be a mapping or a MotionTask, got {echo(t)}")
    # A bare string is one name ("all"), not a sequence of one-letter joint names.
    tasks = [dataclasses.replace(t, joints=(t.joints,)) if isinstance(t.joints, str) else t for t in tasks]
    # joints: ["all"] is every controlled joint, in the robot's order.
    tasks = [dataclasses.replace(t, joints=tuple(robot.index.joints)) if t.joints == ("all",) else t for t in tasks]
    for t in tasks:
        check_types(t)
    if not tasks or tasks[-1].kind != "postural":
        raise ValueError(
            "the task stack must end with the postural task (kind 'postural', the lowest priority); "
            f"got kinds {[t.kind for t in tasks]}"
        )
    names = [t.name for t in tasks]
    duplicates = sorted({n for n in names if names.count(n) > 1})
    if duplicates:
        raise ValueError(f"duplicate task names {duplicates}; each task needs its own name")
    if sum(t.kind == "postural" for t in tasks) != 1:
        raise ValueError("the stack must have exactly one postural task (the last one)")
    qpos = robot.home_qpos() if qpos is None else np.asarray(qpos, dtype=float)
    if qpos.shape != (robot.index.nq,):
        raise ValueError(f"qpos must have shape ({robot.index.nq},), got {qpos.shape}")
    priorities = [k if t.priority is None else t.priority for k, t in enumerate(tasks)]
    if any(p >= priorities[-1] for p in priorities[:-1]):
        raise ValueError("the postural task must have the lowest priority (alone in the last level)")
    if priorities != sorted(priorities):
        raise ValueError(f"tasks must be listed by priority (highest first), got priorities {priorities}")
    level_of = {p: k for k, p in enumerate(sorted(set(priorities[:-1])))}

    frames: list[tuple[int, tuple[float, float, float]]] = []
    resolved = []
    for task, priority in zip(tasks[:-1], priorities[:-1], strict=True):
        if task.kind not in TASK_KINDS:
            raise ValueError(f"task {echo(task.name)}: unknown kind {echo(task.kind)}; valid kinds: {list(TASK_KINDS)}")
        if not (math.isfinite(task.weight) and 0 < task.weight <= MAX_TASK_GAIN):
            raise ValueError(f"task {echo(task.name)}: weight must be in (0, {MAX_TASK_GAIN:g}], got {task.weight}")
        ref = task.reference
        if ref.kind not in REFERENCE_KINDS:
            raise ValueError(
                f"task {echo(task.name)}: unknown reference kind {echo(ref.kind)}; valid: {list(REFERENCE_KINDS)}"
            )
        dofs: tuple[int, ...] = ()
        frame = -1
        if task.kind == "joints":
            if not task.joints:
                raise ValueError(f"task {echo(task.name)}: a joints task needs joint names")
            for j in task.joints:
                if j not in robot.index.joints:
                    raise ValueError(
                        f"task {echo(task.name)}: unknown joint {echo(j)}; valid joints: {list(robot.index.joints)}"
                    )
            dofs = tuple(robot.index.joints.index(j) for j in task.joints)
        if task.kind in ("position", "orientation"):
            body, offset = _resolve_frame(robot, task)
            if (body, offset) not in frames:
                frames.append((body, offset))
            frame = frames.index((body, offset))
        elif task.frame is not None:
            raise ValueError(f"task {echo(task.name)}: a {task.kind} task takes no frame (got {echo(task.frame)})")
        rows = task_dimension(task)
        if ref.kind == "circle":
            if task.kind not in ("position", "com"):
                raise ValueError(f"task {echo(task.name)}: a circle reference needs a position or com task")
            if not (
                0 < ref.radius <= MAX_CIRCLE_RADIUS_M
                and 0 < ref.frequency <= MAX_CIRCLE_FREQUENCY_HZ
                and 0 <= ref.ramp <= MAX_RAMP_S
            ):
                raise ValueError(
                    f"task {echo(task.name)}: circle needs radius in (0, {MAX_CIRCLE_RADIUS_M:g}] m, "
                    f"frequency in (0, {MAX_CIRCLE_FREQUENCY_HZ:g}] Hz and ramp in [0, {MAX_RAMP_S:g}] "
                    f"s, got {ref.radius}, {ref.frequency}, {ref.ramp}"
                )
            axes = [a.lstrip("+-") for a in ref.plane]
            if len(ref.plane) != 2 or any(a not in AXES for a in axes) or axes[0] == axes[1]:
                raise ValueError(
                    f"task {echo(task.name)}: circle plane must be two different axes of {list(AXES)}, each "
                    f"optionally signed ('-z'), got {list(ref.plane)}"
                )
        target_len = 4 if task.kind in ("orientation", "base_orientation") else rows
        if ref.target is not None:
            target = np.asarray(ref.target, dtype=float)
            if target.shape != (target_len,) or not np.all(np.isfinite(target)):
                raise ValueError(
                    f"task {echo(task.name)}: reference target must have {target_len} finite entries "
                    f"({'a (w, x, y, z) quaternion' if target_len == 4 else 'the task dimension'}), "
                    f"got shape {target.shape}"
                )
        target = _resolve_target(robot, task, qpos, frames[frame] if frame >= 0 else None)
        resolved.append(
            ResolvedTask(
                name=task.name,
                kind=task.kind,
                level=level_of[priority],
                frame=frame,
                dofs=dofs,
                kp=_per_row("kp", task.kp, rows),
                kd=_per_row("kd", 2 * np.sqrt(np.asarray(task.kp, float)) if task.kd is None else task.kd, rows),
                weight=float(task.weight),
                reference=ref,
                target=target,
            )
        )
    return TaskStack(
        tasks=tuple(resolved),
        bodies=tuple(b for b, _ in frames),
        offsets=tuple(o for _, o in frames),
    )


def _resolve_target(robot: Robot, task: MotionTask, qpos, frame) -> tuple[float, ...]:
    ref = task.reference
    if task.kind in ("orientation", "base_orientation"):
        if ref.target is not None:
            R = np.zeros(9)
            mujoco.mju_quat2Mat(R, np.asarray(ref.target, float) / np.linalg.norm(ref.target))
        elif task.kind == "orientation":
            R = _initial_values(robot, qpos, *frame)[1].ravel()
        else:
            R = _initial_values(robot, qpos, robot.index.base_body, (0.0, 0.0, 0.0))[1].ravel()
        return tuple(float(x) for x in R)
    if ref.target is not None:
        return tuple(float(x) for x in ref.target)
    if task.kind == "position":
        return tuple(float(x) for x in _initial_values(robot, qpos, *frame)[0])
    if task.kind == "joints":
        return tuple(
            float(qpos[robot.index.qpos_joints[k]]) for k in (robot.index.joints.index(j) for j in task.joints)
        )
    d = mujoco.MjData(robot.mj_model)  # com
    d.qpos[:] = qpos
    mujoco.mj_forward(robot.mj_model, d)
    return tuple(float(x) for x in d.subtree_com[robot.index.base_body])


def task_from_dict(values: dict) -> MotionTask:
    """A :class:`MotionTask` from a JSON/YAML mapping (``reference`` as a nested mapping)."""
    fields = {f.name for f in dataclasses.fields(MotionTask)}
    if not isinstance(values, dict):
        raise ValueError(f"a task must be a mapping, got {echo(values)}")
    unknown = sorted(map(str, set(values) - fields))
    if unknown or "name" not in values or "kind" not in values:
        raise ValueError(
            f"task {echo(values.get('name'))}: unknown keys {unknown} (valid: {sorted(fields)}); "
            "'name' and 'kind' are required"
        )
    values = dict(values)
    ref = values.pop("reference", {}) or {}
    ref_fields = {f.name for f in dataclasses.fields(TaskReference)}
    if not isinstance(ref, dict) or set(ref) - set(map(str, ref_fields)) or not all(isinstance(k, str) for k in ref):
        raise ValueError(f"task {echo(values['name'])}: reference keys must be among {sorted(ref_fields)}")
    ref = {k: tuple(v) if isinstance(v, list) else v for k, v in ref.items()}
    values = {k: tuple(v) if isinstance(v, list) else v for k, v in values.items()}
    if isinstance(values.get("joints"), str):
        values["joints"] = (values["joints"],)  # "all", or a single joint name
    return MotionTask(**values, reference=TaskReference(**ref))
