"""The voting's compiled loops against the numpy expressions they replace: the hypotheses, their
scores and the angles to a center to the bit, the line fit to rounding."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from posefuse.estimator.frontend.voting import (
    UNIT_TOLERANCE,
    VotingConfig,
    _cos_and_distance,
    _count_inliers,
    _finite_intersections,
    _intersections,
    _line_fit,
    _normal_equations,
    _percentile_90,
    _percentile_90_sorted,
    _round,
    _unit,
    labelled_pixels,
    vote_instances,
)


def _lines(seed: int, n: int, spread: float = 0.3):
    """(p, v): n pixels on a 48-cell grid and unit vectors roughly towards (20, 30)."""
    rng = np.random.default_rng(seed)
    p = rng.integers(0, 48, (n, 2)).astype(np.float64)
    v = np.array([20.0, 30.0]) - p + rng.normal(0, spread, (n, 2)) * 10
    v /= np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)
    return p, v


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 10_000), st.integers(2, 300), st.floats(0.99, 0.9999))
def test_hypotheses_and_their_scores_are_numpys_to_the_bit(seed, n, inlier_cos):
    p, v = _lines(seed, n)
    rng = np.random.default_rng(seed + 1)
    i, j = rng.integers(n, size=64), rng.integers(n, size=64)
    j[:4] = i[:4]  # a line with itself: parallel, no intersection
    h = _intersections(p, v, i, j)
    h = h[np.all(np.isfinite(h), axis=1)]
    got = _finite_intersections(p, v, i, j)
    assert got.shape == h.shape and np.array_equal(got, h)
    dx = h[:, 0, None] - p[None, :, 0]
    dy = h[:, 1, None] - p[None, :, 1]
    norm = np.sqrt(dx * dx + dy * dy)
    cos = (dx * v[None, :, 0] + dy * v[None, :, 1]) / np.maximum(norm, 1e-9)
    assert np.array_equal(_count_inliers(h, p, v, inlier_cos), (cos > inlier_cos).sum(1))
    for point in [h[0] if len(h) else np.zeros(2), p[0]]:  # p[0]: a zero offset
        d = point[None] - p
        want_cos = (d * v).sum(1) / np.maximum(np.linalg.norm(d, axis=1), 1e-9)
        got_cos, got_dist = _cos_and_distance(point, p, v)
        assert np.array_equal(got_cos, want_cos)
        assert np.array_equal(got_dist, np.linalg.norm(d, axis=1))


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 10_000), st.integers(3, 300))
def test_the_line_fit_is_the_normal_equations_to_rounding(seed, n):
    p, v = _lines(seed, n)
    use = np.random.default_rng(seed).random(n) < 0.7
    use[:3] = True
    x, A, sigma2 = _normal_equations(p[use], v[use])
    got_x, got_A, got_sigma2, solved = _line_fit(p, v, use)
    assert solved
    np.testing.assert_allclose(got_A, A, rtol=1e-12, atol=1e-12 * len(p))
    np.testing.assert_allclose(got_x, x, rtol=0, atol=1e-9 * (1 + np.abs(x).max()))
    assert got_sigma2 == np.float64(sigma2) or abs(got_sigma2 - sigma2) <= 1e-9 * (1 + sigma2)


def test_parallel_lines_have_no_point_and_vote_for_nothing():
    """Every vector alike: no pair intersects, the normal matrix is singular; the voting
    finds no instance instead of failing."""
    p = np.stack(np.meshgrid(np.arange(10.0), np.arange(10.0)), -1).reshape(-1, 2)
    v = np.tile([[0.6, 0.8]], (len(p), 1))
    assert not _line_fit(p, v, np.ones(len(p), bool))[3]
    assert len(_finite_intersections(p, v, np.arange(50), np.arange(50, 100))) == 0
    assert vote_instances(p, v, VotingConfig(min_inliers=5), seed=0) == []


def test_lines_along_one_line_have_no_point_until_one_crosses_them():
    """Lines all along one line have no point to meet at; one line across them fixes it."""
    p = np.stack([np.arange(30.0), np.zeros(30)], 1)
    v = np.tile([[1.0, 0.0]], (30, 1))
    assert not _line_fit(p, v, np.ones(30, bool))[3]
    v[0] = [0.0, 1.0]
    x, _, _, solved = _line_fit(p, v, np.ones(30, bool))
    assert solved and np.isfinite(x).all()


@settings(max_examples=100, deadline=None)
@given(st.lists(st.floats(0.0, 100.0), min_size=1, max_size=300))
def test_the_compiled_percentile_is_the_partial_sorts_to_the_bit(values):
    x = np.array(values)
    assert _percentile_90_sorted(x) == _percentile_90(x)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 10_000), st.integers(1, 24), st.sampled_from([np.float32, np.float64]))
def test_the_labelled_cells_are_nonzeros_in_its_order(seed, g, dtype):
    rng = np.random.default_rng(seed)
    logit = rng.normal(size=(g, g)).astype(dtype)
    vectors = rng.normal(size=(2, g, g)).astype(dtype)
    ys, xs = np.nonzero(logit > 0)
    pix, vec = labelled_pixels(logit, vectors)
    assert pix.dtype == vec.dtype == np.float64
    assert np.array_equal(pix, np.stack([xs, ys], 1).astype(np.float64))
    assert np.array_equal(vec, vectors[:, ys, xs].T.astype(np.float64))


def test_vectors_off_unit_length_are_normalised_and_unit_ones_left_as_they_are():
    p, v = _lines(3, 50)
    assert np.array_equal(_unit(v), v)
    scaled = v * 1.01  # beyond the tolerance: divided by its length
    np.testing.assert_allclose(_unit(scaled), v, rtol=1e-12, atol=1e-12)
    nearly = v * (1 + 0.5 * UNIT_TOLERANCE)  # within it: left bit for bit
    assert np.array_equal(_unit(nearly), nearly)


def _reference_vote(pixels, vectors, config, seed):
    """The voting in numpy expressions (its code before the compiled loops), for the tests."""
    rng = np.random.default_rng(seed)
    remaining = np.arange(len(pixels))
    out = []
    while len(remaining) >= config.min_inliers and len(out) < config.max_instances:
        p, v = pixels[remaining], vectors[remaining]
        i = rng.integers(len(p), size=config.n_hypotheses)
        j = rng.integers(len(p), size=config.n_hypotheses)
        h = _intersections(p, v, i, j)
        h = h[np.all(np.isfinite(h), axis=1)]
        if len(h) == 0:
            break
        if len(p) > config.max_scoring_pixels:
            sub = rng.choice(len(p), config.max_scoring_pixels, replace=False)
        else:
            sub = np.arange(len(p))
        ps, vs = p[sub], v[sub]
        dx = h[:, 0, None] - ps[None, :, 0]
        dy = h[:, 1, None] - ps[None, :, 1]
        norm = np.sqrt(dx * dx + dy * dy)
        cos = (dx * vs[None, :, 0] + dy * vs[None, :, 1]) / np.maximum(norm, 1e-9)
        d = h[int(np.argmax((cos > config.inlier_cos).sum(1)))][None] - p
        inliers = (d * v).sum(1) / np.maximum(np.linalg.norm(d, axis=1), 1e-9) > config.inlier_cos
        if inliers.sum() < config.min_inliers:
            break
        center, A, sigma2 = _normal_equations(p[inliers], v[inliers])
        d = center[None] - p
        dist = np.linalg.norm(d, axis=1)
        cos = (d * v).sum(1) / np.maximum(dist, 1e-9)
        strict = cos > config.inlier_cos
        if strict.sum() >= config.min_inliers:
            center, A, sigma2 = _normal_equations(p[strict], v[strict])
        core = dist[strict] if strict.sum() >= config.min_inliers else dist[inliers]
        radius = config.member_radius_factor * np.percentile(core, 90) + 2.0
        members = (((cos > config.member_cos) | inliers) & (dist <= radius)) | (dist < 3.0)
        cov = sigma2 * np.linalg.inv(A) * config.cov_scale + np.eye(2) * config.min_center_var
        out.append((center, cov, remaining[members]))
        remaining = remaining[~members]
    return out


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 10_000), st.integers(1, 4), st.floats(0.0, 0.05))
def test_the_voting_finds_what_its_numpy_expressions_find(seed, n_parts, noise):
    """Instances, their pixels and centers as the numpy reference finds them (centers and
    covariances to rounding), on fields of up to four parts, more pixels than the scoring
    subset included."""
    rng = np.random.default_rng(seed)
    centers = rng.uniform(10, 50, (n_parts, 2))
    ys, xs = np.mgrid[0:60, 0:60]
    pix = np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64)
    owner = np.argmin(np.linalg.norm(pix[:, None] - centers[None], axis=2), axis=1)
    near = np.linalg.norm(pix - centers[owner], axis=1) < 14
    pix, owner = pix[near], owner[near]
    vec = centers[owner] - pix + rng.normal(0, noise * 10, pix.shape)
    vec /= np.maximum(np.linalg.norm(vec, axis=1, keepdims=True), 1e-9)
    config = VotingConfig()
    want = _reference_vote(pix, vec, config, seed)
    got = vote_instances(pix, vec, config, seed)
    assert len(got) == len(want) >= 1
    for g, (center, cov, members) in zip(got, want, strict=True):
        assert np.array_equal(g.pixels, members)
        np.testing.assert_allclose(g.center, center, rtol=0, atol=1e-9)
        np.testing.assert_allclose(g.cov, cov, rtol=1e-9, atol=1e-15)


def test_inliers_on_one_line_are_set_aside_and_the_search_goes_on():
    """Pixels along one line, each pointing along it, and a few off it pointing away: every
    hypothesis lies on the line and gathers only the line's parallel vectors, whose fit has no
    point (``np.linalg.solve`` raised there). The round says so, and the voting sets those
    pixels aside instead of failing; a part elsewhere is still found."""
    line = np.stack([np.arange(30.0), np.zeros(30)], 1)
    away = np.array([[10.0, 5.0], [20.0, -5.0], [30.0, 7.0], [40.0, -6.0], [5.0, 9.0]])
    p = np.concatenate([line, away])
    v = np.concatenate([np.tile([[1.0, 0.0]], (30, 1)), np.array([[0.6, 0.8]] * 5)])
    v[30:, 1] *= np.sign(away[:, 1])  # away from the line
    h = np.array([[45.0, 0.0]])
    status, _, _, members = _round(h, p, v, np.zeros(0, np.int64), 0.99, 5, 0.9, 1.3, 1.0, 0.05)
    assert status == 2 and members[:30].all() and not members[30:].any()
    config = VotingConfig(min_inliers=5)
    assert vote_instances(p, v, config, seed=0) == []
    part, part_v = _lines(7, 120, spread=0.01)
    found = vote_instances(np.concatenate([p, part + 60]), np.concatenate([v, part_v]), config, 0)
    assert len(found) == 1 and np.linalg.norm(found[0].center - [80.0, 90.0]) < 1.0


def test_a_voting_config_out_of_range_is_refused_naming_the_field():
    for kw, field in [
        (dict(min_inliers=2), "min_inliers"),
        (dict(n_hypotheses=0), "n_hypotheses"),
        (dict(inlier_cos=1.0), "inlier_cos"),
        (dict(cov_scale=float("nan")), "cov_scale"),
        (dict(min_center_var=-1.0), "min_center_var"),
    ]:
        with pytest.raises(ValueError, match=field):
            VotingConfig(**kw)


@pytest.mark.parametrize("spread", [1e-7, 1e-3])
def test_whether_lines_meet_does_not_depend_on_their_direction(spread):
    """The same bundle of lines turned by 0, 45 and 90 degrees: solved alike (a bundle within a
    tenth of a microradian of parallel is not, one of a milliradian is)."""
    rng = np.random.default_rng(1)
    p = np.stack([np.arange(40.0), rng.normal(0, 3, 40)], 1)
    angles = rng.normal(0, spread, 40)
    solved = set()
    for turn in (0.0, np.pi / 4, np.pi / 2):
        c, s = np.cos(turn), np.sin(turn)
        R = np.array([[c, -s], [s, c]])
        v = np.stack([np.cos(angles), np.sin(angles)], 1) @ R.T
        solved.add(bool(_line_fit(p @ R.T, v, np.ones(40, bool))[3]))
    assert solved == {spread > 1e-5}
