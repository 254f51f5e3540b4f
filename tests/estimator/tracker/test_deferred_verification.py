"""Deferred verification (TrackerConfig.deferred_verification): the update measures and fuses
rotations only; the tracks whose views changed wait, and are verified when asked, the longest
waiting first. Checked after every update, the estimates are those of the verification in the
update, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from posefuse.estimator.tracker import Frame, MultiViewEstimator, TrackerConfig
from posefuse.evaluation.dataset import load_dataset
from posefuse.evaluation.oracle import OracleConfig, OracleFrontend


def _frames(dataset, scene_id):
    """(Frame, detections) of a scene's views, in order."""
    front = OracleFrontend(dataset, OracleConfig(center_sigma_px=1.0, with_masks=True, seed=0))
    scene = dataset.scene(scene_id)
    for im in scene.im_ids:
        view = scene.view(im)
        yield Frame(im, view.camera, view.T_world_cam, scene.load_rgb(im)), front.detect(view)


def _same(a, b) -> None:
    assert [e.object_id for e in a] == [e.object_id for e in b]
    for x, y in zip(a, b, strict=True):
        assert np.array_equal(x.T_world_obj, y.T_world_obj), x.object_id
        assert np.array_equal(x.cov, y.cov), x.object_id
        assert x.confidence == y.confidence
        assert x.verified == y.verified


@pytest.fixture(scope="module")
def dataset(small_dataset_root):
    return load_dataset(small_dataset_root)


def test_checked_after_every_update_the_estimates_are_those_of_the_update_bit_for_bit(
    dataset, default_banks
):
    inline = MultiViewEstimator(dataset.catalog, TrackerConfig(), banks=default_banks)
    deferred = MultiViewEstimator(
        dataset.catalog, TrackerConfig(deferred_verification=True), banks=default_banks
    )
    checked = 0
    for scene_id in dataset.scene_ids:
        for frame, detections in _frames(dataset, scene_id):
            inline.update(frame, detections)
            deferred.update(frame, detections)
            checked += len(deferred.check_all())
            assert deferred.checks_due() == []
            _same(inline.estimates(), deferred.estimates())
        inline.reset()
        deferred.reset()
    assert checked > 0


def test_a_waiting_track_keeps_its_new_views_warped_only_and_the_check_makes_their_maps(
    dataset, default_banks
):
    """The frame's path warps each new view's RoI; the costly maps wait for the check, and are
    the maps the inline step makes of the same view."""
    from posefuse.estimator.verification.edge_maps import EdgeRoi, EdgeView

    inline = MultiViewEstimator(dataset.catalog, TrackerConfig(), banks=default_banks)
    deferred = MultiViewEstimator(
        dataset.catalog, TrackerConfig(deferred_verification=True), banks=default_banks
    )
    rois = 0
    for frame, detections in _frames(dataset, dataset.scene_ids[0]):
        inline.update(frame, detections)
        deferred.update(frame, detections)
        due = set(deferred.checks_due())
        for k, track in deferred.tracks.items():
            waiting = [v for v in track.edge_views if isinstance(v, EdgeRoi)]
            rois += len(waiting)
            assert not waiting or k in due  # only a waiting track holds views without maps
        deferred.check_all()
        for k, track in deferred.tracks.items():
            assert all(isinstance(v, EdgeView) for v in track.edge_views)
            for a, b in zip(track.edge_views, inline.tracks[k].edge_views, strict=True):
                assert a.stamp_ns == b.stamp_ns
                assert np.array_equal(a.dcdt, b.dcdt)
                assert (a.mask_dt is None) == (b.mask_dt is None)
                if a.mask_dt is not None:
                    assert np.array_equal(a.mask_dt, b.mask_dt)
                    assert np.array_equal(a.mask_points, b.mask_points)
    assert rois > 0


def test_a_box_mask_bounds_the_rotation_step_but_its_edges_are_never_the_outline(
    dataset, default_banks
):
    """With box masks the kept views have no mask maps: the verification reads the image's
    edges alone, not the box's sides as if they were the part's outline."""
    from dataclasses import replace

    from posefuse.estimator.verification.edge_maps import EdgeView

    kept = {}
    for kind in ("silhouette", "box"):
        estimator = MultiViewEstimator(dataset.catalog, TrackerConfig(), banks=default_banks)
        for frame, detections in _frames(dataset, dataset.scene_ids[0]):
            estimator.update(frame, [replace(d, mask_kind=kind) for d in detections])
        views = [v for t in estimator.tracks.values() for v in t.edge_views]
        assert views and all(isinstance(v, EdgeView) for v in views)
        kept[kind] = views
    assert all(v.mask_dt is not None and v.mask_points is not None for v in kept["silhouette"])
    assert all(v.mask_dt is None and v.mask_points is None for v in kept["box"])


def test_tracks_wait_longest_first_and_publish_unverified_until_checked(dataset, default_banks):
    estimator = MultiViewEstimator(
        dataset.catalog, TrackerConfig(deferred_verification=True), banks=default_banks
    )
    first_due: dict[str, int] = {}
    for serial, (frame, detections) in enumerate(_frames(dataset, dataset.scene_ids[0]), 1):
        updated = estimator.update(frame, detections)
        for k in estimator.checks_due():
            first_due.setdefault(k, serial)
        # a waiting track is never published as verified
        for e in updated:
            if e.object_id in estimator.checks_due():
                assert not e.verified
    due = estimator.checks_due()
    assert len(due) >= 2
    # the longest waiting first
    assert [first_due[k] for k in due] == sorted(first_due[k] for k in due)
    assert estimator.check_next("no-such-object") is None
    done = estimator.check_next()
    assert done is not None and done.object_id == due[0]
    assert done.verified
    assert estimator.checks_due() == due[1:]
    rest = estimator.check_all()
    assert [e.object_id for e in rest] == due[1:]
    assert estimator.checks_due() == [] and estimator.check_next() is None
    assert all(e.verified for e in rest)
    # checked once at the end, each track's pose is one its views agree on: the verified
    # hypothesis (or its refinement), as a check after every view would give
    for track in estimator.tracks.values():
        if track.object_id in due:
            assert track.verdict is not None
            assert len(track.verdict.weights) == len(track.mixture.components)


