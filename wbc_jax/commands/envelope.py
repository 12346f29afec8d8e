"""``wbc-jax envelope``: the recovery envelope by batched bisection (:mod:`wbc_jax.jobs.envelope`)."""

from __future__ import annotations

from wbc_jax.commands import Command
from wbc_jax.jobs import envelope


def run(cfg: envelope.EnvelopeConfig, progress: bool) -> dict:
    found = envelope.search(cfg, progress=progress)  # checks cfg first
    return {
        "rollouts": found["rollouts"],
        "grid_rollouts": found["grid_rollouts"],
        "rounds": found["rounds"],
        "backend": found["backend"],
        "run_s": found["run_s"],
        "compile_s": found["compile_s"],
        "started_s": found["started_s"],
        "impulse_ns": {str(a): e["impulse_ns"] for a, e in found["envelope"][0].items()},
    }


COMMAND = Command(
    "envelope", "recovery envelope by batched bisection over the sweep's magnitudes", envelope.default_config, run
)
