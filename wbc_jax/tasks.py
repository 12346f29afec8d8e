"""[motion tasks] The seed's lower-priority motion tasks, as data.

A motion task tracks a reference acceleration of a quantity x_i with Jacobian J_i:

    J_i nu_dot + Jdot_i nu = nu_dot*_i,    nu_dot*_i = a_d + K_D (v_d - v) + K_P (p_d - p)

(orientation: the error is vee(R R_d^T - R_d R^T) / 2, as the WBC orientation tasks). A stack is
a list of :class:`MotionTask` in priority order (highest first, all below the force task) whose
last entry is the postural task (``kind="postural"``, the controller's postural law). Tasks that
share a ``priority`` value form one level, their rows weighted by sqrt(weight).

:func:`resolve` checks a stack against the robot and turns names into indices before anything is
compiled; :func:`levels` evaluates the resolved stack at one state (pure, jit/vmap/grad-safe) into
the :class:`wbc_jax.hierarchy.TaskLevel` list that :func:`wbc_jax.hierarchy.solve` takes.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from wbc_jax.constants import min_jerk
from wbc_jax.dynamics import DynamicsTerms, Frames
from wbc_jax.hierarchy import TaskLevel
from wbc_jax.model import NAMED_POINTS, Robot
from wbc_jax.types import Array

TASK_KINDS = ("position", "orientation", "com", "base_orientation", "joints", "postural")
REFERENCE_KINDS = ("constant", "circle")
TASK_DIMENSIONS = {"position": 3, "orientation": 3, "com": 3, "base_orientation": 3}
AXES = {"x": 0, "y": 1, "z": 2}


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
      frame: body, site or named point (``NAMED_POINTS``) for position / orientation tasks.
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
    of the dynamics terms (:func:`wbc_jax.dynamics.terms`)."""

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
    owner = f"task {task.name!r}"
    expected = {
        "name": (lambda v: isinstance(v, str) and v, "a non-empty string"),
        "kind": (lambda v: isinstance(v, str), f"one of {list(TASK_KINDS)}"),
        "frame": (lambda v: v is None or isinstance(v, str), "a body, site or named point"),
        "offset": (lambda v: isinstance(v, (tuple, list)) and len(v) == 3 and all(_is_number(x) for x in v), "3 numbers"),
        "joints": (lambda v: isinstance(v, (tuple, list)) and all(isinstance(j, str) for j in v), "joint names, or 'all'"),
        "kp": (_numbers, "a number or a list of numbers"),
        "kd": (lambda v: v is None or _numbers(v), "a number, a list of numbers or null"),
        "priority": (lambda v: v is None or (isinstance(v, (int, np.integer)) and not isinstance(v, bool)), "a whole number"),
        "weight": (_is_number, "a positive number"),
    }  # fmt: skip
    for name, (ok, what) in expected.items():
        value = getattr(task, name)
        if not ok(value):
            raise ValueError(f"{owner}: {name} must be {what}, got {value!r}")
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
        "plane": (lambda v: isinstance(v, (tuple, list)) and len(v) == 2 and all(isinstance(a, str) for a in v),
                  "two axis names, e.g. [y, z]"),
    }  # fmt: skip
    for name, (ok, what) in ref_expected.items():
        value = getattr(ref, name)
        if not ok(value):
            raise ValueError(f"{owner}: reference {name} must be {what}, got {value!r}")


def _per_row(name: str, value, rows: int) -> tuple[float, ...]:
    arr = np.atleast_1d(np.asarray(value, dtype=float))
    if arr.shape not in ((1,), (rows,)):
        raise ValueError(f"task gain {name} must be a number or have {rows} entries, got {arr.shape}")
    if not np.all(np.isfinite(arr)) or np.any(arr < 0):
        raise ValueError(f"task gain {name} must be finite and non-negative, got {arr.tolist()}")
    return tuple(float(x) for x in np.broadcast_to(arr, (rows,)))