def test_without_deferral_or_verification_nothing_waits(dataset, default_banks):
    off = MultiViewEstimator(
        dataset.catalog,
        TrackerConfig.with_verification(False, deferred=True),
        banks=default_banks,
    )
    inline = MultiViewEstimator(dataset.catalog, TrackerConfig(), banks=default_banks)
    for frame, detections in _frames(dataset, dataset.scene_ids[0]):
        off.update(frame, detections)
        inline.update(frame, detections)
        assert off.checks_due() == [] and inline.checks_due() == []
    assert not any(e.verified for e in off.estimates())
    assert any(e.verified for e in inline.estimates())


def test_the_tracks_expect_parts_where_they_are_unless_a_detection_covers_them(
    dataset, default_banks
):
    """``expected_parts``: after a scene, each confirmed track is expected where its true part
    projects (within a few pixels), with a side the part's size at its depth allows; a view's
    own detections cover the tracks they measure; a tentative track is never expected."""
    from posefuse.estimator.tracker.tracks import CONFIRMED

    estimator = MultiViewEstimator(dataset.catalog, TrackerConfig(), banks=default_banks)
    frames = list(_frames(dataset, dataset.scene_ids[0]))
    for frame, detections in frames:
        estimator.update(frame, detections)
    frame, detections = frames[-1]
    scene = dataset.scene(dataset.scene_ids[0])
    view = scene.view(scene.im_ids[-1])
    expected = estimator.expected_parts(frame.camera, frame.T_world_cam)
    confirmed = {k for k, t in estimator.tracks.items() if t.status == CONFIRMED}
    assert expected and {e.object_id for e in expected} <= confirmed
    near = 0
    for e in expected:
        truth = [
            (g, frame.camera.project(g.T_cam_obj[:3, 3]))
            for g in view.gts
            if g.obj_id == e.obj_id and g.T_cam_obj[2, 3] > 0
        ]
        g, uv = min(truth, key=lambda gu: np.linalg.norm(gu[1] - e.center_uv))
        if np.linalg.norm(uv - e.center_uv) <= 5.0:
            near += 1
            # a side between a quarter of the diameter's image and all of it (a box of an
            # elongated part may be far smaller, seen end-on)
            f = frame.camera.K[0, 0]
            diameter_px = f * dataset.catalog[e.obj_id].diameter / g.T_cam_obj[2, 3]
            assert 0.25 * diameter_px <= e.side_px <= diameter_px
    assert near >= 0.8 * len(expected)
    # the view's detections measure most of them: only the others are left
    left = estimator.expected_parts(frame.camera, frame.T_world_cam, detections)
    assert len(left) < len(expected)
    assert {e.object_id for e in left} < {e.object_id for e in expected}


def test_a_snapshot_taken_while_tracks_wait_restores_their_views_and_checks_the_same(
    dataset, default_banks
):
    """Views whose maps the check has not yet made travel in a snapshot; checked after the
    restore, the estimates are those of the estimator that never stopped."""
    import pickle

    from posefuse.estimator.verification.edge_maps import EdgeRoi

    config = TrackerConfig(deferred_verification=True)
    running = MultiViewEstimator(dataset.catalog, config, banks=default_banks)
    for frame, detections in list(_frames(dataset, dataset.scene_ids[0]))[:3]:
        running.update(frame, detections)
    assert any(isinstance(v, EdgeRoi) for t in running.tracks.values() for v in t.edge_views), (
        "no view waited for its maps: the snapshot would not carry one"
    )
    restored = MultiViewEstimator(dataset.catalog, config, banks=default_banks)
    restored.import_state(pickle.loads(pickle.dumps(running.export_state())))
    assert restored.checks_due() == running.checks_due()
    running.check_all()
    restored.check_all()
    _same(running.estimates(), restored.estimates())


def test_a_part_whose_near_symmetric_turns_are_judged_is_deferred_bit_for_bit(
    dataset, default_banks
):
    """The turn judge runs in the check, inline or deferred: with a made-up near-symmetric group
    on every part, the deferred estimates are those of the update, bit for bit, and judged."""
    import dataclasses

    from posefuse.estimator.core.objects import Catalog
    from posefuse.estimator.core.symmetry import SymmetryAxis

    axis = SymmetryAxis((1.0, 0.0, 0.0), 7, 0.02)
    catalog = Catalog(
        [dataclasses.replace(m, near_symmetries=(axis,)) for m in dataset.catalog.values()]
    )
    inline = MultiViewEstimator(catalog, TrackerConfig(), banks=default_banks)
    deferred = MultiViewEstimator(
        catalog, TrackerConfig(deferred_verification=True), banks=default_banks
    )
    for frame, detections in _frames(dataset, dataset.scene_ids[0]):
        inline.update(frame, detections)
        deferred.update(frame, detections)
        deferred.check_all()
        _same(inline.estimates(), deferred.estimates())
    judged = [t for t in deferred.tracks.values() if t.turns is not None]
    assert judged
    for track in judged:
        other = inline.tracks[track.object_id].turns
        assert other is not None and np.array_equal(other.turn, track.turns.turn)
        assert np.array_equal(other.odds, track.turns.odds)
