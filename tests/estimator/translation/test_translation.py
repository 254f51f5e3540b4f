"""Translation step: Jacobians, convergence, honest covariances, degenerate input."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from posefuse.estimator.translation.gaussian import (
    CenterObservations,
    estimate_translation,
    predict,
    prior_from_first_view,
    variance_factor,
)
from posefuse.sim.scenes import REALSENSE_1280x720, SceneSpec, sample_views

CAM = REALSENSE_1280x720
COV = np.eye(2) * 4.0


def _views(n, seed):
    return sample_views(SceneSpec(n_views=n), np.random.default_rng(seed))


def _observe(t_world, T_world_cams, noise=0.0, seed=0):
    rng = np.random.default_rng(seed)
    obs = CenterObservations.empty()
    for k, T_wc in enumerate(T_world_cams):
        T_cw = np.linalg.inv(T_wc)
        uv = CAM.project(T_cw[:3, :3] @ t_world + T_cw[:3, 3]) + rng.normal(0, noise, 2)
        obs = obs.append(T_cw, CAM.K, uv, COV, k)
    return obs


@settings(max_examples=40, deadline=None)
@given(
    st.lists(st.floats(-0.1, 0.1), min_size=3, max_size=3),
    st.integers(0, 10_000),
)
def test_projection_jacobian_matches_central_differences(t, seed):
    t = np.array(t) + [0, 0, 0.03]
    obs = _observe(t, _views(3, seed))
    _, J, _ = predict(t, obs)
    h = 1e-6
    numeric = np.stack(
        [(predict(t + h * e, obs)[0] - predict(t - h * e, obs)[0]) / (2 * h) for e in np.eye(3)],
        axis=-1,
    )
    np.testing.assert_allclose(J, numeric, rtol=1e-5, atol=1e-3)


def test_converges_from_a_prior_depth_30_percent_off():
    t_true = np.array([0.04, -0.03, 0.02])
    T_wcs = _views(4, 1)
    obs = _observe(t_true, T_wcs)
    T_cw0 = np.linalg.inv(T_wcs[0])
    z_true = (T_cw0[:3, :3] @ t_true + T_cw0[:3, 3])[2]
    diameter = 0.08
    bbox_diag = CAM.K[0, 0] * diameter / (1.3 * z_true)  # the box says 30% farther
    mean, cov = prior_from_first_view(T_wcs[0], CAM.K, obs.uv[0], bbox_diag, diameter)
    ratio = np.linalg.norm(mean - T_wcs[0][:3, 3]) / np.linalg.norm(t_true - T_wcs[0][:3, 3])
    assert ratio == pytest.approx(1.3, abs=0.02)
    est = estimate_translation(obs, mean, cov)
    assert np.linalg.norm(est.t_world_obj - t_true) < 1e-5
    assert np.all(est.weights == 1.0)


def test_one_view_covariance_is_long_along_the_ray():
    t_true = np.array([0.0, 0.0, 0.02])
    T_wc = _views(1, 2)[0]
    obs = _observe(t_true, [T_wc])
    z = np.linalg.norm(t_true - T_wc[:3, 3])
    mean, cov = prior_from_first_view(T_wc, CAM.K, obs.uv[0], CAM.K[0, 0] * 0.08 / z, 0.08)
    est = estimate_translation(obs, mean, cov)
    ray = (t_true - T_wc[:3, 3]) / z
    along = np.sqrt(ray @ est.cov @ ray)
    across = np.sqrt(np.linalg.eigvalsh(est.cov)[:2])
    assert along == pytest.approx(0.5 * z, rel=0.05)  # the prior's 50% depth uncertainty
    assert np.all(across < 2.5 * 2.0 * z / CAM.K[0, 0])  # ~ 2 px at depth z
    # the estimate still lies on the ray through the measured center
    np.testing.assert_allclose(np.cross(est.t_world_obj - T_wc[:3, 3], ray), 0, atol=1e-6)


def test_two_cameras_at_the_same_pose_leave_depth_uncertain_without_nan():
    t_true = np.array([0.01, 0.02, 0.03])
    T_wc = _views(1, 3)[0]
    obs = _observe(t_true, [T_wc, T_wc, T_wc], noise=2.0, seed=4)
    z = np.linalg.norm(t_true - T_wc[:3, 3])
    mean, cov = prior_from_first_view(T_wc, CAM.K, obs.uv[0], CAM.K[0, 0] * 0.08 / z, 0.08)
    est = estimate_translation(obs, mean, cov)
    assert np.all(np.isfinite(est.t_world_obj)) and np.all(np.isfinite(est.cov))
    assert np.sqrt(np.linalg.eigvalsh(est.cov).max()) > 0.3 * z  # no triangulation, no depth


def test_outlier_view_is_downweighted():
    t_true = np.array([0.02, 0.01, 0.03])
    T_wcs = _views(6, 5)
    obs = _observe(t_true, T_wcs, noise=1.0, seed=6)
    bad = obs.uv.copy()
    bad[3] += [60.0, -40.0]
    obs = CenterObservations(obs.R_cam_world, obs.t_cam_world, obs.K, bad, obs.info, obs.stamp_ns)
    mean, cov = prior_from_first_view(T_wcs[0], CAM.K, obs.uv[0], 110.0, 0.08)
    est = estimate_translation(obs, mean, cov)
    assert est.weights[3] < 0.2 and np.all(np.delete(est.weights, 3) > 0.5)
    assert np.linalg.norm(est.t_world_obj - t_true) < 3e-3


def test_the_variance_factor_is_the_weighted_scatter_per_degree_of_freedom_never_below_one():
    w = np.array([1.0, 1.0, 0.5, 0.0])
    s = np.array([4.0, 6.0, 20.0, 1e9])  # the last view has no weight: not counted at all
    # three views used: 2 * 3 - 3 = 3 degrees of freedom, scatter 4 + 6 + 10 = 20
    assert variance_factor(w, s, 0.0) == pytest.approx(20 / 3)
    assert variance_factor(w, s, 3.0) == pytest.approx(23 / 6)  # shrunk towards 1
    assert variance_factor(w, np.array([0.1, 0.2, 0.1, 0.0]), 0.0) == 1.0
    assert variance_factor(np.ones(1), np.array([50.0]), 0.0) == 1.0  # one view: no dof
    with pytest.raises(ValueError, match="prior_dof"):
        variance_factor(w, s, -1.0)


def test_centres_of_two_parts_widen_the_covariance_and_consistent_ones_do_not():
    t_true = np.array([0.02, 0.01, 0.03])
    T_wcs = _views(6, 5)
    obs = _observe(t_true, T_wcs, noise=0.5, seed=6)
    mean, cov = prior_from_first_view(T_wcs[0], CAM.K, obs.uv[0], 110.0, 0.08)
    plain = estimate_translation(obs, mean, cov)
    honest = estimate_translation(obs, mean, cov, variance_prior_dof=0.0)
    np.testing.assert_array_equal(honest.cov, plain.cov)  # they scatter less than said
    # half the views see a neighbour 25 mm away: each view agrees with some point, not one
    other = _observe(t_true + [0.025, 0.0, 0.0], T_wcs, noise=0.5, seed=7)
    uv = np.where(np.arange(6)[:, None] % 2 == 1, other.uv, obs.uv)
    mixed = CenterObservations(obs.R_cam_world, obs.t_cam_world, obs.K, uv, obs.info, obs.stamp_ns)
    plain = estimate_translation(mixed, mean, cov)
    honest = estimate_translation(mixed, mean, cov, variance_prior_dof=0.0)
    np.testing.assert_allclose(honest.t_world_obj, plain.t_world_obj)  # the same solution
    factor = variance_factor(plain.weights, plain.chi2, 0.0)
    assert factor > 5
    np.testing.assert_allclose(honest.cov, plain.cov * factor, rtol=1e-9)
    error = plain.t_world_obj - t_true
    assert error @ np.linalg.solve(plain.cov, error) > 3 * (
        error @ np.linalg.solve(honest.cov, error)
    )


def _biased_nees(n_views, shared_std, trials=100):
    """Mean NEES of tracks whose centres all point at the part moved by one bias (a 3 mm std
    per axis, drawn per track), each view adding its own 1 px noise (covariance 4 px^2, as
    said): what the views share and what they do not."""
    rng = np.random.default_rng(11)
    out = []
    for trial in range(trials):
        t_true = np.array([0.02, 0.01, 0.03])
        T_wcs = _views(n_views, trial)
        bias = rng.normal(0, 3e-3, 3)
        obs = _observe(t_true + bias, T_wcs, noise=2.0, seed=trial)
        mean, cov = prior_from_first_view(T_wcs[0], CAM.K, obs.uv[0], 110.0, 0.08)
        est = estimate_translation(obs, mean, cov, shared_std=shared_std)
        error = est.t_world_obj - t_true
        out.append(error @ np.linalg.solve(est.cov, error))
    return float(np.mean(out))


def test_an_error_the_views_share_is_covered_by_the_shared_floor_and_not_by_more_views():
    # a bias shared by every view is not averaged out: the NEES grows with the views
    assert _biased_nees(2, 0.0) < _biased_nees(8, 0.0) / 2
    assert _biased_nees(8, 0.0) > 10
    # with its std declared, the NEES is what a Gaussian of 3 dimensions gives, at any count
    for n in (2, 8):
        assert 2.0 < _biased_nees(n, 3e-3) < 4.0


def test_the_shared_floor_widens_the_covariance_and_leaves_the_solution():
    t_true = np.array([0.02, 0.01, 0.03])
    T_wcs = _views(5, 3)
    obs = _observe(t_true, T_wcs, noise=1.0, seed=4)
    mean, cov = prior_from_first_view(T_wcs[0], CAM.K, obs.uv[0], 110.0, 0.08)
    plain = estimate_translation(obs, mean, cov, variance_prior_dof=0.0)
    floored = estimate_translation(obs, mean, cov, variance_prior_dof=0.0, shared_std=2e-3)
    np.testing.assert_array_equal(floored.t_world_obj, plain.t_world_obj)
    np.testing.assert_allclose(floored.cov, plain.cov + np.eye(3) * 4e-6, rtol=1e-12)
    with pytest.raises(ValueError, match="shared_std"):
        estimate_translation(obs, mean, cov, shared_std=-1e-3)
    with pytest.raises(ValueError, match="shared_std"):
        estimate_translation(obs, mean, cov, shared_std=float("nan"))


@pytest.mark.parametrize(
    "cov, uv",
    [
        (np.zeros((2, 2)), [640.0, 360.0]),
        (np.array([[4.0, 0], [0, np.nan]]), [640.0, 360.0]),
        (np.eye(2), [np.inf, 360.0]),
        (np.array([[1.0, 2.0], [2.0, 1.0]]), [640.0, 360.0]),
    ],
)
def test_bad_measurements_are_refused(cov, uv):
    why = (
        "must be finite"
        if not np.all(np.isfinite(cov)) or not np.all(np.isfinite(uv))
        else ("not positive definite")
    )
    with pytest.raises(ValueError, match=f"^center measurement: .*{why}"):
        CenterObservations.empty().append(np.eye(4), CAM.K, np.array(uv), cov, 0)


def test_prior_refuses_bad_sizes():
    with pytest.raises(ValueError, match="bbox diagonal"):
        prior_from_first_view(np.eye(4), CAM.K, np.zeros(2), 0.0, 0.08)
    with pytest.raises(ValueError, match="diameter"):
        prior_from_first_view(np.eye(4), CAM.K, np.zeros(2), 100.0, np.nan)


def test_folding_old_views_into_the_prior_keeps_the_estimate():
    from posefuse.estimator.translation.gaussian import marginalize_oldest

    t_true = np.array([0.02, -0.01, 0.03])
    T_wcs = np.concatenate([_views(8, s) for s in range(5)])  # 40 views
    obs = _observe(t_true, T_wcs, noise=2.0, seed=11)
    z = np.linalg.norm(t_true - T_wcs[0][:3, 3])
    mean, cov = prior_from_first_view(T_wcs[0], CAM.K, obs.uv[0], CAM.K[0, 0] * 0.08 / z, 0.08)
    full = estimate_translation(obs, mean, cov)
    window = CenterObservations(
        obs.R_cam_world[:10],
        obs.t_cam_world[:10],
        obs.K[:10],
        obs.uv[:10],
        obs.info[:10],
        obs.stamp_ns[:10],
    )
    m, P = mean, cov
    est = estimate_translation(window, m, P)
    for k in range(10, 40):
        window = window.append(
            np.vstack([np.hstack([obs.R_cam_world[k], obs.t_cam_world[k][:, None]]), [0, 0, 0, 1]]),
            obs.K[k],
            obs.uv[k],
            np.linalg.inv(obs.info[k]),
            k,
        )
        window, m, P = marginalize_oldest(window, m, P, est.t_world_obj)
        est = estimate_translation(window, m, P, start=est.t_world_obj)
    assert len(window) == 10
    assert np.linalg.norm(est.t_world_obj - full.t_world_obj) < 0.2e-3
    np.testing.assert_allclose(np.sqrt(np.diag(est.cov)), np.sqrt(np.diag(full.cov)), rtol=0.2)


def test_bbox_diagonal_ratio_of_a_sphere_and_of_a_rod():
    """A sphere's projection is a disk of its diameter d whatever the turn: its box has the
    diagonal d sqrt(2). A rod of length d seen at angle theta to its axis spans d sin(theta):
    with cos(theta) uniform on [-1, 1] the median of |sin(theta)| is sqrt(3) / 2."""
    from posefuse.estimator.translation.gaussian import bbox_diagonal_ratio

    rng = np.random.default_rng(0)
    sphere = rng.normal(size=(4000, 3))
    sphere = 0.05 * sphere / np.linalg.norm(sphere, axis=1, keepdims=True)  # diameter 0.1
    assert bbox_diagonal_ratio(sphere, 0.1) == pytest.approx(np.sqrt(2), rel=0.01)
    rod = np.outer(np.linspace(-0.05, 0.05, 101), [0.0, 0.0, 1.0])
    ratio = bbox_diagonal_ratio(rod, 0.1, n=4000)
    assert ratio == pytest.approx(np.sqrt(3) / 2, abs=0.02)
    # the same draw for the same seed; another seed differs only by sampling
    assert bbox_diagonal_ratio(rod, 0.1, n=4000) == ratio
    assert bbox_diagonal_ratio(rod, 0.1, n=4000, seed=1) != ratio
    assert bbox_diagonal_ratio(rod * 2, 0.2, n=4000) == pytest.approx(ratio, rel=1e-12)


def _obs_of(stamps, seed=0):
    rng = np.random.default_rng(seed)
    obs = CenterObservations.empty()
    for s in stamps:
        T = np.eye(4)
        T[:3, 3] = rng.normal(0, 0.1, 3)
        obs = obs.append(T, CAM.K * rng.uniform(0.9, 1.1), rng.uniform(0, 500, 2), COV * s, s)
    return obs


def test_select_and_concat_keep_every_field_of_each_view_together():
    a, b = _obs_of([1, 4, 6], seed=1), _obs_of([2, 5, 3], seed=2)
    fields = ("R_cam_world", "t_cam_world", "K", "uv", "info", "stamp_ns")
    both = a.concat(b)
    assert len(both) == 6 and both.stamp_ns.tolist() == [1, 2, 3, 4, 5, 6]
    for k, stamp in enumerate(both.stamp_ns):
        src = a if stamp in a.stamp_ns else b
        i = src.stamp_ns.tolist().index(stamp)
        for f in fields:
            np.testing.assert_array_equal(getattr(both, f)[k], getattr(src, f)[i])
    # equal stamps keep their order: self's view first
    tie = _obs_of([7], seed=3).concat(_obs_of([7], seed=4))
    np.testing.assert_array_equal(tie.uv[0], _obs_of([7], seed=3).uv[0])
    for keep in (np.array([True, False, True]), np.array([2, 0])):
        sub = a.select(keep)
        idx = np.flatnonzero(keep) if keep.dtype == bool else keep
        for f in fields:
            np.testing.assert_array_equal(getattr(sub, f), getattr(a, f)[idx])


def test_robust_cost_is_the_prior_plus_huber_on_each_view():
    """Against a second implementation: an inlier view costs s, an outlier 2 k sqrt(s) - k^2,
    a view with the part behind the camera 1e6, plus (t - m)^T P^-1 (t - m)."""
    from posefuse.estimator.translation.gaussian import HUBER_K, robust_cost

    t = np.array([0.01, -0.02, 0.0])
    T_wcs = _views(3, 5)
    obs = _observe(t, T_wcs)
    uv = obs.uv.copy()
    uv[1] += [1.0, 0.5]  # s = (1 + 0.25) / 4, an inlier
    uv[2] += [40.0, 0.0]  # s = 400, far beyond the Huber threshold
    obs = CenterObservations(obs.R_cam_world, obs.t_cam_world, obs.K, uv, obs.info, obs.stamp_ns)
    m, P = t + [0.003, 0.0, -0.004], np.diag([1e-4, 4e-4, 1e-4])
    d = t - m
    k = HUBER_K
    expected = d @ np.linalg.solve(P, d) + 0.0 + 1.25 / 4 + (2 * k * 20.0 - k**2)
    assert robust_cost(t, obs, m, P) == pytest.approx(expected, rel=1e-9)
    assert robust_cost(t, obs, m, P, huber_k=30.0) == pytest.approx(
        d @ np.linalg.solve(P, d) + 1.25 / 4 + 400.0, rel=1e-9
    )
    # a view that sees the point from behind counts 1e6, not its residual
    behind = np.eye(4)
    behind[:3, 3] = [0.0, 0.0, -1.0]  # t_cam = t - (0, 0, 1): z < 0
    flipped = obs.append(behind, CAM.K, np.array([640.0, 360.0]), COV, 9)
    assert robust_cost(t, flipped, m, P) == pytest.approx(expected + 1e6, rel=1e-9)


def _info_form(P, m, J, W, r, t_hat):
    """The Gaussian product of N(m, P) and one linearised view, written out."""
    A = np.linalg.inv(P)
    # minimise (t - m)^T A (t - m) + (J (t - t_hat) + r)^T W (J (t - t_hat) + r)
    H = A + J.T @ W @ J
    g = A @ m - J.T @ W @ (r - J @ t_hat)
    return np.linalg.solve(H, g), np.linalg.inv(H)


def test_marginalize_oldest_folds_exactly_the_first_view_into_the_prior():
    from posefuse.estimator.translation.gaussian import HUBER_K, marginalize_oldest

    t = np.array([0.02, 0.01, 0.0])
    T_wcs = _views(4, 8)
    obs = _observe(t, T_wcs, noise=1.5, seed=2)
    m, P = t + [0.01, -0.01, 0.02], np.eye(3) * 4e-4
    t_hat = t + [0.001, 0.0, -0.002]
    rest, mean, cov = marginalize_oldest(obs, m, P, t_hat)
    assert len(rest) == 3
    for f in ("R_cam_world", "t_cam_world", "K", "uv", "info", "stamp_ns"):
        np.testing.assert_array_equal(getattr(rest, f), getattr(obs, f)[1:])
    uv, J, _ = predict(t_hat, obs.select([0]))
    r = uv[0] - obs.uv[0]
    W = obs.info[0]
    assert np.sqrt(r @ W @ r) <= HUBER_K  # an inlier: folded at full weight
    want_mean, want_cov = _info_form(P, m, J[0], W, r, t_hat)
    np.testing.assert_allclose(mean, want_mean, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(cov, want_cov, rtol=1e-9, atol=1e-15)
    np.testing.assert_array_equal(cov, cov.T)
    # an outlier first view is folded with its Huber weight k / sqrt(s)
    uv_f = obs.uv.copy()
    uv_f[0] += [60.0, 0.0]
    far = CenterObservations(obs.R_cam_world, obs.t_cam_world, obs.K, uv_f, obs.info, obs.stamp_ns)
    _, mean_f, cov_f = marginalize_oldest(far, m, P, t_hat)
    r_f = uv[0] - far.uv[0]
    s = r_f @ W @ r_f
    assert np.sqrt(s) > HUBER_K
    want_mean, want_cov = _info_form(P, m, J[0], W * HUBER_K / np.sqrt(s), r_f, t_hat)
    np.testing.assert_allclose(mean_f, want_mean, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(cov_f, want_cov, rtol=1e-9, atol=1e-15)
    # a first view with the part behind it teaches nothing: the prior stays
    behind = np.eye(4)
    behind[:3, 3] = [0.0, 0.0, -1.0]
    b_obs = CenterObservations.empty().append(behind, CAM.K, np.array([640.0, 360.0]), COV, 0)
    b_obs = b_obs.concat(obs.select([1, 2]))
    rest_b, mean_b, cov_b = marginalize_oldest(b_obs, m, P, t)
    np.testing.assert_allclose(mean_b, m, rtol=1e-12)
    np.testing.assert_allclose(cov_b, P, rtol=1e-12)
    assert len(rest_b) == 2


def test_the_estimate_reports_its_views_residuals_and_cost_at_the_solution():
    from posefuse.estimator.translation.gaussian import robust_cost

    t_true = np.array([0.02, -0.01, 0.03])
    T_wcs = _views(5, 21)
    obs = _observe(t_true, T_wcs, noise=2.0, seed=4)
    mean, cov = prior_from_first_view(T_wcs[0], CAM.K, obs.uv[0], 60.0, 0.08)
    est = estimate_translation(obs, mean, cov)
    assert est.n_views == 5 and est.t_world_obj.dtype == np.float64
    uv, _, _ = predict(est.t_world_obj, obs)
    r = uv - obs.uv
    np.testing.assert_allclose(est.chi2, np.einsum("ni,nij,nj->n", r, obs.info, r), rtol=1e-9)
    assert est.cost == pytest.approx(robust_cost(est.t_world_obj, obs, mean, cov), rel=1e-12)
    # the minimum: no small move lowers the cost
    for d in np.vstack([np.eye(3), -np.eye(3)]) * 1e-5:
        assert robust_cost(est.t_world_obj + d, obs, mean, cov) >= est.cost - 1e-9
    # no iteration: the start itself (as float64), not the prior mean
    start = [0, 0, 1]
    still = estimate_translation(obs, mean, cov, start=start, max_iterations=0)
    np.testing.assert_array_equal(still.t_world_obj, [0.0, 0.0, 1.0])
    assert still.t_world_obj.dtype == np.float64
    # run to the end (tolerance 0): the same minimum, found without giving up
    again = estimate_translation(obs, mean, cov, start=est.t_world_obj + 0.01, tolerance=0.0)
    np.testing.assert_allclose(again.t_world_obj, est.t_world_obj, atol=1e-7)


def test_a_view_behind_the_camera_gets_no_weight():
    t_true = np.array([0.0, 0.01, 0.02])
    T_wcs = _views(3, 30)
    obs = _observe(t_true, T_wcs, noise=1.0, seed=6)
    mean, cov = prior_from_first_view(T_wcs[0], CAM.K, obs.uv[0], 60.0, 0.08)
    good = estimate_translation(obs, mean, cov)
    behind = np.eye(4)
    behind[:3, 3] = -t_true - [0.0, 0.0, 1.0]  # the part 1 m behind this camera
    with_behind = obs.append(behind, CAM.K, np.array([640.0, 360.0]), COV, 9)
    est = estimate_translation(with_behind, mean, cov)
    assert np.all(np.isfinite(est.t_world_obj)) and np.all(np.isfinite(est.cov))
    assert est.weights[-1] == 0.0 and np.all(est.weights[:-1] > 0)
    np.testing.assert_allclose(est.t_world_obj, good.t_world_obj, atol=1e-9)
    # at exactly MIN_DEPTH a view gives nothing either (``z > MIN_DEPTH``)
    from posefuse.estimator.translation.gaussian import MIN_DEPTH

    at_edge = np.eye(4)
    at_edge[:3, 3] = [0.0, 0.0, MIN_DEPTH]  # the origin at depth MIN_DEPTH
    edge_obs = CenterObservations.empty().append(at_edge, CAM.K, np.array([640.0, 360.0]), COV, 0)
    origin = np.zeros(3)
    edge = estimate_translation(edge_obs, origin, np.eye(3), start=origin, max_iterations=0)
    assert edge.weights[0] == 0.0


def test_huber_weights_are_one_inside_and_k_over_root_outside():
    from posefuse.estimator.translation.gaussian import _huber_weights

    s = np.array([0.0, 0.25, 0.5, 4.0, 9.0])
    np.testing.assert_allclose(_huber_weights(s, 2.0), [1, 1, 1, 1, 2 / 3])
    # a threshold below one standard deviation: 0.5 / sqrt(0.5) for s = 0.5
    np.testing.assert_allclose(_huber_weights(s, 0.5), [1, 1, 0.5 / np.sqrt(0.5), 0.25, 0.5 / 3])


def test_a_measurement_keeps_its_inverse_covariance_and_integer_stamp():
    cov = np.array([[4.0, 1.0], [1.0, 2.0]])
    obs = CenterObservations.empty().append(np.eye(4), CAM.K, [10, 20], cov, 123)
    np.testing.assert_allclose(obs.info[0], np.linalg.inv(cov), rtol=1e-12)
    assert obs.uv.dtype == np.float64 and obs.uv.shape == (1, 2)
    assert obs.stamp_ns.dtype == np.int64 and obs.stamp_ns.tolist() == [123]
    # positive definite means the smaller eigenvalue above 1e-9 x max(1, the larger)
    CenterObservations.empty().append(np.eye(4), CAM.K, [0, 0], np.diag([1.2e-9, 1.0]), 0)
    for bad in (np.diag([0.9e-9, 1.0]), np.diag([5e-8, 100.0])):
        with pytest.raises(ValueError, match="not positive definite"):
            CenterObservations.empty().append(np.eye(4), CAM.K, [0, 0], bad, 0)


def test_prior_depth_scales_with_size_ratio_and_refuses_zero_or_infinite_sizes():
    K = CAM.K
    t1, _ = prior_from_first_view(np.eye(4), K, K[:2, 2], 60.0, 0.08)
    t2, P2 = prior_from_first_view(np.eye(4), K, K[:2, 2], 60.0, 0.08, size_ratio=2.0)
    f = 0.5 * (K[0, 0] + K[1, 1])
    np.testing.assert_allclose(t1, [0, 0, f * 0.08 / 60.0], atol=1e-12)
    np.testing.assert_allclose(t2, 2 * t1, atol=1e-12)
    np.testing.assert_allclose(P2, np.eye(3) * (0.5 * t2[2]) ** 2)
    prior_from_first_view(np.eye(4), K, K[:2, 2], 0.5, 0.08)  # a box under a pixel is a box
    for diag, diameter in [(60.0, 0.0), (60.0, np.inf), (np.inf, 0.08)]:
        with pytest.raises(ValueError):
            prior_from_first_view(np.eye(4), K, K[:2, 2], diag, diameter)


def test_projection_with_a_skewed_camera():
    K = np.array([[500.0, 3.0, 300.0], [0.0, 480.0, 200.0], [0.0, 0.0, 1.0]])
    T = np.eye(4)
    T[:3, 3] = [0.01, -0.02, 0.5]
    obs = CenterObservations.empty().append(T, K, [0, 0], COV, 0)
    t = np.array([0.03, 0.04, 0.1])
    uv, _, z = predict(t, obs)
    p = K @ (t + T[:3, 3])
    np.testing.assert_allclose(uv[0], p[:2] / p[2], rtol=1e-12)
    assert z[0] == pytest.approx(0.6)
