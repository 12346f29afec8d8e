"""The persistent compilation cache's key (the lowered text) of a program does not depend on what the process
traced before it.

The race's hybrid compiles the tuning gradient program once per budget in one process; before
``runner.lower_fresh`` the second and third compiles missed the carried cache (their lowered text differed from
the first's in how private functions were shared), costing 214 and 225 s on one H200 inside 150 and 300 s budget
halves (docs/tuning/README.md, "The race, scheduled gains")."""

import hashlib

import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

from wbc_jax.sim import runner
from wbc_jax.tuning import config
from wbc_jax.tuning.algorithms import gradient
from wbc_jax.tuning.algorithms import problem as tp


@pytest.mark.slow  # lowers the tuning gradient program through the closed loop three times (minutes of CPU)
@pytest.mark.timeout(2400)
def test_gradient_program_lowers_to_the_same_text_whatever_was_traced_before():
    tc = config.TuneConfig(batch=2, horizon=0.1, push_onset=0.0, duration_range=(0.02, 0.05), eval_horizon=0.1)
    problem = tp.make_problem(tc)
    opt = gradient.make_optimizer(tc.lr, tc.clip_norm)
    flat0, unravel = ravel_pytree(problem.init_params())

    def text(shift: float, fresh: bool) -> str:
        params = unravel(jnp.asarray(np.asarray(flat0) + shift, flat0.dtype))  # the hybrid's other starts
        step = gradient.GradientStep(problem, opt)
        params_b, _, rollouts, _, _ = step.rows_of(params, 0)
        program = step.grads.program  # one device: the jitted program
        lowered = runner.lower_fresh(program, params_b, rollouts) if fresh else program.lower(params_b, rollouts)
        return hashlib.sha256(lowered.as_text().encode()).hexdigest()

    first = text(0.0, fresh=True)
    assert text(0.1, fresh=True) == first  # traced second in the process, another start: the same key
    assert text(0.2, fresh=False) != first  # the cause: without clearing, the text depends on earlier traces
