"""Refinement of a track's full pose over all its views (estimator.verification.refinement): it
converges back from a 10 degree / 0.05 d perturbation on renders, its gradient is the cost's
derivative, it refuses what it may not do, and a warm start saves work without changing where it
ends."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from test_verification import CONFIG, _edges, _tube

from posefuse.estimator.core.geometry import invert, so3_exp
from posefuse.estimator.nbv import look_at
from posefuse.estimator.rotation.mixture import closest_equivalent
from posefuse.estimator.verification.edge_maps import EdgeView
from posefuse.estimator.verification.model_edges import ModelEdges
from posefuse.estimator.verification.refinement import (
    EdgeScoring,
    PoseGuess,
    PosePrior,
    RefineConfig,
    _linearize,
    _ViewStack,
    refine_pose,
)

_TUBE: dict = {}


def _tube_once(robi_catalog):
    """_tube's render and the model's edges, made once per process (they never change)."""
    if not _TUBE:
        model, T_world_obj, views = _tube(robi_catalog)
        _TUBE.update(model=model, T=T_world_obj, views=views, edges=_edges(model))
    return _TUBE["model"], _TUBE["T"], _TUBE["views"], _TUBE["edges"]


def _refine_from(model, edges, views, R0, t0, config, **kwargs):
    """refine_pose from (R0, t0) with the priors there: 0.1 d on the translation, 20 degrees
    on the rotation, the verification's edge settings."""
    return refine_pose(
        edges,
        views,
        PoseGuess(R0, t0),
        PosePrior(t0, np.eye(3) * (0.1 * model.diameter) ** 2, np.eye(3) * np.deg2rad(20.0) ** 2),
        EdgeScoring.of(CONFIG),
        config,
        **kwargs,
    )


def _starts_ten_degrees_and_five_percent_off(model, R_true, t_true, n=3, seed=7):
    """n starts (R0, t0), each turned 10 degrees about a random axis and moved 0.05 d in a
    random direction from the truth."""
    rng = np.random.default_rng(seed)
    starts = []
    for _ in range(n):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        shift = rng.normal(size=3)
        shift *= 0.05 * model.diameter / np.linalg.norm(shift)
        starts.append((so3_exp(np.deg2rad(10.0) * axis) @ R_true, t_true + shift))
    return starts


@pytest.mark.parametrize("stride", [1, 3])
def test_refinement_converges_back_from_ten_degrees_and_five_percent(robi_catalog, stride):
    """From 10 degrees and 0.05 d off, back within 2 degrees and 0.02 d; also reading every
    third edge sample only (RefineConfig.sample_stride), each standing for three."""
    model, T_world_obj, views, edges = _tube_once(robi_catalog)
    R_true, t_true = T_world_obj[:3, :3], T_world_obj[:3, 3]
    discrete = np.concatenate([np.eye(3)[None], model.symmetries_discrete[:, :3, :3]])
    for R0, t0 in _starts_ten_degrees_and_five_percent_off(model, R_true, t_true):
        # the prior sits where the start is: it does not know the truth
        config = RefineConfig(iterations=20, sample_stride=stride)
        out = _refine_from(model, edges, views, R0, t0, config)
        assert out.accepted and out.cost < out.cost_start
        _, angle = closest_equivalent(out.R_world_obj, R_true, discrete, np.zeros((0, 3)))
        assert np.rad2deg(angle) < 2.0
        assert np.linalg.norm(out.t_world_obj - t_true) < 0.02 * model.diameter
        # the covariance is a proper one, and tighter than the priors
        assert np.all(np.linalg.eigvalsh(out.cov) > 0)
        assert np.trace(out.cov[3:, 3:]) < 3 * np.deg2rad(20.0) ** 2


