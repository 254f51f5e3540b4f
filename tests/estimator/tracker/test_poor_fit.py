"""A confirmed track whose verified pose fits its views' edges poorly is published as
tentative (``VerificationConfig.max_fit``, ``Track.fit``): a track of a part fits and stays
confirmed; a track of nothing (detections of a part where none is, as a pile's stray centres
make) is confirmed by its centres, and its pose fits nothing the views show."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from posefuse.estimator.frontend.detection import Detection
from posefuse.estimator.tracker import CONFIRMED, Frame, MultiViewEstimator, TrackerConfig
from posefuse.estimator.tracker.tracks import TENTATIVE
from posefuse.estimator.verification.verify import VerificationConfig, score_hypotheses
from posefuse.evaluation.dataset import load_dataset
from posefuse.evaluation.oracle import OracleConfig, OracleFrontend


@pytest.fixture(scope="module")
def dataset(small_dataset_root):
    return load_dataset(small_dataset_root)


def _ghost(view, obj_id: int, p_world: np.ndarray, side_px: float) -> Detection:
    """A detection of class ``obj_id`` centred on the projection of ``p_world``, where no part
    is: a filled disc of the part's apparent size as its silhouette."""
    uv = view.camera.project((view.T_cam_world @ np.append(p_world, 1.0))[:3])
    h, w = view.camera.height, view.camera.width
    yy, xx = np.mgrid[0:h, 0:w]
    mask = (xx - uv[0]) ** 2 + (yy - uv[1]) ** 2 <= (side_px / 2) ** 2
    box = np.array([uv[0] - side_px / 2, uv[1] - side_px / 2, side_px, side_px])
    return Detection(obj_id, box, uv, np.eye(2) * 4.0, mask, 0.9)


def _run(dataset, banks, config: TrackerConfig, ghost_at=None):
    """The estimator over the first scene's views (oracle detections, and a ghost's in every
    view when ``ghost_at`` = (obj_id, p_world, side_px)); returns it and the ghost's class."""
    front = OracleFrontend(dataset, OracleConfig(center_sigma_px=1.0, with_masks=True, seed=0))
    scene = dataset.scene(dataset.scene_ids[0])
    estimator = MultiViewEstimator(dataset.catalog, config, banks=banks)
    for im in scene.im_ids:
        view = scene.view(im)
        detections = front.detect(view)
        if ghost_at is not None:
            detections = [*detections, _ghost(view, *ghost_at)]
        estimator.update(Frame(im, view.camera, view.T_world_cam, scene.load_rgb(im)), detections)
    return estimator


def _ghost_place(dataset):
    """A class of the scene and a point above the bin's floor, away from every part of it."""
    scene = dataset.scene(dataset.scene_ids[0])
    view = scene.view(scene.im_ids[0])
    parts = np.array([(view.T_world_cam @ g.T_cam_obj)[:3, 3] for g in view.gts])
    obj_id = view.gts[0].obj_id
    d = dataset.catalog[obj_id].diameter
    centre = parts.mean(0)
    # the floor's point farthest from the parts, on a ring around their middle
    angles = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    ring = centre + 0.12 * np.stack([np.cos(angles), np.sin(angles), np.zeros_like(angles)], 1)
    far = ring[np.argmax([np.min(np.linalg.norm(parts - p, axis=1)) for p in ring])]
    side = d * view.camera.K[0, 0] / np.linalg.norm((view.T_cam_world @ np.append(far, 1))[:3])
    return obj_id, far, side


def test_the_tracks_of_parts_fit_and_are_published_confirmed(dataset, default_banks):
    config = TrackerConfig()
    estimator = _run(dataset, default_banks, config)
    estimates = {e.object_id: e for e in estimator.estimates()}
    verified = [t for t in estimator.tracks.values() if t.status == CONFIRMED and t.fit is not None]
    assert verified
    for track in verified:
        assert track.fit <= config.verification.max_fit, track.object_id
        assert estimates[track.object_id].status == CONFIRMED


def test_the_fit_is_the_published_pose_s_cost_in_the_kept_views(dataset, default_banks):
    config = TrackerConfig()
    estimator = _run(dataset, default_banks, config)
    estimates = {e.object_id: e for e in estimator.estimates()}
    checked = 0
    for track in estimator.tracks.values():
        if track.fit is None:
            continue
        T = estimates[track.object_id].T_world_obj
        edges, _ = estimator.poses.model_edges(track.obj_id)
        cost = score_hypotheses(
            edges, track.edge_views, T[None, :3, :3], T[:3, 3], config.verification
        )
        assert track.fit == pytest.approx(float(cost.mean()), rel=1e-12)
        checked += 1
    assert checked


def test_a_track_of_nothing_is_confirmed_by_its_centres_and_published_tentative(
    dataset, default_banks
):
    obj_id, p_world, side = _ghost_place(dataset)
    config = TrackerConfig()
    estimator = _run(dataset, default_banks, config, (obj_id, p_world, side))
    # the ghost's track: the confirmed track of its class nearest the made-up point
    ghost = min(
        (t for t in estimator.tracks.values() if t.obj_id == obj_id),
        key=lambda t: np.linalg.norm(t.estimate.t_world_obj - p_world),
    )
    d = dataset.catalog[obj_id].diameter
    assert np.linalg.norm(ghost.estimate.t_world_obj - p_world) < 0.1 * d
    assert ghost.status == CONFIRMED
    assert ghost.fit is not None and ghost.fit > config.verification.max_fit
    published = {e.object_id: e for e in estimator.estimates(include_tentative=True)}
    assert published[ghost.object_id].status == TENTATIVE
    assert ghost.object_id not in {
        e.object_id for e in estimator.estimates(include_tentative=False)
    }

    # without the gate the same track is published confirmed, and no pose changes
    off = replace(config, verification=replace(config.verification, max_fit=None))
    ungated = _run(dataset, default_banks, off, (obj_id, p_world, side))
    again = {e.object_id: e for e in ungated.estimates(include_tentative=True)}
    assert again[ghost.object_id].status == CONFIRMED
    assert ungated.tracks[ghost.object_id].fit is None  # nothing measured without the gate
    for k, e in published.items():
        assert np.array_equal(e.T_world_obj, again[k].T_world_obj), k


@pytest.mark.parametrize("value", [0.0, -1.0, float("nan")])
def test_a_gate_that_would_hold_back_every_track_is_refused(value):
    with pytest.raises(ValueError, match="invalid verification config"):
        VerificationConfig(max_fit=value)
