"""Which hypothesis leads a verification: a flip only where the views agree on it."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from posefuse.estimator.core.geometry import so3_exp
from posefuse.estimator.verification.verify import (
    Verdict,
    VerificationConfig,
    alternative_turns,
)
from posefuse.estimator.verification.verify import lead_hypothesis as _lead

CONFIG = VerificationConfig()


def lead_hypothesis(per_view, R, comp, var, w, config):
    """The lead with a config's flip settings."""
    return _lead(
        per_view,
        R,
        comp,
        var,
        w,
        flip_z=config.flip_z,
        flip_min_views=config.flip_min_views,
        flip_deg=config.flip_deg,
    )


R_FAV = so3_exp(np.array([0.3, -0.2, 0.1]))
FLIP = so3_exp(np.array([np.pi, 0.0, 0.0]))  # end over end, about the object's x axis
NEAR = so3_exp(np.array([0.0, 0.0, np.deg2rad(30.0)]))


def _hypotheses(turn: np.ndarray):
    """Two hypotheses of one component (the favourite as it is, and turned by ``turn``) and a
    lighter second component: R (3, 3, 3), component (3,), variant (3,), weights (2,)."""
    R = np.stack([R_FAV, R_FAV @ turn, so3_exp(np.array([-1.0, 0.5, 0.2]))])
    return R, np.array([0, 0, 1]), np.array([0, 1, 0]), np.array([0.7, 0.3])


# per view, the favourite's cost and the flip's: half the views prefer each, and the flip's
# mean is lower by 0.012 (the duck of a real photograph, with a box mask)
SCATTERED = np.array(
    [
        [0.52, 0.50, 0.55, 0.50, 0.56, 0.50],
        [0.48, 0.58, 0.52, 0.44, 0.60, 0.45],
    ]
)
# every view prefers the flip by about as much
AGREEING = np.array(
    [
        [0.52, 0.50, 0.55, 0.50, 0.56, 0.50],
        [0.45, 0.44, 0.49, 0.45, 0.50, 0.43],
    ]
)


def _per_view(two_rows: np.ndarray) -> np.ndarray:
    """(3, V): the two rows, and a third hypothesis that fits every view badly."""
    return np.vstack([two_rows, np.full((1, two_rows.shape[1]), 0.9)])


def test_a_flip_the_views_disagree_on_leaves_the_lead_to_the_favourite():
    R, comp, var, w = _hypotheses(FLIP)
    per_view = _per_view(SCATTERED)
    assert per_view.mean(axis=1).argmin() == 1  # the flip has the lowest mean cost
    assert lead_hypothesis(per_view, R, comp, var, w, CONFIG) == 0


def test_a_flip_every_view_prefers_leads():
    R, comp, var, w = _hypotheses(FLIP)
    assert lead_hypothesis(_per_view(AGREEING), R, comp, var, w, CONFIG) == 1


def test_with_two_views_the_lowest_mean_cost_leads():
    R, comp, var, w = _hypotheses(FLIP)
    per_view = _per_view(SCATTERED)[:, [0, 3]]  # one view each way, the flip lower on average
    assert lead_hypothesis(per_view, R, comp, var, w, CONFIG) == 1


def test_a_turn_short_of_a_flip_leads_by_its_mean_cost():
    R, comp, var, w = _hypotheses(NEAR)
    assert lead_hypothesis(_per_view(SCATTERED), R, comp, var, w, CONFIG) == 1


def test_without_the_rule_the_lowest_mean_cost_leads():
    R, comp, var, w = _hypotheses(FLIP)
    off = replace(CONFIG, flip_z=None)
    assert lead_hypothesis(_per_view(SCATTERED), R, comp, var, w, off) == 1


def test_the_favourite_kept_publishes_the_flip_beside_it_as_just_as_likely():
    R, comp, var, w = _hypotheses(FLIP)
    per_view = _per_view(SCATTERED)
    best = lead_hypothesis(per_view, R, comp, var, w, CONFIG)
    verdict = Verdict(R, comp, var, per_view.mean(axis=1), per_view, w, best)
    turns, odds = alternative_turns(verdict, CONFIG.temperature)
    assert len(turns) == 1
    np.testing.assert_allclose(R[best] @ turns[0], R[1], atol=1e-9)
    assert odds[0] == pytest.approx(1.0)


def test_a_flip_of_another_component_kept_back_is_published_beside_the_favourite():
    # the flip is the lighter component as it is, not a variant of the favourite
    R = np.stack([R_FAV, so3_exp(np.array([0.1, 0.0, 0.0])) @ R_FAV, R_FAV @ FLIP])
    comp, var, w = np.array([0, 0, 1]), np.array([0, 1, 0]), np.array([0.7, 0.3])
    per_view = SCATTERED[[0, 0, 1]] + np.array([[0.0], [0.3], [0.0]])
    best = lead_hypothesis(per_view, R, comp, var, w, CONFIG)
    assert best == 0
    cost = per_view.mean(axis=1)
    kept = Verdict(R, comp, var, cost, per_view, w, best, overruled=2)
    turns, odds = alternative_turns(kept, CONFIG.temperature)
    flip = [k for k, turn in enumerate(turns) if np.allclose(R[0] @ turn, R[2], atol=1e-9)]
    assert len(flip) == 1 and odds[flip[0]] == pytest.approx(1.0)
    # without the flip kept back, only the favourite's own variants are its alternatives
    turns, odds = alternative_turns(replace(kept, overruled=-1), CONFIG.temperature)
    assert len(turns) == 1 and np.allclose(R[0] @ turns[0], R[1], atol=1e-9)


@settings(max_examples=60, deadline=None)
@given(
    costs=st.lists(st.floats(0.0, 1.0), min_size=9, max_size=18),
    heavy=st.integers(0, 1),
)
def test_the_lead_is_the_lowest_mean_cost_or_the_favourite(costs, heavy):
    V = len(costs) // 3
    per_view = np.asarray(costs[: 3 * V]).reshape(3, V)
    R, comp, var, w = _hypotheses(FLIP)
    w = w if heavy == 0 else w[::-1]
    lead = lead_hypothesis(per_view, R, comp, var, w, CONFIG)
    lowest = int(per_view.mean(axis=1).argmin())
    favourite = 0 if heavy == 0 else 2
    assert lead in (lowest, favourite)
    if lead != lowest:  # the favourite kept: a flip, over enough views that disagree
        assert V >= CONFIG.flip_min_views
        gain = per_view[favourite] - per_view[lowest]
        assert gain.mean() < CONFIG.flip_z * gain.std(ddof=1) / np.sqrt(V)


@pytest.mark.parametrize(
    "change", [{"flip_z": -0.5}, {"flip_z": float("nan")}, {"flip_min_views": 1}, {"flip_deg": 0.0}]
)
def test_a_flip_rule_that_cannot_work_is_refused(change):
    with pytest.raises(ValueError, match="invalid verification config"):
        VerificationConfig(**change)