def test_the_published_covariance_adds_its_floor_and_covers_the_error(robi_catalog):
    """From three starts 10 degrees and 0.05 d off, the refined pose's error, translation and
    rotation (left perturbation, world frame, to the closest symmetric equivalent), lies
    inside the published covariance's 99% ellipsoid (chi2 with 6 degrees of freedom). The floor
    is added to the inverse information and changes nothing else: without it the pose, cost
    and steps are the same to the bit, and the covariance is the floored one less the floor."""
    from posefuse.estimator.core.geometry import so3_log

    model, T_world_obj, views, edges = _tube_once(robi_catalog)
    R_true, t_true = T_world_obj[:3, :3], T_world_obj[:3, 3]
    discrete = np.concatenate([np.eye(3)[None], model.symmetries_discrete[:, :3, :3]])
    config = RefineConfig(iterations=20)
    bare = dataclasses.replace(config, floor_translation_frac=0.0, floor_rotation_deg=0.0)
    floor = np.diag(
        [(config.floor_translation_frac * model.diameter) ** 2] * 3
        + [np.deg2rad(config.floor_rotation_deg) ** 2] * 3
    )
    for R0, t0 in _starts_ten_degrees_and_five_percent_off(model, R_true, t_true):
        out = _refine_from(model, edges, views, R0, t0, config)
        assert out.accepted
        R_eq, _ = closest_equivalent(out.R_world_obj, R_true, discrete, np.zeros((0, 3)))
        error = np.concatenate([t_true - out.t_world_obj, so3_log(R_true @ R_eq.T)])
        assert float(error @ np.linalg.solve(out.cov, error)) < 16.81  # chi2, 6 dof, 99%
        plain = _refine_from(model, edges, views, R0, t0, bare)
        np.testing.assert_array_equal(plain.R_world_obj, out.R_world_obj)
        np.testing.assert_array_equal(plain.t_world_obj, out.t_world_obj)
        assert (plain.cost, plain.iterations) == (out.cost, out.iterations)
        np.testing.assert_allclose(out.cov - floor, plain.cov, rtol=1e-9, atol=1e-18)
    with pytest.raises(ValueError, match="refinement config"):
        RefineConfig(floor_rotation_deg=-1.0)


def test_the_default_bounds_accept_a_start_twenty_degrees_off_and_bring_it_back(robi_catalog):
    """A template match in a pile can be 20 degrees off in its true basin: with the default
    bounds (``accept_deg``) the refinement that brings it back within 2 degrees is accepted, while
    a bound of 15 degrees, the default before, refuses the same result."""
    model, T_world_obj, views, edges = _tube_once(robi_catalog)
    R_true, t_true = T_world_obj[:3, :3], T_world_obj[:3, 3]
    discrete = np.concatenate([np.eye(3)[None], model.symmetries_discrete[:, :3, :3]])
    axis = np.array([1.0, 2.0, -1.0]) / np.sqrt(6.0)
    R0 = so3_exp(np.deg2rad(20.0) * axis) @ R_true
    config = RefineConfig(iterations=20)
    out = _refine_from(model, edges, views, R0, t_true, config)
    assert out.accepted and out.refused == ""
    _, angle = closest_equivalent(out.R_world_obj, R_true, discrete, np.zeros((0, 3)))
    assert np.rad2deg(angle) < 2.0
    narrow = _refine_from(
        model, edges, views, R0, t_true, dataclasses.replace(config, accept_deg=15.0)
    )
    assert not narrow.accepted and narrow.refused == "rotation"


def _smooth_views(rng, n_views: int, bins: int, with_mask: list[bool]):
    """EdgeViews of smooth synthetic distance fields (every orientation bin alike, so that a
    sample's bin does not matter), cameras 0.4-0.6 m from the origin looking at it."""

    L = 96
    v, u = np.mgrid[0:L, 0:L].astype(float)
    views = []
    for k in range(n_views):
        a, b, c = rng.uniform(5.0, 14.0, size=3)
        field = 5.0 + 4.0 * np.sin(u / a + c) * np.cos(v / b)  # pixels, within (0, 10)
        maps = np.round(field / 10.0 * 255).astype(np.uint8)
        mask = np.round((5.0 + 4.0 * np.cos(u / b - v / a)) / 10.0 * 255).astype(np.uint8)
        eye = rng.normal(size=3)
        eye *= rng.uniform(0.4, 0.6) / np.linalg.norm(eye)
        T_world_cam = look_at(eye, np.zeros(3), np.array([0.0, 0.0, 1.0]))
        K = np.array([[300.0, 0.0, 47.5], [0.0, 300.0, 47.5], [0.0, 0.0, 1.0]])
        views.append(
            EdgeView(
                invert(T_world_cam),
                K,
                np.repeat(maps[None], bins, axis=0),
                mask if with_mask[k] else None,
                k,
            )
        )
    return views


