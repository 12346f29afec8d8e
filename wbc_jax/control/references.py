"""References for the balancing tasks: CoM trajectories, postural set-points, contact activations.

Every reference is a sum of minimum-jerk segments, x(t) = x0 + sum_i delta_i mj((t - t_i) / T_i),
with mj(u) = 10u^3 - 15u^4 + 6u^5 on [0, 1]: position, velocity and acceleration are
continuous, as the minimum-jerk filters of the WBC state machine. Tasks (stand, sinusoid,
one-foot) build these from the robot's initial state; ``at(t)`` is pure and jit-safe.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import jax.numpy as jnp
import numpy as np

from wbc_jax.core.constants import min_jerk
from wbc_jax.core.types import Array, pytree_dataclass

TASKS = ("stand", "sinusoid", "one-foot")
# Each task's length when none is given (s).
DEFAULT_DURATIONS = {"stand": 10.0, "sinusoid": 20.0, "one-foot": 16.0}


@pytree_dataclass
class Reference:
    """References at one tick: com_pos/com_vel/com_acc (3,), s_des (n,), activation (2,) of the
    feet (the task's contact schedule: left, right)."""

    com_pos: Array
    com_vel: Array
    com_acc: Array
    s_des: Array
    activation: Array


def segments(t: Array, x0: Array, starts, durations, deltas) -> tuple[Array, Array, Array]:
    """Sum of minimum-jerk segments at time t: (pos, vel, acc), each shaped like x0 (d,).
    starts, durations: (k,) numpy; deltas: (k, d)."""
    starts, durations = np.asarray(starts, float), np.asarray(durations, float)
    deltas = jnp.asarray(deltas, x0.dtype)
    if len(starts) == 0:
        zero = jnp.zeros_like(x0)
        return x0, zero, zero
    p, v, a = min_jerk(jnp.asarray((t - starts) / durations, x0.dtype))
    pos = x0 + jnp.einsum("k,kd->d", p, deltas)
    vel = jnp.einsum("k,kd->d", v / durations, deltas)
    acc = jnp.einsum("k,kd->d", a / durations**2, deltas)
    return pos, vel, acc


@dataclasses.dataclass(frozen=True, eq=False)
class Schedule:
    """A task's references as minimum-jerk segments plus an optional CoM sinusoid."""

    name: str
    duration: float
    com0: np.ndarray  # (3,)
    s0: np.ndarray  # (n,)
    com_segments: tuple = ((), (), np.zeros((0, 3)))
    posture_segments: tuple = ((), (), None)
    activation_segments: tuple = ((), (), np.zeros((0, 2)))
    sine_amplitude: float = 0.0
    sine_frequency: float = 0.0
    sine_axis: tuple = (0.0, 1.0, 0.0)

    def at(self, t: Array, dtype=jnp.float32) -> Reference:
        """References at time t (s)."""
        com0 = jnp.asarray(self.com0, dtype)
        com, com_v, com_a = segments(t, com0, *self.com_segments)
        if self.sine_amplitude:
            w = 2 * np.pi * self.sine_frequency
            axis = jnp.asarray(self.sine_axis, dtype)
            com = com + self.sine_amplitude * jnp.sin(w * t) * axis
            com_v = com_v + self.sine_amplitude * w * jnp.cos(w * t) * axis
            com_a = com_a - self.sine_amplitude * w**2 * jnp.sin(w * t) * axis
        s0 = jnp.asarray(self.s0, dtype)
        post = self.posture_segments
        s_des = s0 if post[2] is None else segments(t, s0, *post)[0]
        act = segments(t, jnp.ones(2, dtype), *self.activation_segments)[0]
        return Reference(com_pos=com, com_vel=com_v, com_acc=com_a, s_des=s_des, activation=act)


def make_schedule(
    task: str,
    *,
    com0: np.ndarray,
    s0: np.ndarray,
    left_sole: np.ndarray,
    joints: tuple[str, ...],
    foot_lift_deg: Mapping[str, float] | None = None,
    duration: float | None = None,
    amplitude: float = 0.02,
    frequency: float = 0.2,
) -> Schedule:
    """Build the references of a task.

    Args:
      task: ``stand`` (constant CoM), ``sinusoid`` (CoM along y, 2 cm at 0.2 Hz: the WBC
        COORDINATOR demo) or ``one-foot`` (two feet -> CoM over the left foot -> unload and lift
        the right foot -> balance -> put it back -> two feet).
      com0: (3,) initial CoM. s0: (n,) postural reference (home posture).
      left_sole: (3,) left sole origin. joints: joint names (controller order).
      foot_lift_deg: joint -> degrees that lift the right foot with its sole parallel to the floor
        (the robot description's ``foot_lift_deg``; needed by ``one-foot``).
      duration: seconds (default: 10 for stand, 20 for sinusoid, 16 for one-foot).
      amplitude, frequency: of the sinusoid (m, Hz).
    """
    if task not in TASKS:
        raise ValueError(f"unknown task {task!r}; valid tasks: {list(TASKS)}")
    com0 = np.asarray(com0, float)
    s0 = np.asarray(s0, float)
    if com0.shape != (3,):
        raise ValueError(f"com0 must have shape (3,), got {com0.shape}")
    if s0.shape != (len(joints),):
        raise ValueError(f"s0 must have shape ({len(joints)},), got {s0.shape}")
    if duration is not None and not (np.isfinite(duration) and duration > 0):
        raise ValueError(f"duration must be positive, got {duration}")
    if task == "stand":
        return Schedule("stand", duration or DEFAULT_DURATIONS["stand"], com0, s0)
    if task == "sinusoid":
        if not (amplitude >= 0 and frequency > 0):
            raise ValueError("sinusoid amplitude must be >= 0 and frequency > 0")
        return Schedule(
            "sinusoid",
            duration or DEFAULT_DURATIONS["sinusoid"],
            com0,
            s0,
            sine_amplitude=amplitude,
            sine_frequency=frequency,
        )
    # One-foot sequence (WBC YOGA state machine, simplified), seconds:
    # 1-4 CoM over the left sole; 4-5 unload the right foot; 5.5-7 lift it; 7-9 balance on the
    # left foot; 9-11 put it back; 11.5-12.5 load it; 12.5-15.5 CoM back to the middle.
    over_left = np.array([com0[0], left_sole[1], com0[2]])
    shift = over_left - com0
    if not foot_lift_deg:
        raise ValueError(
            "the one-foot task needs foot_lift_deg: the joint angles that lift the right foot (the robot description's)"
        )
    lift = np.zeros(len(s0))
    for joint, degrees in foot_lift_deg.items():  # hip and knee flexion, the ankle keeping the sole flat
        lift[joints.index(joint)] = np.deg2rad(degrees)
    com_seg = ((1.0, 12.5), (3.0, 3.0), np.stack([shift, -shift]))
    post_seg = ((5.5, 9.0), (1.5, 2.0), np.stack([lift, -lift]))
    act_seg = ((4.0, 11.5), (1.0, 1.0), np.array([[0.0, -1.0], [0.0, 1.0]]))
    return Schedule(
        "one-foot",
        duration or DEFAULT_DURATIONS["one-foot"],
        com0,
        s0,
        com_segments=com_seg,
        posture_segments=post_seg,
        activation_segments=act_seg,
    )
