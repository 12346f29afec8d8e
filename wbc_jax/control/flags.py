"""The controller's job flags, declared once: every job that runs the controller holds a
:class:`ControllerFlags` as a nested field (:func:`wbc_jax.core.options.nested`), so ``--tasks``,
``--forces``, ``--postural``, ``--angular-weight-soft``, ``--qp-warm-start``, ``--qp-unrolled-steps`` and ``--qp-engine``
mean the same in balance, push-sweep, envelope, limit, tune and heldout."""

from __future__ import annotations

import dataclasses

from wbc_jax.control import qp
from wbc_jax.control.controller import FORCE_MODES, ControllerConfig
from wbc_jax.control.torques import POSTURAL_VARIANTS
from wbc_jax.core import constants
from wbc_jax.core.options import option


@dataclasses.dataclass(frozen=True)
class ControllerFlags:
    """The controller settings a job takes from its command line (the rest of
    :class:`~wbc_jax.control.controller.ControllerConfig` keeps its defaults)."""

    tasks: str | None = option(
        None,
        "task/contact file (JSON/YAML): motion tasks, contacts, scene objects, initial posture; "
        "e.g. experiments/tasks/reach_circle.yaml, experiments/tasks/hand_on_table.yaml",
        metavar="FILE",
        input_file=True,
    )
    forces: str = option("qp", "force distribution", choices=FORCE_MODES)
    postural: str = option("stable", "postural task variant", choices=POSTURAL_VARIANTS)
    angular_weight_soft: float = option(
        1.0,
        "soft momentum QP: weight of the angular-momentum rate against the linear one where a push asks for "
        "more than the feet can give (1: WBC; < 1: the CoM first, the upper body absorbs the rest)",
        gt=constants.ANGULAR_WEIGHT_RANGE[0],
        le=constants.ANGULAR_WEIGHT_RANGE[1],
    )
    qp_warm_start: bool = option(
        False,
        "start each tick's force QP from the last tick's multipliers and slacks: fewer interior-point steps "
        "(the batch's slowest after a push 10 instead of 14), at a tighter tolerance (BENCHMARKS.md, issue 46)",
    )
    qp_unrolled_steps: int = option(
        0,
        "the force QP's first Newton steps written out before its while loop (the same solutions; on a GPU each "
        "pass of the loop waits for its predicate on the host: BENCHMARKS.md, issue 46)",
        ge=0,
        le=qp.DEFAULT_ITERATIONS,
    )
    qp_engine: str = option(
        "auto",
        "the force QP's solver: auto (where no warm start or unrolled steps are asked for, warp_active_set on a GPU "
        "with warp-lang and eiquadprog in a CPU program where it builds, else jax; the job's fingerprint records the "
        "engine it names), jax (the interior "
        "point), warp (the same as one Warp kernel, one thread per problem, "
        "wbc_jax/control/qp_warp.py), warp_active_set (the dual active-set method as one Warp kernel: the exact "
        "solution, no --qp-warm-start) or eiquadprog (the same method by eiquadprog on the CPU); the Warp engines "
        "need warp-lang, eiquadprog the 'eiquadprog' extra; all but jax take --qp-unrolled-steps 0",
        choices=qp.ENGINE_CHOICES,
    )

    def config(self, base: ControllerConfig | None = None) -> ControllerConfig:
        """``base`` (default: the defaults) with these settings (the jobs' configs check the declared
        ranges first; :class:`ControllerConfig` checks the values again)."""
        return dataclasses.replace(
            base or ControllerConfig(),
            forces=self.forces,
            postural=self.postural,
            angular_weight_soft=self.angular_weight_soft,
            qp_warm_start=self.qp_warm_start,
            qp_unrolled_steps=self.qp_unrolled_steps,
            qp_engine=self.qp_engine,
        )
