"""The bisection envelope: the search against an oracle of known thresholds, and against a grid
sweep on the C MuJoCo engine."""

import json

import numpy as np
import pandas as pd
import pytest

from wbc_jax.core import provenance
from wbc_jax.jobs import envelope, sweep, sweep_config

# The documented grid: 64 pushes of 10-400 N for 0.1 s.
GRID = np.linspace(10.0, 400.0, 64) * 0.1


def _threshold_oracle(thresholds, asked):
    """Survival iff the impulse is at most the search's threshold; records who was asked."""

    def survives(k, impulse):
        assert k.shape == impulse.shape and len(set(k.tolist())) == k.size
        asked.append(k.copy())
        return impulse <= thresholds[k]

    return survives


def test_bisection_brackets_the_grids_monotone_envelope():
    rng = np.random.default_rng(3)
    thresholds = np.concatenate([rng.uniform(0.0, 41.0, 200), GRID[[0, 5, 62, 63]], [0.5, 45.0]])
    asked = []
    found = envelope.bisect(GRID, _threshold_oracle(thresholds, asked), thresholds.size, 0.25)
    # What a grid sweep reports: the largest grid impulse below the first failure (0: none survived).
    grid_monotone = np.array([GRID[GRID <= t].max() if t >= GRID[0] else 0.0 for t in thresholds])
    top = thresholds >= GRID[-2]  # the largest grid impulse is taken as a fall without running it
    np.testing.assert_array_equal(found["grid_lo"][~top], grid_monotone[~top])
    np.testing.assert_array_equal(found["grid_lo"][top], GRID[-2])
    assert np.all(found["at_cap"] == top)
    # The refined bracket holds the threshold (below the cap) and is at most 0.25 N s wide.
    inside = ~top | (thresholds < GRID[-1])
    assert np.all(found["lo"][inside] <= thresholds[inside]) and np.all(thresholds[inside] < found["hi"][inside])
    assert np.all(found["hi"] - found["lo"] <= 0.25 + 1e-12) and np.all(found["hi"] - found["lo"] > 0.1)
    # Within the grid step above the grid's envelope (0-1 N s below the first grid impulse).
    step_above = np.concatenate([[0.0], GRID, [np.inf]])[np.searchsorted(GRID, grid_monotone, side="right") + 1]
    assert np.all((found["lo"] >= found["grid_lo"]) & (found["lo"] < step_above))
    # 6 rounds on the 64 grid impulses, 2 inside a step (0.62 N s; the first, 0-1 N s, is the widest).
    assert found["rounds"] == 8 and found["rollouts"] == 8 * thresholds.size
    assert envelope.rounds_needed(GRID, 0.25) == (6, 2)
    assert sum(a.size for a in asked) == found["rollouts"]


def test_closed_searches_are_not_run_again():
    """A grid of 5 impulses: searches whose bracket closes after 2 rounds are not asked a third time."""
    grid = np.array([1.0, 2.0, 3.0, 4.0, 5.0])
    thresholds = np.array([0.0, 1.5, 2.5, 3.5, 9.0])
    asked = []
    found = envelope.bisect(grid, _threshold_oracle(thresholds, asked), 5, 1.0)
    np.testing.assert_array_equal(found["grid_lo"], [0.0, 1.0, 2.0, 3.0, 4.0])
    assert envelope.rounds_needed(grid, 1.0) == (3, 0)
    assert [a.size for a in asked] == [5, 5, 2] and found["rollouts"] == 12


def test_bad_search_input():
    with pytest.raises(ValueError, match="sorted 1-D array of distinct positive"):
        envelope.bisect(np.array([2.0, 1.0]), lambda k, i: i < 1, 1, 0.25)
    with pytest.raises(ValueError, match="resolution must be a positive"):
        envelope.bisect(GRID, lambda k, i: i < 1, 1, float("nan"))
    with pytest.raises(ValueError, match=r"--magnitudes must be a number in \(0, 5000\] N, got 0"):
        envelope.search(sweep_config.SweepConfig(magnitudes=(0.0, 50.0), out=None), progress=False)
    with pytest.raises(ValueError, match=r"--resolution must be a number in \[0.001, 1000\] N s, got 0"):
        envelope.search(sweep_config.SweepConfig(out=None), resolution=0.0, progress=False)
    with pytest.raises(ValueError, match=r"--resolution 0.001 N s needs 22 bisection rounds inside a grid step"):
        envelope.search(
            envelope.EnvelopeConfig(magnitudes=(5000.0,), push_duration=0.5, horizon=2.0, resolution=1e-3, out=None),
            progress=False,
        )


@pytest.mark.slow  # 40 CPU s on the 2-core CI machine; the default set keeps the bisection's own tests
def test_search_matches_a_grid_sweep_on_c_mujoco(tmp_path):
    """Two directions, pushes of 1-8 N s in 1 N s steps: the search's grid bracket is the grid's
    monotone envelope, its answer within the step above it, in 5 rounds (10 rollouts, 16 for the grid);
    each round's searches run in batches of --chunk-size 1 (one compiled shape for both)."""
    common = dict(magnitudes=tuple(np.linspace(10.0, 80.0, 8)), directions=(0.0, 180.0), backend="mujoco", chunk_size=1)
    grid = sweep.run_sweep(sweep_config.SweepConfig(**common, out=str(tmp_path / "grid")), progress=False)
    found = envelope.search(envelope.EnvelopeConfig(**common, out=str(tmp_path / "env")), progress=False)
    table = pd.read_parquet(tmp_path / "grid" / "results.parquet")
    for az in (0.0, 180.0):
        rows = table[table["azimuth_deg"] == az].sort_values("impulse_ns")
        alive = rows["survived"].to_numpy()
        assert alive[0] and not alive[-1] and np.all(np.diff(alive.astype(int)) <= 0), "a monotone boundary inside"
        e = found["envelope"][0][az]
        assert e["grid_impulse_ns"] == pytest.approx(grid["envelope"][az]["monotone_impulse_ns"])
        assert e["grid_impulse_ns"] <= e["impulse_ns"] < e["grid_impulse_ns"] + 1.0
        assert e["bracket_ns"][1] - e["bracket_ns"][0] <= 0.25 and not e["at_cap"]
    assert found["rounds"] == 5 and found["rollouts"] == 10 and found["grid_rollouts"] == 16
    written = json.loads((tmp_path / "env" / "summary.json").read_text())
    assert written["rollouts"] == 10 and written["device"] == provenance.device_label()
    # The same search again into its folder redoes it; with other settings it is refused, naming them.
    again = envelope.search(envelope.EnvelopeConfig(**common, out=str(tmp_path / "env")), progress=False)
    assert again["envelope"] == found["envelope"]
    with pytest.raises(
        ValueError, match=r"holds an envelope run made with other inputs \(config.resolution: 0.25 -> 0.5"
    ):
        envelope.search(envelope.EnvelopeConfig(**common, resolution=0.5, out=str(tmp_path / "env")), progress=False)
