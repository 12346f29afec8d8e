"""``wbc-jax push-sweep``: the batched push-recovery sweep, the main job (:mod:`wbc_jax.jobs.sweep`)."""

from __future__ import annotations

from wbc_jax.commands import Command
from wbc_jax.jobs import sweep_config

# The summary's entries on the command's JSON line.
LINE_KEYS = (
    "n_envs",
    "survival_rate",
    "upright_rate",
    "nan_envs",
    "qp_infeasible_envs",
    "backend",
    "physics_steps_per_s",
    "compile_s",
    "run_s",
    "started_s",
    "n_devices",
)


def run(cfg: sweep_config.SweepConfig, progress: bool) -> dict:
    from wbc_jax.jobs import sweep  # (imported when run: the flags need only the config)

    summary = sweep.run_sweep(cfg, progress=progress)  # checks cfg first
    return {k: summary[k] for k in LINE_KEYS}


COMMAND = Command(
    "push-sweep", "batched push-recovery sweep (the main job)", sweep_config.default_config, run, resumable=True
)
