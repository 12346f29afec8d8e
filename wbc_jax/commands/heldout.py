"""``wbc-jax heldout``: gain files on the held-out evaluation (:mod:`wbc_jax.tuning.orchestration.heldout`)."""

from __future__ import annotations

from wbc_jax.commands import Command
from wbc_jax.tuning import heldout_config


def run(cfg: heldout_config.HeldoutConfig, progress: bool) -> dict:
    from wbc_jax.tuning.orchestration import heldout  # (imported when run: the flags need only the config)

    return heldout.run(cfg, progress=progress)  # cfg checked when it was made


COMMAND = Command(
    "heldout",
    "gain files on the held-out grid, variations, one-foot task and sinusoid",
    heldout_config.heldout_default_config,
    run,
    resumable=True,
)
