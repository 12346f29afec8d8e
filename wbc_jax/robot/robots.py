"""The robots by name: each robot's :class:`~wbc_jax.robot.description.RobotDescription`
(``wbc_jax/robot/<name>.py``), and the ``--robot`` field every job's config declares. Imports neither
JAX nor MuJoCo."""

from __future__ import annotations

from wbc_jax.core.options import option
from wbc_jax.robot import icub, talos
from wbc_jax.robot.description import RobotDescription

DESCRIPTIONS: dict[str, RobotDescription] = {d.name: d for d in (icub.DESCRIPTION, talos.DESCRIPTION)}
ROBOT_NAMES = tuple(DESCRIPTIONS)
DEFAULT_ROBOT = ROBOT_NAMES[0]


def describe(name: str) -> RobotDescription:
    """The description of robot ``name``; one line naming the valid robots otherwise."""
    if name not in DESCRIPTIONS:
        raise ValueError(f"unknown robot {name!r}; valid robots: {list(ROBOT_NAMES)}")
    return DESCRIPTIONS[name]


def robot_option():
    """The ``--robot`` field of every job's config: declared once, here."""
    return option(DEFAULT_ROBOT, "robot model (wbc_jax/robot/<name>.py)", choices=ROBOT_NAMES)
