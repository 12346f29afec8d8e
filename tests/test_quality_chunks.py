"""tuning/quality: the zeroth-order population is evaluated in calls that fit ENVS_PER_CALL (the race's 2,048 pushes x
129 candidates asked one H200 for 168 GiB), with every candidate's value where it belongs."""

import jax.numpy as jnp
import numpy as np
import pytest

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


def test_snr_of_heavy_tailed_float32_rows_is_finite():
    """A few diverging rollouts give per-rollout gradients near float32's range; their variance must not
    overflow (it did: snr 0.0). One row of 1e30 among 63 of a mean of 1: SNR = |m|^2 / (tr Cov / n)."""
    rng = np.random.default_rng(0)
    rows = (1.0 + 0.1 * rng.standard_normal((64, 3))).astype(np.float32)
    rows[5] = 1e30
    expected = (lambda r: r.mean(0) @ r.mean(0) / (r.var(0, ddof=1).sum() / len(r)))(rows.astype(np.float64))
    got = quality.snr(rows)
    assert np.isfinite(got) and got > 0
    assert got == pytest.approx(expected, rel=1e-12)
    # one outlier x among n rows: |m|^2 ~ D (x/n)^2 and tr Cov / n ~ D x^2 / n^2, so the SNR is about 1
    assert got == pytest.approx(1.0, rel=0.05)