def _resolve_frame(robot: Robot, task: MotionTask) -> tuple[int, tuple[float, float, float]]:
    m, idx = robot.mj_model, robot.index
    offset = np.asarray(task.offset, dtype=float)
    if offset.shape != (3,) or not np.all(np.isfinite(offset)):
        raise ValueError(f"task {task.name!r}: offset must be 3 finite numbers, got {task.offset!r}")
    if task.frame in NAMED_POINTS:
        body, point = NAMED_POINTS[task.frame]
        return idx.body_id(body), tuple(float(x) for x in np.asarray(point) + offset)
    if task.frame in idx.body_names and task.frame:
        return idx.body_id(task.frame), tuple(float(x) for x in offset)
    if task.frame in idx.site_names and task.frame:
        sid = idx.site_id(task.frame)
        return int(m.site_bodyid[sid]), tuple(float(x) for x in m.site_pos[sid] + offset)
    valid = sorted(set(idx.body_names) | set(idx.site_names) | set(NAMED_POINTS) - {""})
    raise ValueError(f"task {task.name!r}: unknown frame {task.frame!r}; valid frames: {valid}")


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
            raise ValueError(f"a task must be a mapping or a MotionTask, got {t!r}")
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
            raise ValueError(f"task {task.name!r}: unknown kind {task.kind!r}; valid kinds: {list(TASK_KINDS)}")
        if not (math.isfinite(task.weight) and task.weight > 0):
            raise ValueError(f"task {task.name!r}: weight must be positive, got {task.weight}")
        ref = task.reference
        if ref.kind not in REFERENCE_KINDS:
            raise ValueError(f"task {task.name!r}: unknown reference kind {ref.kind!r}; valid: {list(REFERENCE_KINDS)}")
        dofs: tuple[int, ...] = ()
        frame = -1
        if task.kind == "joints":
            if not task.joints:
                raise ValueError(f"task {task.name!r}: a joints task needs joint names")
            for j in task.joints:
                if j not in robot.index.joints:
                    raise ValueError(
                        f"task {task.name!r}: unknown joint {j!r}; valid joints: {list(robot.index.joints)}"
                    )
            dofs = tuple(robot.index.joints.index(j) for j in task.joints)
        if task.kind in ("position", "orientation"):
            body, offset = _resolve_frame(robot, task)
            if (body, offset) not in frames:
                frames.append((body, offset))
            frame = frames.index((body, offset))
        elif task.frame is not None:
            raise ValueError(f"task {task.name!r}: a {task.kind} task takes no frame (got {task.frame!r})")
        rows = task_dimension(task)
        if ref.kind == "circle":
            if task.kind not in ("position", "com"):
                raise ValueError(f"task {task.name!r}: a circle reference needs a position or com task")
            if not (ref.radius > 0 and ref.frequency > 0 and ref.ramp >= 0):
                raise ValueError(f"task {task.name!r}: circle needs radius > 0, frequency > 0, ramp >= 0")
            axes = [a.lstrip("+-") for a in ref.plane]
            if len(ref.plane) != 2 or any(a not in AXES for a in axes) or axes[0] == axes[1]:
                raise ValueError(
                    f"task {task.name!r}: circle plane must be two different axes of {list(AXES)}, each "
                    f"optionally signed ('-z'), got {list(ref.plane)}"
                )
        target_len = 4 if task.kind in ("orientation", "base_orientation") else rows
        if ref.target is not None:
            target = np.asarray(ref.target, dtype=float)
            if target.shape != (target_len,) or not np.all(np.isfinite(target)):
                raise ValueError(
                    f"task {task.name!r}: reference target must have {target_len} finite entries "
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
            )  # fmt: skip
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
        raise ValueError(f"a task must be a mapping, got {values!r}")
    unknown = sorted(map(str, set(values) - fields))
    if unknown or "name" not in values or "kind" not in values:
        raise ValueError(f"task {values.get('name')!r}: unknown keys {unknown} (valid: {sorted(fields)}); "
                         "'name' and 'kind' are required")  # fmt: skip
    values = dict(values)
    ref = values.pop("reference", {}) or {}
    ref_fields = {f.name for f in dataclasses.fields(TaskReference)}
    if not isinstance(ref, dict) or set(ref) - set(map(str, ref_fields)) or not all(isinstance(k, str) for k in ref):
        raise ValueError(f"task {values['name']!r}: reference keys must be among {sorted(ref_fields)}")
    ref = {k: tuple(v) if isinstance(v, list) else v for k, v in ref.items()}
    values = {k: tuple(v) if isinstance(v, list) else v for k, v in values.items()}
    if isinstance(values.get("joints"), str):
        values["joints"] = (values["joints"],)  # "all", or a single joint name
    return MotionTask(**values, reference=TaskReference(**ref))


