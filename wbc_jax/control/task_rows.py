"""The rows of resolved motion tasks at one state: references, errors and the
:class:`wbc_jax.control.hierarchy.TaskLevel` list that :func:`wbc_jax.control.hierarchy.solve`
takes (pure, jit/vmap/grad-safe; :mod:`wbc_jax.control.tasks` defines and resolves the tasks).

A task's reference acceleration is ``a_d + K_D (v_d - v) + K_P (p_d - p)``; an orientation
error is vee(R R_d^T - R_d R^T) / 2, as the WBC orientation tasks.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax.control.hierarchy import TaskLevel
from wbc_jax.control.tasks import AXES, ResolvedTask, TaskReference, TaskStack
from wbc_jax.core.constants import min_jerk
from wbc_jax.core.types import Array
from wbc_jax.robot.dynamics import DynamicsTerms


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
    """The stack's priority levels at one state (highest first), for :func:`wbc_jax.control.hierarchy.solve`.

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
