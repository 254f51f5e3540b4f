"""The model card's centre covariance calibration by detection score."""

from pathlib import Path

import numpy as np
import pytest

from posefuse.estimator.frontend.card import ModelCard, _cov_by_score, score_factor


def test_the_factor_of_a_score_is_its_bins():
    table = ((0.4, 20.0), (0.8, 3.0), (1.0, 1.0))
    assert [score_factor(table, s) for s in (0.0, 0.39, 0.4, 0.79, 0.95, 1.0)] == [
        20.0,
        20.0,
        3.0,
        3.0,
        1.0,
        1.0,
    ]
    assert score_factor((), 0.1) == 1.0  # no calibration: as voted


@pytest.mark.parametrize(
    "rows, message",
    [
        ([[0.8, 2.0], [0.4, 3.0]], "must ascend"),
        ([[0.0, 2.0]], "must ascend in"),
        ([[0.5, 0.5]], ">= 1"),
        ([[0.5, float("nan")]], "finite"),
    ],
)
def test_a_malformed_calibration_is_refused(rows, message):
    with pytest.raises(ValueError, match=message):
        _cov_by_score(rows)


def test_the_shipped_card_is_calibrated_and_round_trips():
    import json

    from posefuse.service.resources import DEFAULT_MODEL

    path = Path(DEFAULT_MODEL).with_suffix(".json")
    card = ModelCard.from_json(json.loads(path.read_text()), path)
    factors = [f for _, f in card.cov_by_score]
    assert factors and factors == sorted(factors, reverse=True)  # lower scores, wider
    again = ModelCard.from_json(card.to_json(), path)
    assert again.cov_by_score == card.cov_by_score
    assert np.isclose(again.cov_scale, card.cov_scale)