def test_refinement_gradient_is_the_cost_derivative_by_central_differences():
    """The analytic gradient of the robust chamfer (chain rule through the map's bilinear
    gradient, the pinhole and the pose perturbation t + dt, exp(dphi) R) against central
    differences of the cost, all terms on: contour, creases at half weight, a mask in two of
    three views, samples both inside and past the Huber bound."""

    rng = np.random.default_rng(11)
    P, bins = 60, 8
    points = rng.uniform(-0.03, 0.03, size=(P, 3))
    directions = rng.normal(size=(P, 3))
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    edges = ModelEdges(points, directions, np.zeros((P, 2, 3)), np.zeros(P, bool), 0.08)
    views = _smooth_views(rng, 3, bins, [True, False, True])
    stack = _ViewStack.of(views)
    contour = np.zeros((3, P), bool)
    contour[:, : P // 2] = True
    crease = ~contour
    config = RefineConfig(huber_px=1.5, points_per_view=20.0)
    args = (10.0, bins, 0.5, 1.5, config)
    for _ in range(3):
        R = so3_exp(rng.normal(size=3))
        t = rng.normal(size=3) * 0.005
        cost, H, g, _ = _linearize(edges, stack, R, t, *args, True, (contour, crease))
        d, *_ = _linearize(edges, stack, R, t, *args, False, (contour, crease))
        assert d == cost and cost > 0
        numeric = np.zeros(6)
        for i in range(6):
            step = np.zeros(6)
            step[i] = 1e-8  # well below a pixel cell: no sample crosses a bilinear kink
            up, *_ = _linearize(
                edges, stack, so3_exp(step[3:]) @ R, t + step[:3], *args, False, (contour, crease)
            )
            down, *_ = _linearize(
                edges, stack, so3_exp(-step[3:]) @ R, t - step[:3], *args, False, (contour, crease)
            )
            numeric[i] = (up - down) / 2e-8
        # d cost = 2 g (cost is a sum of squared-like terms, g = J^T W r)
        np.testing.assert_allclose(2 * g, numeric, rtol=1e-4, atol=1e-5 * np.abs(numeric).max())
        # the information is symmetric positive semi-definite
        np.testing.assert_allclose(H, H.T, atol=1e-9 * np.abs(H).max())
        assert np.linalg.eigvalsh(H).min() > -1e-9 * np.abs(H).max()
        # each view counts at most points_per_view samples' worth: every sample twice (30 + 30
        # per term, past the cap of 20) changes nothing, every view twice doubles it all
        twice = ModelEdges(
            np.concatenate([points, points]),
            np.concatenate([directions, directions]),
            np.zeros((2 * P, 2, 3)),
            np.zeros(2 * P, bool),
            0.08,
        )
        sets2 = (np.concatenate([contour, contour], 1), np.concatenate([crease, crease], 1))
        c2, H2, g2, _ = _linearize(twice, stack, R, t, *args, True, sets2)
        np.testing.assert_allclose([c2, *g2, *H2.ravel()], [cost, *g, *H.ravel()], rtol=1e-9)
        doubled = _ViewStack.of(views + views)
        sets_v = (np.concatenate([contour, contour]), np.concatenate([crease, crease]))
        c3, H3, g3, _ = _linearize(edges, doubled, R, t, *args, True, sets_v)
        np.testing.assert_allclose(
            [c3, *g3, *H3.ravel()], [2 * cost, *2 * g, *2 * H.ravel()], rtol=1e-9
        )


def _tube_refinement(robi_catalog, config, degrees=6.0, **kwargs):
    """The tube fitting in three views, started ``degrees`` off about a fixed axis and 0.02 d
    off, with priors at the start; (model, truth (R, t), start (R, t), result)."""
    model, T_world_obj, views, edges = _tube_once(robi_catalog)
    R_true, t_true = T_world_obj[:3, :3], T_world_obj[:3, 3]
    axis = np.array([0.6, -0.48, 0.64])
    R0 = so3_exp(np.deg2rad(degrees) * axis) @ R_true
    t0 = t_true + 0.02 * model.diameter * np.array([0.0, 0.6, 0.8])
    out = _refine_from(model, edges, views, R0, t0, config, **kwargs)
    return model, (R_true, t_true), (R0, t0), out


def test_a_refinement_that_moves_too_far_is_refused_and_keeps_the_priors(robi_catalog):
    from posefuse.estimator.core.geometry import rotation_angle

    # allowed: it comes back by about 6 degrees
    model, (R_true, _), (R0, t0), ok = _tube_refinement(robi_catalog, RefineConfig())
    assert ok.accepted and ok.cost < ok.cost_start
    assert np.rad2deg(rotation_angle(ok.R_world_obj @ R_true.T)) < 2.0
    assert 1 <= ok.iterations <= RefineConfig().iterations
    # the same run may move at most 1 degree, or 0.001 d: refused, the start and the priors
    # come back, and the cost reported is the start's
    assert ok.refused == ""
    for config, why in (
        (RefineConfig(accept_deg=1.0), "rotation"),
        (RefineConfig(accept_frac=0.001, accept_frac_max=None), "translation"),
    ):
        *_, out = _tube_refinement(robi_catalog, config)
        assert not out.accepted and out.refused == why
        np.testing.assert_array_equal(out.R_world_obj, R0)
        np.testing.assert_array_equal(out.t_world_obj, t0)
        assert out.cost == out.cost_start == ok.cost_start
        expected = np.zeros((6, 6))
        expected[:3, :3] = np.eye(3) * (0.1 * model.diameter) ** 2
        expected[3:, 3:] = np.eye(3) * np.deg2rad(20.0) ** 2
        np.testing.assert_allclose(out.cov, expected)
    # the accepted covariance is the refinement's own: tighter than the rotation prior, and
    # in metres^2 for the translation (far below the prior's (0.1 d)^2)
    assert np.all(np.linalg.eigvalsh(ok.cov) > 0)
    assert np.trace(ok.cov[3:, 3:]) < np.trace(np.eye(3) * np.deg2rad(20.0) ** 2)
    assert np.trace(ok.cov[:3, :3]) < 3 * (0.1 * model.diameter) ** 2


def test_a_move_past_accept_frac_is_accepted_only_where_the_translation_prior_allows_it(
    robi_catalog,
):
    """Beyond accept_frac, up to accept_frac_max, a translation is accepted when its move is
    likely under the prior (squared Mahalanobis distance at most accept_chi2): the tube comes
    back about 0.02 d, well inside its prior of 0.1 d, so it is accepted with the bound at
    0.001 d; the same move refused where the gate is shut, or the farther bound is off."""
    model, (_, t_true), (_, t0), ok = _tube_refinement(robi_catalog, RefineConfig())
    moved = ok.t_world_obj - t0
    assert 0.001 * model.diameter < np.linalg.norm(moved) < 0.3 * model.diameter
    chi2 = float(moved @ moved) / (0.1 * model.diameter) ** 2  # the prior is isotropic here
    drop = 1.0 - ok.cost / ok.cost_start
    assert 0.0 < drop < 1.0
    shut = RefineConfig(accept_frac=0.001, accept_chi2=0.5 * chi2, stop_when_refused=False)
    for config, accepted in (
        (RefineConfig(accept_frac=0.001, accept_frac_max=0.3), True),
        (
            RefineConfig(
                accept_frac=0.001,
                accept_frac_max=0.3,
                accept_chi2=0.5 * chi2,
                accept_cost_drop=None,
            ),
            False,
        ),
        (RefineConfig(accept_frac=0.001, accept_frac_max=None), False),
        (RefineConfig(accept_frac=0.001, accept_frac_max=0.001), False),
        # the gate shut, and the cost fell by enough, or not (judged at the end)
        (dataclasses.replace(shut, accept_cost_drop=0.9 * drop), True),
        (dataclasses.replace(shut, accept_cost_drop=1.1 * drop), False),
    ):
        *_, out = _tube_refinement(robi_catalog, config)
        assert out.accepted is accepted, config
        assert out.refused == ("" if accepted else "translation")
        if accepted:
            np.testing.assert_allclose(out.t_world_obj, ok.t_world_obj, atol=1e-9)
            assert np.linalg.norm(out.t_world_obj - t_true) < np.linalg.norm(t0 - t_true)
    with pytest.raises(ValueError, match="refinement config"):
        RefineConfig(accept_frac=0.2, accept_frac_max=0.1)


def test_a_refinement_past_what_would_be_accepted_stops_there_with_the_same_answer(
    robi_catalog,
):
    """Once the translation has moved farther than accept_frac, the refinement stops: here,
    as running on, it ends refused (the start and the priors come back), in fewer steps."""
    strict = RefineConfig(accept_frac=0.001, accept_frac_max=None)
    *_, (R0, t0), stopped = _tube_refinement(robi_catalog, strict)
    *_, ran_on = _tube_refinement(
        robi_catalog, dataclasses.replace(strict, stop_when_refused=False)
    )
    assert not stopped.accepted and not ran_on.accepted
    assert stopped.iterations < ran_on.iterations
    for a, b in ((stopped.R_world_obj, ran_on.R_world_obj), (stopped.t_world_obj, t0)):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(stopped.cov, ran_on.cov)
    assert stopped.cost == ran_on.cost == stopped.cost_start


def test_a_warm_start_ends_where_a_cold_one_does_in_fewer_steps_and_a_bad_one_is_ignored(
    robi_catalog,
):
    from posefuse.estimator.core.geometry import rotation_angle

    _, (R_true, t_true), _, cold = _tube_refinement(robi_catalog, RefineConfig())
    *_, warm = _tube_refinement(
        robi_catalog, RefineConfig(), warm=PoseGuess(cold.R_world_obj, cold.t_world_obj)
    )
    assert warm.accepted and warm.iterations < cold.iterations
    assert rotation_angle(warm.R_world_obj @ cold.R_world_obj.T) < np.deg2rad(0.5)
    assert np.linalg.norm(warm.t_world_obj - cold.t_world_obj) < 1e-3
    # a warm start that costs more than the start (30 degrees off the other way) is not taken:
    # the result is the cold run's, step for step
    bad = so3_exp(np.deg2rad(30.0) * np.array([0.0, 0.0, 1.0])) @ R_true
    *_, ignored = _tube_refinement(robi_catalog, RefineConfig(), warm=PoseGuess(bad, t_true))
    np.testing.assert_allclose(ignored.R_world_obj, cold.R_world_obj, atol=1e-12)
    assert ignored.iterations == cold.iterations and ignored.cost == cold.cost


def test_refinement_cost_is_the_weighted_robust_chamfer_read_sample_by_sample():
    """The data term against a plain reference: each view's contour samples read from its
    directional map and (with a mask) its mask map, its crease samples from the directional
    map, each term's Huber cost scaled by its weight, by 1 / sigma^2, and by the per-view cap
    on samples; read with scipy's bilinear interpolation. Samples at the truncation count
    fully in the cost."""
    from scipy.ndimage import map_coordinates

    from posefuse.estimator.verification.model_edges import pose_edges

    rng = np.random.default_rng(5)
    P, bins, truncate = 50, 8, 10.0
    points = rng.uniform(-0.03, 0.03, size=(P, 3))
    directions = rng.normal(size=(P, 3))
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    edges = ModelEdges(points, directions, np.zeros((P, 2, 3)), np.zeros(P, bool), 0.08)
    views = _smooth_views(rng, 3, bins, [True, False, True])
    for view in views:  # every orientation bin its own map: the bin read must be the right one
        for b in range(bins):
            view.dcdt[b] = np.roll(view.dcdt[b], 7 * b, axis=1)
    # one view sees half its samples past the truncation: its map is flat at the truncation
    views[1].dcdt[:, :, 48:] = 255
    stack = _ViewStack.of(views)
    contour = rng.random((3, P)) < 0.6
    crease = ~contour & (rng.random((3, P)) < 0.7)
    for sigma, huber, cap, crease_w, mask_w in [
        (1.5, 2.0, 40.0, 0.5, 1.5),
        (1.0, 1.0, 10.0, 0.25, 0.0),
        (2.5, 3.0, 1000.0, 1.0, 3.0),
        (1.5, 2.0, 25.0, 0.5, 0.75),
    ]:
        config = RefineConfig(sigma_px=sigma, huber_px=huber, points_per_view=cap)
        R = so3_exp(rng.normal(size=3))
        t = rng.normal(size=3) * 0.005
        cost, H0, g0, _ = _linearize(
            edges, stack, R, t, truncate, bins, crease_w, mask_w, config, False, (contour, crease)
        )
        assert not H0.any() and not g0.any()  # asked for the cost alone
        expected = 0.0
        for k, view in enumerate(views):
            R_cw, t_cw = view.T_cam_world[:3, :3], view.T_cam_world[:3, 3]
            p = points @ (R_cw @ R).T + (R_cw @ t + t_cw)
            uv = p[:, :2] / p[:, 2:3] @ view.K_roi[:2, :2].T + view.K_roi[:2, 2]

            def read(image, uv=uv):
                return map_coordinates(image.astype(float), [uv[:, 1], uv[:, 0]], order=1) * (
                    truncate / 255.0
                )

            # the projected edge direction's bin, nearest of ``bins`` over [0, pi)
            q = directions @ (R_cw @ R).T
            duv = (q[:, :2] - p[:, :2] / p[:, 2:3] * q[:, 2:3]) / p[:, 2:3] @ view.K_roi[:2, :2].T
            angle = np.mod(np.arctan2(duv[:, 1], duv[:, 0]), np.pi)
            nearest = np.round(angle / (np.pi / bins)).astype(int) % bins
            d_dir = np.array([read(view.dcdt[b])[i] for i, b in enumerate(nearest)])
            terms = [(d_dir[contour[k]], 1.0), (d_dir[crease[k]], crease_w)]
            if view.mask_dt is not None and mask_w > 0:
                terms.append((read(view.mask_dt)[contour[k]], mask_w))
            for d, weight in terms:
                if len(d) == 0:
                    continue
                rho = np.where(d <= huber, d * d, 2 * huber * d - huber * huber)
                expected += weight * min(1.0, cap / len(d)) / sigma**2 * rho.sum()
        np.testing.assert_allclose(cost, expected, rtol=1e-9)
    # without given sets, the samples are those pose_edges shows at the pose: contour, and
    # active but not contour as creases
    normals = rng.normal(size=(P, 2, 3))
    normals /= np.linalg.norm(normals, axis=2)[..., None]
    crease_flag = rng.random(P) < 0.5
    real = ModelEdges(points, directions, normals, crease_flag, 0.08)
    config = RefineConfig()
    R, t = so3_exp(rng.normal(size=3)), np.zeros(3)
    cost, H, g, (c_used, k_used) = _linearize(real, stack, R, t, truncate, bins, 0.5, 1.5, config)
    _, _, active, shown_contour = pose_edges(real, stack.R_cw @ R, stack.R_cw @ t + stack.t_cw)
    np.testing.assert_array_equal(c_used, shown_contour)
    np.testing.assert_array_equal(k_used, active & ~shown_contour)
    assert k_used.any() and c_used.any()
    again = _linearize(real, stack, R, t, truncate, bins, 0.5, 1.5, config, True, (c_used, k_used))
    assert again[0] == cost
    np.testing.assert_array_equal(again[1], H)


def test_without_edges_to_read_the_priors_alone_decide_and_give_the_covariance():
    """Views whose maps are all at the truncation say nothing: the refinement moves the
    translation onto its prior's mean, keeps the rotation at the start (its prior's mean), and
    its covariance is the priors', the rotation's floored at ``rotation_floor_deg``, plus the
    floor every published covariance carries. One view is enough to run."""
    rng = np.random.default_rng(2)
    P = 40
    points = rng.uniform(-0.03, 0.03, size=(P, 3))
    directions = rng.normal(size=(P, 3))
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    normals = rng.normal(size=(P, 2, 3))
    normals /= np.linalg.norm(normals, axis=2)[..., None]
    edges = ModelEdges(points, directions, normals, np.ones(P, bool), 0.08)
    blind = []
    for view in _smooth_views(rng, 1, 8, [True]):
        blind.append(
            EdgeView(
                view.T_cam_world,
                view.K_roi,
                np.full_like(view.dcdt, 255),
                np.full_like(view.mask_dt, 255),
                0,
            )
        )
    R0 = so3_exp(np.array([0.2, -0.4, 0.3]))
    t_prior = np.array([0.01, 0.0, -0.02])
    t0 = t_prior + np.array([0.003, -0.002, 0.001])  # 0.05 d off the prior's mean
    cov_t = np.diag([1e-4, 4e-4, 9e-4])
    V = so3_exp(np.array([0.3, 0.1, -0.2]))
    cov_R = V @ np.diag(np.deg2rad([1.0, 10.0, 20.0]) ** 2) @ V.T  # 1 degree: below the floor
    out = refine_pose(
        edges,
        blind,
        PoseGuess(R0, t0),
        PosePrior(t_prior, cov_t, cov_R),
        EdgeScoring(truncate_px=10.0, bins=8, crease_weight=0.5, mask_weight=1.5),
        RefineConfig(),
    )
    assert out.accepted and out.cost < out.cost_start
    # within 1% of the way (the damping and the 0.2% cost tolerance stop it just short)
    np.testing.assert_allclose(out.t_world_obj, t_prior, atol=0.01 * np.linalg.norm(t0 - t_prior))
    np.testing.assert_allclose(out.R_world_obj, R0, atol=1e-12)
    expected = np.zeros((6, 6))
    expected[:3, :3] = cov_t
    expected[3:, 3:] = V @ np.diag(np.deg2rad([3.0, 10.0, 20.0]) ** 2) @ V.T
    config = RefineConfig()
    floor = np.diag(
        [(config.floor_translation_frac * 0.08) ** 2] * 3
        + [np.deg2rad(config.floor_rotation_deg) ** 2] * 3
    )
    np.testing.assert_allclose(out.cov, expected + floor, rtol=1e-6, atol=1e-15)
    # the costs it reports: the data's (constant) plus the translation prior's
    r0, r1 = t0 - t_prior, out.t_world_obj - t_prior
    prior_drop = float(r0 @ np.linalg.solve(cov_t, r0) - r1 @ np.linalg.solve(cov_t, r1))
    np.testing.assert_allclose(out.cost_start - out.cost, prior_drop, rtol=1e-9)


def test_a_sample_stride_below_one_is_refused():
    with pytest.raises(ValueError, match="refinement config"):
        RefineConfig(sample_stride=0)
    from posefuse.estimator.verification.verify import VerificationConfig

    with pytest.raises(ValueError, match="verification config"):
        VerificationConfig(sample_stride=0)


def test_accepts_translation_bounds_the_move_by_the_diameter_and_the_prior():
    from posefuse.estimator.verification.refinement import accepts_translation

    d, config = 0.1, RefineConfig()  # accept_frac 0.1 d, up to 0.3 d where the prior allows
    x = np.array([1.0, 0.0, 0.0])
    loose = np.eye(3) / (0.2 * d) ** 2  # the prior's std 0.2 d
    tight = np.eye(3) / (0.01 * d) ** 2
    assert accepts_translation(0.09 * d * x, tight, d, config)  # within 0.1 d: always
    assert accepts_translation(0.25 * d * x, loose, d, config)  # (1.25)^2 <= 11.34
    assert not accepts_translation(0.25 * d * x, tight, d, config)
    assert not accepts_translation(0.35 * d * x, loose, d, config)  # past 0.3 d: never
    fixed = dataclasses.replace(config, accept_frac_max=None)
    assert not accepts_translation(0.25 * d * x, loose, d, fixed)


@pytest.mark.parametrize("drop", [0.0, -0.1, 1.5])
def test_a_cost_drop_outside_zero_to_one_is_refused(drop):
    with pytest.raises(ValueError, match="refinement config"):
        RefineConfig(accept_cost_drop=drop)


def test_a_negative_challenge_cost_is_refused():
    from posefuse.estimator.verification.verify import VerificationConfig

    with pytest.raises(ValueError, match="verification config"):
        VerificationConfig(challenge_cost=-0.1)
    assert VerificationConfig(challenge_cost=None).challenge_cost is None


def test_accepts_translation_the_views_plainly_prefer_past_a_sure_prior():
    """A prior sure of a biased centre refuses the move; a cost that fell by at least
    accept_cost_drop of the start's takes it, up to accept_frac_max and never past it."""
    from posefuse.estimator.verification.refinement import accepts_translation

    d = 0.1
    config = RefineConfig(accept_cost_drop=0.3)
    x = np.array([0.0, 0.0, 1.0])
    tight = np.eye(3) / (0.02 * d) ** 2  # a move of 0.13 d is 6.5 sigma
    assert not accepts_translation(0.13 * d * x, tight, d, config)  # no cost given
    assert not accepts_translation(0.13 * d * x, tight, d, config, cost_drop=0.29)
    assert accepts_translation(0.13 * d * x, tight, d, config, cost_drop=0.31)
    assert not accepts_translation(0.31 * d * x, tight, d, config, cost_drop=0.9)
    off = dataclasses.replace(config, accept_cost_drop=None)
    assert not accepts_translation(0.13 * d * x, tight, d, off, cost_drop=0.9)