def _signed_axis(name: str, dtype) -> Array:
    """Unit vector of a world axis name, optionally signed: "y", "+y", "-z"."""
    return jnp.zeros(3, dtype).at[AXES[name.lstrip("+-")]].set(-1.0 if name.startswith("-") else 1.0)


def _circle(ref: TaskReference, p0: Array, t: Array) -> Array:
    e1, e2 = (_signed_axis(a, p0.dtype) for a in ref.plane)
    w = 2 * math.pi * ref.frequency
    radius = ref.radius * (min_jerk(t / ref.ramp)[0] if ref.ramp > 0 else 1.0)
    return p0 + radius * ((jnp.cos(w * t) - 1) * e1 + jnp.sin(w * t) * e2)


def reference_at(task: ResolvedTask, t: Array, dtype) -> tuple[Array, Array, Array]:
    """(position, velocity, acceleration) of a position-like task's reference at time t."""
    p0 = jnp.asarray(task.target, dtype)
    if task.reference.kind == "constant":
        zero = jnp.zeros_like(p0)
        return p0, zero, zero
    t = jnp.asarray(t, dtype)
    pos = lambda s: _circle(task.reference, p0, s)  # noqa: E731
    vel = lambda s: jax.jvp(pos, (s,), (jnp.ones_like(s),))[1]  # noqa: E731
    return pos(t), vel(t), jax.jvp(vel, (t,), (jnp.ones_like(t),))[1]


def _vee_error(R: Array, R_des: Array) -> Array:
    E = R @ R_des.T
    return 0.5 * jnp.array([E[2, 1] - E[1, 2], E[0, 2] - E[2, 0], E[1, 0] - E[0, 1]])


def task_rows(task: ResolvedTask, t: DynamicsTerms, time: Array, frame0: int):
    """(J (m, nv), Jdot_nu (m,), nu_dot_star (m,), error (m,)) of one task at one state; the
    stack's frames start at frame ``frame0`` of the dynamics terms (after the contacts')."""
    dtype = t.M.dtype
    nv = t.M.shape[0]
    kp, kd = jnp.asarray(task.kp, dtype), jnp.asarray(task.kd, dtype)
    k = frame0 + task.frame
    if task.kind in ("orientation", "base_orientation"):
        if task.kind == "orientation":
            J, Jdot_nu, R = t.J_frames[k, 3:], t.Jdot_nu_frames[k, 3:], t.W_R_frames[k]
        else:
            J = jnp.zeros((3, nv), dtype).at[:, 3:6].set(jnp.eye(3, dtype=dtype))
            Jdot_nu, R = jnp.zeros(3, dtype), t.W_R_B
        err = _vee_error(R, jnp.asarray(task.target, dtype).reshape(3, 3))
        return J, Jdot_nu, -kd * (J @ t.nu) - kp * err, err
    if task.kind == "joints":
        dofs = np.asarray(task.dofs)
        J = jnp.zeros((len(dofs), nv), dtype).at[np.arange(len(dofs)), 6 + dofs].set(1.0)
        Jdot_nu, p = jnp.zeros(len(dofs), dtype), t.s[dofs]
    elif task.kind == "position":
        J, Jdot_nu, p = t.J_frames[k, :3], t.Jdot_nu_frames[k, :3], t.W_p_frames[k]
    else:  # com
        J, Jdot_nu, p = t.J_CoM, t.Jdot_nu_CoM, t.W_p_CoM
    p_des, v_des, a_des = reference_at(task, time, dtype)
    err = p - p_des
    return J, Jdot_nu, a_des + kd * (v_des - J @ t.nu) - kp * err, err


