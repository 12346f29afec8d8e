"""``wbc-jax balance``: one closed-loop balancing run (:mod:`wbc_jax.jobs.balance`)."""

from __future__ import annotations

from wbc_jax.commands import Command
from wbc_jax.jobs import balance


def run(cfg: balance.BalanceConfig, progress: bool) -> dict:
    return balance.run(cfg, progress=progress)  # checks cfg first


COMMAND = Command(
    "balance", "closed-loop balancing run: metrics, trajectory, plots", balance.default_config, run, one_robot=True
)
