"""``wbc-jax info``: the robot model's summary (:func:`wbc_jax.robot.model.summary`)."""

from __future__ import annotations

import dataclasses

from wbc_jax.core.options import check_options
from wbc_jax.robot import model
from wbc_jax.robot.robots import robot_option


@dataclasses.dataclass(frozen=True)
class InfoConfig:
    """The CLI flags of ``wbc-jax info`` are generated from these fields."""

    robot: str = robot_option()

    def check(self) -> None:
        check_options(self)


def default_config() -> InfoConfig:
    return InfoConfig()


def run(cfg: InfoConfig) -> dict:
    return model.summary(model.load_robot(cfg.robot))
