"""tuning/quality: the zeroth-order population is evaluated in calls that fit ENVS_PER_CALL (the race's 2,048 pushes x
129 candidates asked one H200 for 168 GiB), with every candidate's value where it belongs."""

import jax.numpy as jnp
import numpy as np

from wbc_jax.tuning.orchestration import quality


def test_candidates_per_call_caps_the_rollouts_of_one_call():
    assert quality.candidates_per_call(129, 2048) == quality.ENVS_PER_CALL // 2048 == 8
    assert quality.candidates_per_call(5, 4) == 5  # all fit: one call, as before
    assert quality.candidates_per_call(3, quality.ENVS_PER_CALL + 1) == 1  # never zero


def test_evaluate_in_calls_keeps_each_candidate_value():
    rng = np.random.default_rng(0)
    points, filler = rng.normal(size=(11, 3)), np.zeros(3)
    calls = []

    def pop(batch, scen):  # a population program of 4 candidates: J = w . p + scen
        assert batch.shape == (4, 3)
        calls.append(np.asarray(batch))
        return (batch @ jnp.asarray([1.0, -2.0, 0.5]) + scen,)

    values = quality.evaluate(pop, 4, lambda p: p, points, filler, 0.25)
    np.testing.assert_allclose(values, points @ np.array([1.0, -2.0, 0.5]) + 0.25, rtol=1e-6)
    assert len(calls) == 3 and np.all(calls[-1][3:] == filler)  # 11 = 4 + 4 + 3, padded with the filler
