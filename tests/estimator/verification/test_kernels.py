"""The verification's compiled kernels (estimator.verification.kernels) against the numpy code
they replace, kept as the reference: the faces that show, the chamfer sums of the scoring, the
refinement's data term with its Jacobian, and a whole refinement, agree to rounding."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_refinement import _smooth_views, _tube_refinement
from test_verification import CONFIG, _edges, _random_poses, _tube

from posefuse.estimator.core.geometry import so3_exp
from posefuse.estimator.verification.model_edges import ModelEdges, pose_edges
from posefuse.estimator.verification.refinement import (
    EdgeScoring,
    RefineConfig,
    _data,
    _ViewStack,
)
from posefuse.estimator.verification.verify import score_hypotheses


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    stride=st.sampled_from([1, 3]),
    crease_weight=st.sampled_from([0.0, 0.5]),
    mask_weight=st.sampled_from([0.0, 1.5]),
    spread=st.sampled_from([0.005, 0.05]),
)
def test_the_compiled_data_term_is_the_numpy_one(seed, stride, crease_weight, mask_weight, spread):
    """Cost, information and gradient of random sample sets at random poses, views with and
    without a mask, samples inside the Huber bound, past it, and (spread 0.05 m) past the map's
    edge, where they read the truncation and leave the fit."""
    rng = np.random.default_rng(seed)
    P, bins, V = 80, 8, 3
    points = rng.uniform(-0.03, 0.03, size=(P, 3))
    directions = rng.normal(size=(P, 3))
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    edges = ModelEdges(points, directions, np.zeros((P, 2, 3)), np.zeros(P, bool), 0.08)
    views = _smooth_views(rng, V, bins, list(rng.random(V) < 0.6))
    # a view's maps differ by orientation bin, so a sample's bin matters here
    views = [dataclasses.replace(v, dcdt=np.roll(v.dcdt, k, axis=2)) for k, v in enumerate(views)]
    views = [
        dataclasses.replace(v, dcdt=v.dcdt + np.arange(bins, dtype=np.uint8)[:, None, None] * 7)
        for v in views
    ]
    stack = _ViewStack.of(views)
    contour = rng.random((V, P)) < 0.4
    crease = ~contour & (rng.random((V, P)) < 0.5)
    config = RefineConfig(sample_stride=stride, points_per_view=20.0)
    scoring = EdgeScoring(10.0, bins, crease_weight, mask_weight)
    R = so3_exp(rng.normal(size=3))
    t = rng.normal(size=3) * spread
    for want_jacobian in (True, False):
        fast = _data(edges, stack, R, t, (contour, crease), scoring, config, want_jacobian)
        numpy_config = dataclasses.replace(config, compiled=False)
        ref = _data(edges, stack, R, t, (contour, crease), scoring, numpy_config, want_jacobian)
        assert ref[0] > 0
        np.testing.assert_allclose(fast[0], ref[0], rtol=1e-12)
        scale = max(np.abs(ref[1]).max(), 1e-300)
        np.testing.assert_allclose(fast[1], ref[1], rtol=1e-9, atol=1e-12 * scale)
        np.testing.assert_allclose(fast[2], ref[2], rtol=1e-9, atol=1e-12 * np.abs(ref[2]).max())


def test_the_compiled_faces_are_the_numpy_ones(robi_catalog):
    """Contour and active samples of 200 random poses of the tube fitting, with its occlusion
    table (the viewpoints' own faces decide which samples the table answers): the same."""
    model, _, _ = _tube(robi_catalog)
    edges = _edges(model)
    R, t = _random_poses(model, 200, seed=4)
    fast = pose_edges(edges, R, t, compiled=True)
    ref = pose_edges(edges, R, t, compiled=False)
    np.testing.assert_array_equal(fast[2], ref[2])
    np.testing.assert_array_equal(fast[3], ref[3])
    assert 0 < ref[3].sum() < ref[2].sum()  # some contour, some creases: the test says something


def test_the_compiled_chamfer_scores_are_the_numpy_ones(robi_catalog):
    """score_hypotheses of 12 hypotheses in three views, one without a mask."""
    model, T_world_obj, views = _tube(robi_catalog)
    views = [views[0], dataclasses.replace(views[1], mask_dt=None), views[2]]
    edges = _edges(model)
    rng = np.random.default_rng(3)
    R = np.array([T_world_obj[:3, :3] @ so3_exp(rng.normal(0.0, 0.5, 3)) for _ in range(12)])
    for config in (CONFIG, dataclasses.replace(CONFIG, mask_weight=0.0, crease_weight=0.0)):
        fast = score_hypotheses(edges, views, R, T_world_obj[:3, 3], config)
        ref = score_hypotheses(
            edges, views, R, T_world_obj[:3, 3], dataclasses.replace(config, compiled=False)
        )
        np.testing.assert_allclose(fast, ref, rtol=0, atol=1e-12)
        assert np.ptp(ref) > 0.1


def test_a_compiled_refinement_ends_where_the_numpy_one_does(robi_catalog):
    """The tube fitting refined from 6 degrees off, both ways: the same steps, accepted, and
    the same pose and covariance to rounding."""
    *_, fast = _tube_refinement(robi_catalog, RefineConfig())
    *_, ref = _tube_refinement(robi_catalog, RefineConfig(compiled=False))
    assert fast.accepted and ref.accepted and fast.iterations == ref.iterations > 1
    np.testing.assert_allclose(fast.R_world_obj, ref.R_world_obj, rtol=0, atol=1e-12)
    np.testing.assert_allclose(fast.t_world_obj, ref.t_world_obj, rtol=0, atol=1e-12)
    np.testing.assert_allclose(fast.cov, ref.cov, rtol=1e-8, atol=1e-20)
    np.testing.assert_allclose(fast.cost, ref.cost, rtol=1e-12)


def test_a_kernel_with_nowhere_to_cache_is_compiled_all_the_same(monkeypatch):
    """Where numba finds no folder to keep its cache in (a read-only install, no home), a
    kernel is compiled in the process instead of failing at import."""
    import numba.core.caching
    from numba import njit

    from posefuse.estimator.verification.kernels import _compiled

    monkeypatch.setattr(numba.core.caching.CacheImpl, "_locator_classes", [])

    def twice(x):
        return 2 * x

    with pytest.raises(RuntimeError, match="no locator"):
        njit(cache=True)(twice)
    assert _compiled(twice)(21) == 42


def test_the_warm_up_compiles_the_only_version_a_check_uses(robi_catalog):
    """numba compiles a kernel once per argument layout: the warm-up's version is the one a
    refinement and a verification use (a view such as T[:, :3, :3] passed as it is would compile
    another, seconds in the middle of a check)."""
    from posefuse.estimator.verification import kernels

    kernels.compile_kernels()
    *_, out = _tube_refinement(robi_catalog, RefineConfig())
    model, T_world_obj, views = _tube(robi_catalog)
    R = np.array([T_world_obj[:3, :3] @ so3_exp(np.array([0.0, 0.0, a])) for a in (0.0, 0.3)])
    score_hypotheses(_edges(model), views, R, T_world_obj[:3, 3], CONFIG)
    assert out.accepted
    for kernel in (kernels.data_term, kernels.chamfer_costs, kernels.facing_sets):
        assert len(kernel.signatures) == 1, kernel.signatures
