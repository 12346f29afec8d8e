"""``wbc-jax tune``: gain tuning in phases (:mod:`wbc_jax.tuning.orchestration.campaign`). It holds out its gain
sets with the held-out flags (``wbc-jax heldout``'s), whose robot and controller flags are the run's."""

from __future__ import annotations

import dataclasses
import json

from wbc_jax.commands import Command
from wbc_jax.tuning import config, heldout_config


@dataclasses.dataclass(frozen=True)
class TuneJob:
    """The tune command's two configs (each checked when it is made)."""

    tune: config.TuneConfig
    heldout: heldout_config.HeldoutConfig


def combine(tc: config.TuneConfig, hc: heldout_config.HeldoutConfig) -> TuneJob:
    return TuneJob(tc, dataclasses.replace(hc, robot=tc.robot, controller=tc.controller))


def run(cfg: TuneJob, progress: bool) -> dict:
    from wbc_jax.tuning.orchestration import campaign  # (imported when run: the flags need only the config)

    return json.loads(json.dumps(campaign.run(cfg.tune, cfg.heldout, progress=progress), default=str))


COMMAND = Command(
    "tune",
    "gain tuning in phases: gradient, CMA-ES, random search, held-out evaluation, the race's report",
    config.default_config,
    run,
    resumable=True,
    shared=((heldout_config.heldout_default_config, ("out", "robot", "controller")),),
    combine=combine,
)
