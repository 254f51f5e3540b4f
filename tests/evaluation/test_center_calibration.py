"""Centre covariances by score: a bin whose NEES is k times a Gaussian's gets the factor k, an
honest one 1; the factors never fall as the score falls; a thin bin decides nothing."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from posefuse.evaluation.center_calibration import (
    factors_by_score,
    nees_table,
    trimmed_chi2_mean,
)


def _chi2_nees(rng, n: int, inflation: float) -> np.ndarray:
    """2D NEES of ``n`` centres whose errors are ``sqrt(inflation)`` times their stated spread."""
    e = rng.normal(size=(n, 2)) * np.sqrt(inflation)
    return (e**2).sum(axis=1)


def test_the_trimmed_mean_of_a_chi2_is_what_a_sample_gives():
    rng = np.random.default_rng(3)
    x = np.sort(rng.chisquare(2, 400_000))[: int(0.95 * 400_000)]
    assert trimmed_chi2_mean() == pytest.approx(x.mean(), rel=0.01)


def test_a_bin_k_times_too_confident_gets_the_factor_k_and_an_honest_one_1():
    rng = np.random.default_rng(0)
    scores = np.r_[np.full(4000, 0.3), np.full(4000, 0.95)]
    nees = np.r_[_chi2_nees(rng, 4000, 9.0), _chi2_nees(rng, 4000, 1.0)]
    rows = nees_table(scores, nees, (0.4, 0.9))
    assert [r["n"] for r in rows] == [4000, 0, 4000]
    assert rows[0]["factor"] == pytest.approx(9.0, rel=0.05)
    assert rows[2]["factor"] == pytest.approx(1.0, abs=0.05)
    factors = factors_by_score(scores, nees, (0.4, 0.9))
    # the empty middle bin takes the factor above it; the low one its own
    assert [u for u, _ in factors] == [0.4, 0.9, 1.0]
    assert factors[1][1] == factors[2][1] and factors[0][1] == pytest.approx(9.0, rel=0.05)


def test_a_thin_bin_takes_the_factor_above_it():
    rng = np.random.default_rng(1)
    scores = np.r_[np.full(5, 0.1), np.full(500, 0.8)]
    nees = np.r_[np.full(5, 500.0), _chi2_nees(rng, 500, 4.0)]
    factors = factors_by_score(scores, nees, (0.5,), min_matches=10)
    assert factors[0][1] == factors[1][1] == pytest.approx(4.0, rel=0.2)


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**31),
    inflations=st.lists(st.floats(0.2, 50.0), min_size=3, max_size=3),
)
def test_factors_are_at_least_one_and_never_fall_as_the_score_falls(seed, inflations):
    rng = np.random.default_rng(seed)
    scores = np.concatenate([np.full(50, s) for s in (0.2, 0.6, 0.95)])
    nees = np.concatenate([_chi2_nees(rng, 50, k) for k in inflations])
    factors = [f for _, f in factors_by_score(scores, nees, (0.4, 0.8))]
    assert all(f >= 1.0 for f in factors)
    assert all(a >= b for a, b in zip(factors, factors[1:], strict=False))


def test_bad_edges_and_lengths_are_refused():
    with pytest.raises(ValueError, match="increase within"):
        nees_table([0.5], [1.0], (0.8, 0.4))
    with pytest.raises(ValueError, match="differ in length"):
        nees_table([0.5, 0.6], [1.0], (0.4,))
