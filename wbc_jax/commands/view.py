"""``wbc-jax view``: a run (or one env of a push sweep) logged to rerun (:mod:`wbc_jax.jobs.view`)."""

from __future__ import annotations

from wbc_jax.commands import Command
from wbc_jax.jobs import view


def run(cfg: view.ViewConfig, progress: bool) -> dict:
    cfg.check()
    path = view.view(cfg.run_dir, cfg.env, out=cfg.out, spawn=cfg.spawn)
    return {"rrd": None if path is None else str(path), "spawned": bool(cfg.spawn)}


COMMAND = Command(
    "view", "log a run (or one env of a push sweep) to rerun: .rrd or viewer", view.default_config, run, compiles=False
)
