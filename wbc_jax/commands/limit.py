"""``wbc-jax limit``: the physical limit of push recovery (:mod:`wbc_jax.jobs.limit`,
:mod:`wbc_jax.jobs.limit_rounds`)."""

from __future__ import annotations

from wbc_jax.commands import Command
from wbc_jax.jobs import limit


def run(cfg: limit.LimitConfig, progress: bool) -> dict:
    from wbc_jax.jobs import limit_rounds  # (imported when run: the flags need only the config)

    summary = limit_rounds.run(cfg, progress=progress)  # checks cfg first
    return {
        "body": cfg.body,
        "median_fraction_of_lip": summary["median_fraction_of_lip"],
        "targets": summary["targets"],
        "wall_s": summary["wall_s"],
        "device": summary["device"],
        "limit_ns": {str(a): r["limit_ns"] for a, r in summary["directions"].items()},
    }


COMMAND = Command(
    "limit",
    "the physical limit of push recovery: trajectory optimisation through MJX, "
    "bisection over the impulse, every limit replayed in C MuJoCo",
    limit.default_config,
    run,
    resumable=True,
)
