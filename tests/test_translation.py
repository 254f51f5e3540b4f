"""Translation step: Jacobians, convergence, honest covariances, degenerate input."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from posefuse.estimator.translation import (
    CenterObservations,
    estimate_translation,
    predict,
    prior_from_first_view,
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
    with pytest.raises(ValueError, match="center measurement"):
        CenterObservations.empty().append(np.eye(4), CAM.K, np.array(uv), cov, 0)


def test_prior_refuses_bad_sizes():
    with pytest.raises(ValueError, match="bbox diagonal"):
        prior_from_first_view(np.eye(4), CAM.K, np.zeros(2), 0.0, 0.08)
    with pytest.raises(ValueError, match="diameter"):
        prior_from_first_view(np.eye(4), CAM.K, np.zeros(2), 100.0, np.nan)


def test_folding_old_views_into_the_prior_keeps_the_estimate():
    from posefuse.estimator.translation import marginalize_oldest

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