def levels(stack: TaskStack, t: DynamicsTerms, time: Array, frame0: int) -> tuple[TaskLevel, ...]:
    """The stack's priority levels at one state (highest first), for :func:`wbc_jax.hierarchy.solve`.

    Args:
      stack: resolved stack. t: dynamics terms whose frames from ``frame0`` on are
        ``stack.frames``. time: () the reference time (s).
    """
    out = []
    for level in range(stack.n_levels):
        rows = [(task, task_rows(task, t, time, frame0)) for task in stack.tasks if task.level == level]
        scale = [math.sqrt(task.weight) for task, _ in rows]
        out.append(
            TaskLevel(
                J=jnp.concatenate([s * r[0] for s, (_, r) in zip(scale, rows, strict=True)]),
                Jdot_nu=jnp.concatenate([s * r[1] for s, (_, r) in zip(scale, rows, strict=True)]),
                nu_dot_star=jnp.concatenate([s * r[2] for s, (_, r) in zip(scale, rows, strict=True)]),
            )
        )
    return tuple(out)


def task_errors(stack: TaskStack, t: DynamicsTerms, time: Array, frame0: int) -> dict[str, Array]:
    """Per-task tracking error (position: p - p_d in m; orientation: vee error) at one state."""
    return {task.name: task_rows(task, t, time, frame0)[3] for task in stack.tasks}


SPEC_KEYS = ("tasks", "contacts", "scene", "initial_posture_deg")


def load_spec_file(path) -> dict:
    """Read a task/contact specification file (``.json``, ``.yaml``/``.yml``).

    A mapping with any of: ``tasks`` (a list of task mappings, highest priority first, the postural
    task last), ``contacts`` (a list of contact mappings, :class:`wbc_jax.contacts.Contact`; None:
    the two feet), ``scene`` (a list of objects, :class:`wbc_jax.contacts.SceneObject`) and
    ``initial_posture_deg`` (joint name -> angle in degrees, replacing the home posture's). A bare
    list is a list of tasks.

    Returns a dict with those keys (``tasks`` as :class:`MotionTask` list or None).
    """
    import json
    import pathlib

    path = pathlib.Path(path)
    if not path.exists():
        raise FileNotFoundError(f"task file {path} does not exist")
    text = path.read_text()
    if path.suffix in (".yaml", ".yml"):
        import yaml

        try:
            data = yaml.safe_load(text)
        except yaml.YAMLError as err:
            raise ValueError(f"task file {path} is not valid YAML: {err}") from err
    elif path.suffix == ".json":
        try:
            data = json.loads(text)
        except json.JSONDecodeError as err:
            raise ValueError(f"task file {path} is not valid JSON: {err}") from err
    else:
        raise ValueError(f"task file {path}: unknown format {path.suffix!r}; valid: .json, .yaml, .yml")
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
            raise ValueError(f"initial_posture_deg: unknown joint {name!r}; valid joints: {list(robot.index.joints)}")
        if isinstance(deg, bool) or not isinstance(deg, (int, float)) or not math.isfinite(deg):
            raise ValueError(f"initial_posture_deg: {name} must be a finite number of degrees, got {deg!r}")
        k = robot.index.joints.index(name)
        lo, hi = np.degrees(robot.mj_model.jnt_range[robot.mj_model.dof_jntid[robot.index.dof_joints[k]]])
        if not lo - 1e-9 <= deg <= hi + 1e-9:
            raise ValueError(
                f"initial_posture_deg: {name} = {deg} deg is outside its joint range [{lo:.1f}, {hi:.1f}] deg"
            )
        qpos[robot.index.qpos_joints[k]] = math.radians(deg)
    return qpos
