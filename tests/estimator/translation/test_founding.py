"""Founding tracks from two views, merging converged tracks, splitting disagreeing views."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from posefuse.estimator.core.bin_region import BinRegion
from posefuse.estimator.core.geometry import invert, make_transform
from posefuse.estimator.frontend.detection import Detection
from posefuse.estimator.tracker import Frame, MultiViewEstimator, TrackerConfig
from posefuse.estimator.translation.founding import (
    FoundingConfig,
    HeldDetection,
    choose_pairs,
    pair_residual_lower_bounds,
    triangulate_pair,
)
from posefuse.estimator.translation.gaussian import CenterObservations, estimate_translation
from posefuse.estimator.translation.merging import MergeCandidate, MergeConfig, merge_pairs
from posefuse.estimator.translation.splitting import SplitConfig, outlier_views
from posefuse.sim.scenes import REALSENSE_1280x720

K = np.array([[900.0, 0, 640], [0, 900.0, 360], [0, 0, 1]])


def _T_cam_world(cam_x: float, target=(0.0, 0.0, 0.0), height=0.6) -> np.ndarray:
    """A camera at (cam_x, 0, height) looking at ``target`` (world z up)."""
    eye = np.array([cam_x, 0.0, height])
    z = np.asarray(target) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R_world_cam = np.stack([x, y, z], 1)
    return invert(make_transform(R_world_cam, eye))


def _project(T_cam_world, p):
    q = T_cam_world[:3, :3] @ p + T_cam_world[:3, 3]
    return (K @ (q / q[2]))[:2], q[2]


def _held(T, p, serial, box_scale=1.0, obj_id=1, index=0):
    uv, z = _project(T, p)
    return HeldDetection(obj_id, serial * 10, serial, T, K, uv, np.eye(2), z * box_scale, index)


def test_two_views_triangulate_the_point_without_the_box():
    p = np.array([0.05, -0.03, 0.02])
    a = _held(_T_cam_world(-0.15), p, 1, box_scale=1.8)  # boxes wrong by 1.8x and 0.6x
    b = _held(_T_cam_world(0.15), p, 2, box_scale=0.6)
    pair = triangulate_pair(a, b, FoundingConfig())
    assert pair is not None and not pair.static
    np.testing.assert_allclose(pair.prior_mean, p, atol=1e-6)
    obs = (
        CenterObservations.empty()
        .append(a.T_cam_world, K, a.uv, a.cov, 1)
        .append(b.T_cam_world, K, b.uv, b.cov, 2)
    )
    est = estimate_translation(obs, pair.prior_mean, pair.prior_cov)
    np.testing.assert_allclose(est.t_world_obj, p, atol=1e-6)


def test_rays_from_one_camera_centre_found_nothing():
    # two views from the same pose, two different pixels: the rays meet only at the camera
    # centre, which is no place for a part (this once raised a singular-matrix error)
    a = _held(_T_cam_world(0.0), np.array([0.0, 0.0625, 0.0]), 1)
    b = _held(_T_cam_world(0.0, target=(0.02, 0.01, 0.0)), np.array([0.0, 0.009765625, 0.0]), 2)
    assert triangulate_pair(a, b, FoundingConfig()) is None


def test_rays_that_miss_or_boxes_that_contradict_are_gated():
    p = np.array([0.0, 0.0, 0.0])
    a = _held(_T_cam_world(-0.15), p, 1)
    # the second view sees a point 1 cm off the first ray, sideways: no intersection
    b = _held(_T_cam_world(0.15), p + [0.0, 0.01, 0.0], 2)
    assert triangulate_pair(a, b, FoundingConfig()) is None
    # the rays meet, but the box says the part is 3x farther than they do
    c = _held(_T_cam_world(0.15), p, 2, box_scale=3.0)
    assert triangulate_pair(a, c, FoundingConfig()) is None
    # a box truncated by the border (NaN) is not checked
    d = _held(_T_cam_world(0.15), p, 2, box_scale=np.nan)
    assert triangulate_pair(a, d, FoundingConfig()) is not None


_coord = st.floats(-0.2, 0.2)


@settings(max_examples=300, deadline=None)
@given(
    cam_a=st.floats(-0.4, 0.4),
    cam_b=st.floats(-0.4, 0.4),
    p=st.tuples(_coord, _coord, st.floats(-0.05, 0.1)),
    offset=st.tuples(_coord, _coord, _coord),
    near=st.floats(0.0, 1.0),
    box_a=st.floats(0.3, 3.0),
    box_b=st.floats(0.3, 3.0),
    std=st.floats(0.5, 8.0),
)
def test_the_pair_bound_never_rejects_a_pair_that_triangulation_accepts(
    cam_a, cam_b, p, offset, near, box_a, box_b, std
):
    """The cheap bound is below the gate for every pair triangulate_pair founds: skipping the
    pairs above it changes no outcome."""
    config = FoundingConfig()
    p = np.array(p)
    q = p + near**3 * np.array(offset)  # the second view's part: often close, sometimes far
    a = _held(_T_cam_world(cam_a), p, 1, box_scale=box_a)
    b = _held(_T_cam_world(cam_b, target=(0.02, 0.01, 0.0)), q, 2, box_scale=box_b)
    cov = np.diag([std, 1.0]) ** 2
    a = HeldDetection(a.obj_id, 10, 1, a.T_cam_world, K, a.uv, cov, a.box_depth, 0)
    pair = triangulate_pair(a, b, config)
    bound = pair_residual_lower_bounds([a], [b], config)[0, 0]
    assert bound >= 0
    if pair is not None and not pair.static:
        assert bound <= min(pair.cost, config.pair_gate_chi2) + 1e-9


def test_the_pair_bound_rejects_parts_far_apart():
    config = FoundingConfig()
    a = _held(_T_cam_world(-0.15), np.zeros(3), 1)
    b = _held(_T_cam_world(0.15), np.array([0.0, 0.05, 0.0]), 2)  # 5 cm off the first ray
    assert pair_residual_lower_bounds([a], [b], config)[0, 0] > config.pair_gate_chi2


def test_pairs_are_chosen_jointly_and_never_within_one_view():
    pts = [np.array([-0.04, 0.0, 0.0]), np.array([0.04, 0.0, 0.0])]
    Ta, Tb = _T_cam_world(-0.15), _T_cam_world(0.15)
    held = [_held(Ta, p, 1, index=k) for k, p in enumerate(pts)]
    new = [_held(Tb, p, 2, index=k) for k, p in enumerate(pts[::-1])]
    pairs = choose_pairs(held, new, FoundingConfig())
    assert sorted((p.older.index, p.newer.index) for p in pairs) == [(0, 1), (1, 0)]
    assert choose_pairs(held, held, FoundingConfig()) == []


def test_a_static_camera_founds_from_the_box():
    p = np.array([0.0, 0.0, 0.0])
    T = _T_cam_world(0.0 + 1e-9, height=0.6)
    a, b = _held(T, p, 1, box_scale=1.1), _held(T, p, 2, box_scale=1.1)
    pair = triangulate_pair(a, b, FoundingConfig())
    assert pair is not None and pair.static
    assert np.isclose(np.linalg.norm(pair.prior_mean - T[:3, :3].T @ -T[:3, 3]), 0.66, rtol=1e-3)


def _cand(key, t, sigma, stamps, uv=None):
    n = len(stamps)
    obs = CenterObservations(
        np.repeat(np.eye(3)[None], n, 0),
        np.zeros((n, 3)),
        np.repeat(K[None], n, 0),
        np.zeros((n, 2)) if uv is None else np.asarray(uv, float),
        np.repeat(np.eye(2)[None], n, 0),
        np.asarray(stamps, np.int64),
    )
    return MergeCandidate(key, np.asarray(t, float), np.eye(3) * sigma**2, obs)


def test_tracks_merge_when_they_converge_and_were_never_seen_apart():
    cfg = MergeConfig()
    a = _cand("a", [0, 0, 0.5], 0.002, [1, 2])
    b = _cand("b", [0.001, 0, 0.5], 0.002, [3, 4])
    far = _cand("c", [0.03, 0, 0.5], 0.002, [5, 6])
    assert merge_pairs([a, b, far], diameter=0.05, config=cfg) == [("a", "b")]
    # uncertain, but more than a quarter diameter apart: never one part
    loose = _cand("d", [0.02, 0, 0.5], 0.05, [7, 8])
    assert merge_pairs([a, loose], diameter=0.05, config=cfg) == []
    # one view saw both, 30 px apart: two parts
    a2 = _cand("a", [0, 0, 0.5], 0.002, [1, 2], uv=[[0, 0], [0, 0]])
    b2 = _cand("b", [0.001, 0, 0.5], 0.002, [2, 4], uv=[[30, 0], [0, 0]])
    assert merge_pairs([a2, b2], diameter=0.05, config=cfg) == []


def test_views_that_disagree_leave_only_with_a_majority_left():
    class Est:
        chi2 = np.array([0.5, 1.0, 40.0, 0.2, 60.0])

    np.testing.assert_array_equal(outlier_views(Est, SplitConfig()), [0, 0, 1, 0, 1])
    Est.chi2 = np.array([0.5, 40.0, 60.0])  # one view would remain: no split
    assert not outlier_views(Est, SplitConfig()).any()
    with pytest.raises(ValueError):
        SplitConfig(min_inliers=1)


def test_estimator_holds_a_lone_detection_and_founds_on_the_second_view(robi_catalog):
    cam = REALSENSE_1280x720
    p = np.array([0.02, 0.01, 0.0])
    est = MultiViewEstimator(robi_catalog)
    obj_id = next(iter(robi_catalog))
    dia = robi_catalog[obj_id].diameter
    ids = []
    for k, x in enumerate([-0.12, 0.0, 0.12]):
        T_cam_world = _T_cam_world(x)
        q = T_cam_world[:3, :3] @ p + T_cam_world[:3, 3]
        uv = (cam.K @ (q / q[2]))[:2]
        side = cam.K[0, 0] * dia * 0.6 / q[2]
        box = [uv[0] - side / 2, uv[1] - side / 2, side, side]
        det = Detection(obj_id, np.array(box), uv, np.eye(2), None)
        est.update(Frame(k + 1, cam, np.linalg.inv(T_cam_world)), [det])
        ids.append(sorted(est.tracks))
    assert ids[0] == [] and est.last_report.assigned and len(ids[1]) == 1 and ids[2] == ids[1]
    track = est.tracks[ids[1][0]]
    assert [s for s, _ in track.detections] == [1, 2, 3]
    np.testing.assert_allclose(track.estimate.t_world_obj, p, atol=1e-4)


def test_a_track_under_the_bins_floor_is_published_tentative(robi_catalog):
    """Where the cell knows its bin, a track whose centre lies under its floor (detections of
    different parts that met there) is published tentative; the same views inside the bin, or
    without the bin, publish it confirmed. The tracks themselves are the same either way."""
    cam = REALSENSE_1280x720
    obj_id = next(iter(robi_catalog))
    dia = robi_catalog[obj_id].diameter
    config = TrackerConfig(bin=BinRegion((0.4, 0.3), 0.08))
    margin = config.bin_margin_frac * dia

    def detection(T_cam_world, p):
        q = T_cam_world[:3, :3] @ p + T_cam_world[:3, 3]
        uv = (cam.K @ (q / q[2]))[:2]
        side = cam.K[0, 0] * dia * 0.6 / q[2]
        box = np.array([uv[0] - side / 2, uv[1] - side / 2, side, side])
        return Detection(obj_id, box, uv, np.eye(2), None)

    def published(p, config):
        est = MultiViewEstimator(robi_catalog, config)
        for k, x in enumerate([-0.12, 0.0, 0.12]):
            T = _T_cam_world(x)
            est.update(Frame(k + 1, cam, np.linalg.inv(T)), [detection(T, p)])
        (estimate,) = est.estimates(include_tentative=True)
        (track,) = est.tracks.values()
        np.testing.assert_allclose(estimate.t_world_obj, p, atol=1e-4)
        return estimate.status, track.status

    under = np.array([0.02, 0.01, -margin - 0.01])
    barely = np.array([0.02, 0.01, -margin + 0.01])  # within the allowance
    beyond_wall = np.array([0.2 + margin + 0.01, 0.01, 0.02])
    for p in (under, beyond_wall):
        assert published(p, config) == ("tentative", "confirmed")
        assert published(p, TrackerConfig()) == ("confirmed", "confirmed")
    assert published(barely, config) == ("confirmed", "confirmed")
    assert published(np.array([0.02, 0.01, 0.3]), config) == ("confirmed", "confirmed")  # open top
