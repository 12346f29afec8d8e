"""``wbc-jax info``: the robot model's summary as JSON (:mod:`wbc_jax.jobs.info`)."""

from __future__ import annotations

from wbc_jax.commands import Command
from wbc_jax.jobs import info


def run(cfg: info.InfoConfig, progress: bool) -> dict:
    cfg.check()
    return info.run(cfg)


COMMAND = Command("info", "print the robot model summary as JSON", info.default_config, run, compiles=False, indent=2)
