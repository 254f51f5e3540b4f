"""A snapshot written before the estimator's modules were grouped by the method's steps
(state version 2: its classes named by their old modules, a track's views as plain tuples) is
restored by today's daemon, and its tracks publish what they published then, to the bit.

``tests/data/state_v2`` holds such a snapshot of two tracks of a rendered scene (three views,
verified and refined) and the estimates the estimator of that version published for them."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from posefuse.estimator.core.camera import Camera
from posefuse.estimator.core.objects import load_catalog
from posefuse.estimator.tracker import (
    DetectionRef,
    Frame,
    MultiViewEstimator,
    PendingView,
    ViewRef,
)
from posefuse.estimator.tracker.snapshot import STATE_VERSION, legacy_class, upgrade
from posefuse.service.resources import DEFAULT_CATALOG
from posefuse.service.state import StateError, StateStore, catalog_fingerprint

TESTS = Path(__file__).resolve().parents[2]
DATA = TESTS / "data" / "state_v2"


@pytest.fixture(scope="module")
def catalog():
    return load_catalog(DEFAULT_CATALOG)


def _store(tmp_path, catalog) -> StateStore:
    shutil.copytree(DATA, tmp_path / "state")
    return StateStore(tmp_path / "state", catalog_fingerprint(catalog))


def _assert_published(estimator, expected):
    got = {e.object_id: e for e in estimator.estimates()}
    assert sorted(got) == sorted(expected)
    for object_id, want in expected.items():
        e = got[object_id]
        np.testing.assert_array_equal(e.T_world_obj, np.array(want["T_world_obj"]))
        np.testing.assert_array_equal(e.cov, np.array(want["cov"]))
        assert e.confidence == want["confidence"]
        assert (e.n_views, e.status) == (want["n_views"], want["status"])
        assert len(e.hypotheses) == len(want["hypotheses"])
        for h, (q, weight, n) in zip(e.hypotheses, want["hypotheses"], strict=True):
            np.testing.assert_array_equal(h.q, np.array(q))
            assert (h.weight, h.n) == (weight, n)


def test_a_version_2_snapshot_restores_and_publishes_what_it_did(tmp_path, catalog):
    expected = json.loads((DATA / "expected.json").read_text())
    state = _store(tmp_path, catalog).load()
    assert state["version"] == 2
    estimator = MultiViewEstimator(catalog)
    estimator.import_state(state)
    assert estimator.last_stamp_ns == expected["stamp_ns"]
    for track in estimator.tracks.values():
        assert track.refs and all(isinstance(r, ViewRef) for r in track.refs)
        assert all(isinstance(d, DetectionRef) for d in track.detections)
        assert all(isinstance(p, PendingView) for p in track.pending)
        assert track.edge_views and track.verdict is not None and track.refined is not None
    _assert_published(estimator, expected["estimates"])

    # it goes on: a view without detections, then saved as this version and read back
    camera = Camera(np.array([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1]]), 640, 480)
    estimator.update(Frame(expected["stamp_ns"] + 1, camera, np.eye(4)), [])
    store = StateStore(tmp_path / "again", catalog_fingerprint(catalog))
    store.save(estimator.export_state())
    again = MultiViewEstimator(catalog)
    again.import_state(store.load())
    assert again.export_state()["version"] == STATE_VERSION == 3
    assert sorted(again.tracks) == sorted(estimator.tracks)
    for k, track in again.tracks.items():
        np.testing.assert_array_equal(
            track.estimate.t_world_obj, estimator.tracks[k].estimate.t_world_obj
        )


def test_only_known_versions_and_known_classes_are_taken(tmp_path, catalog):
    with pytest.raises(ValueError, match="version must be 2 or 3"):
        upgrade({"version": 1, "tracks": {}})
    with pytest.raises(ValueError, match="version"):
        MultiViewEstimator(catalog).import_state({"version": 4})
    assert legacy_class("posefuse.estimator.mixture", "RotationMixture").__module__ == (
        "posefuse.estimator.rotation.mixture"
    )
    assert legacy_class("posefuse.estimator.mixture", "NoSuchClass") is None
    assert legacy_class("posefuse.nowhere", "Track") is None
    # a snapshot naming a class no module has is set aside with its reason
    store = _store(tmp_path, catalog)
    body = store.path.read_bytes().replace(b"RotationMixture", b"RotationMixturX")
    store.path.write_bytes(body)
    with pytest.raises(StateError, match="unreadable"):
        store.load()
    assert store.path.with_suffix(".rejected").is_file()
