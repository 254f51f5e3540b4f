"""The worker's deferred verification: fused frames leave tracks waiting, checked one at a time
(the daemon's slices between frames) or all after each frame (offline replay); counted and
timed for ``/stats``; a reset forgets the waiting tracks it removed."""

from __future__ import annotations

import pytest

from posefuse.estimator.tracker import MultiViewEstimator
from posefuse.evaluation.dataset import load_dataset
from posefuse.evaluation.oracle import OracleConfig, OracleFrontend
from posefuse.service.settings import Settings
from posefuse.service.sync import SyncedFrame
from posefuse.service.worker import EstimatorWorker, tracker_config


@pytest.fixture(scope="module")
def scene_frames(small_dataset_root):
    """The first scene's frames and an oracle front end that knows them by stamp."""
    dataset = load_dataset(small_dataset_root)
    front = OracleFrontend(dataset, OracleConfig(center_sigma_px=1.0, with_masks=True, seed=0))
    scene = dataset.scene(dataset.scene_ids[0])
    views = {}
    frames = []
    for k, im in enumerate(scene.im_ids, 1):
        view = scene.view(im)
        stamp = k * 100_000_000
        views[stamp] = view
        frames.append(
            SyncedFrame("cam0", stamp, scene.load_rgb(im), view.camera, view.T_world_cam, stamp)
        )
    return dataset, frames, lambda image, stamp_ns: front.detect(views[stamp_ns])


def _worker(dataset, detect, default_banks, **settings):
    config = tracker_config(Settings(**settings))
    return EstimatorWorker(MultiViewEstimator(dataset.catalog, config, banks=default_banks), detect)


def test_the_daemon_is_verified_by_default_and_can_be_told_not_to(monkeypatch):
    assert Settings().verify
    config = tracker_config(Settings())
    assert config.verification.enabled and config.deferred_verification
    assert config.verification.turns.enabled
    monkeypatch.setenv("POSEFUSE_VERIFY_TURNS", "0")
    judge_off = tracker_config(Settings())
    assert judge_off.verification.enabled and not judge_off.verification.turns.enabled
    monkeypatch.setenv("POSEFUSE_VERIFY", "0")
    assert not tracker_config(Settings()).verification.enabled


def test_the_daemon_knows_the_bin_only_when_told(monkeypatch):
    """The nbv_bin_* settings are an example bin until POSEFUSE_BIN_KNOWN says they are the
    cell's: then the estimator gets that bin, as the environment places it; a bin that is
    none is refused when the settings are read, naming them."""
    import numpy as np
    import pytest

    from posefuse.bench.daemon_accuracy import as_environment, bin_settings
    from posefuse.estimator.core.bin_region import BinRegion

    assert tracker_config(Settings()).bin is None
    monkeypatch.setenv("POSEFUSE_BIN_KNOWN", "1")
    monkeypatch.setenv("POSEFUSE_NBV_BIN_CENTER", "[0.5, -0.2, 0.7]")
    monkeypatch.setenv("POSEFUSE_NBV_BIN_SIZE", "[0.6, 0.4]")
    region = tracker_config(Settings()).bin
    assert region is not None and region.size == (0.6, 0.4)
    np.testing.assert_array_equal(region.T_world_bin[:3, 3], [0.5, -0.2, 0.7])
    assert region.distance_outside(np.array([0.5, -0.2, 0.65])) == pytest.approx(0.05)
    monkeypatch.setenv("POSEFUSE_NBV_BIN_SIZE", "[0.6, 0.0]")
    with pytest.raises(ValueError, match=r"nbv_bin_size.*got size \(0.6, 0.0\)"):
        Settings()
    monkeypatch.setenv("POSEFUSE_NBV_BIN_SIZE", "[0.6, 0.4]")
    monkeypatch.setenv("POSEFUSE_NBV_BIN_CENTER", "[0.5, Infinity, 0.7]")
    with pytest.raises(ValueError, match="nbv_bin_center must be finite"):
        Settings()
    monkeypatch.setenv("POSEFUSE_NBV_BIN_CENTER", "[0.5, -0.2, 0.7]")
    # a dataset's bin told to a daemon's process, as the accuracy bench tells it
    T = np.eye(4)
    T[:3, 3] = [0.1, 0.0, -0.3]
    given = BinRegion((0.42, 0.32), 0.08, T)
    for name, value in as_environment(bin_settings(given)).items():
        monkeypatch.setenv(name, value)
    told = tracker_config(Settings()).bin
    assert told.to_json() == given.to_json()
    assert bin_settings(None) == {}


def test_fused_frames_leave_tracks_waiting_and_slices_check_them_oldest_first(
    scene_frames, default_banks
):
    dataset, frames, detect = scene_frames
    worker = _worker(dataset, detect, default_banks)
    for frame in frames:
        fast = worker.fuse(frame, worker.detections(frame))
        waiting = set(worker.estimator.checks_due())
        assert all(not e.verified for e in fast if e.object_id in waiting)
    due = worker.estimator.checks_due()
    assert worker.checks_waiting() == len(due) >= 2
    assert worker.verification_stats()["waiting"] == len(due)
    first = worker.check_next(now_ns=frames[-1].arrival_ns + 50_000_000)
    assert first.object_id == due[0] and first.verified
    # timed from the arrival of the first frame the track waited for
    assert worker.check_latencies_ms[-1] >= 50.0
    # readers see the checked estimate
    assert worker.get(first.object_id).verified
    while worker.check_next() is not None:
        pass
    stats = worker.verification_stats()
    assert stats["waiting"] == 0 and stats["checked"] == len(due) and stats["enabled"]
    assert stats["latency"]["p50_ms"] is not None


def test_offline_processing_publishes_the_fast_estimate_then_the_verified_one(
    scene_frames, default_banks
):
    dataset, frames, detect = scene_frames
    worker = _worker(dataset, detect, default_banks)
    verified_after_fast = 0
    for frame in frames:
        published = worker.process(frame)
        assert worker.checks_waiting() == 0
        seen_fast = set()
        for e in published:
            if not e.verified:
                seen_fast.add(e.object_id)
            elif e.object_id in seen_fast:
                verified_after_fast += 1
    assert verified_after_fast > 0


def test_a_reset_forgets_the_waiting_tracks_it_removed(scene_frames, default_banks):
    dataset, frames, detect = scene_frames
    worker = _worker(dataset, detect, default_banks)
    for frame in frames[:4]:
        worker.fuse(frame, worker.detections(frame))
    assert worker.checks_waiting() > 0
    worker.reset()
    assert worker.checks_waiting() == 0 and worker.check_next() is None


def test_a_check_that_raises_leaves_the_track_unverified_and_waiting_no_more(
    scene_frames, default_banks, monkeypatch
):
    from posefuse.estimator.tracker.pose_stage import PoseStage

    dataset, frames, detect = scene_frames
    worker = _worker(dataset, detect, default_banks)
    for frame in frames:
        worker.process(frame)  # every track verified, none waiting
    verified = [e.object_id for e in worker.snapshot() if e.verified]  # readers' copy made
    assert verified and not worker.estimator.checks_due()
    worker.estimator.tracks[verified[0]].check_since = 0  # it waits again

    def broken(self, track, added):
        raise RuntimeError("a bug in a check")

    monkeypatch.setattr(PoseStage, "check", broken)
    with pytest.raises(RuntimeError):
        worker.check_next()
    # it waits no more (a check that always fails cannot hold the loop), and readers see it
    # as its mixture gives it, not as verified
    assert worker.estimator.checks_due() == []
    assert not worker.get(verified[0]).verified


def test_tracks_that_leave_stop_counting_as_waiting_at_the_next_frame(scene_frames, default_banks):
    dataset, frames, detect = scene_frames
    worker = _worker(dataset, detect, default_banks)
    for frame in frames[:-1]:
        worker.fuse(frame, worker.detections(frame))
    assert worker.checks_waiting() > 0
    worker.estimator.reset()  # behind the worker's back, as a drop or a merge would
    worker.fuse(frames[-1], worker.detections(frames[-1]))
    assert worker.checks_waiting() == len(worker.estimator.checks_due())


def test_the_daemons_network_threads_sleep_after_a_run_unless_told_to_spin(monkeypatch):
    from posefuse.service.worker import make_detector

    assert not Settings().onnx_spin
    monkeypatch.setenv("POSEFUSE_ONNX_SPIN", "1")
    assert Settings().onnx_spin
    monkeypatch.delenv("POSEFUSE_ONNX_SPIN")
    seen = {}

    class Recorder:
        def __init__(self, model, catalog, threads, spin):
            seen.update(threads=threads, spin=spin)

    monkeypatch.setattr("posefuse.estimator.frontend.network.NetworkFrontend", Recorder)
    make_detector(Settings(onnx_threads=1), catalog=None)
    assert seen == {"threads": 1, "spin": False}


def test_the_daemon_takes_the_verification_settings_its_models_card_gives(tmp_path):
    """A part set's card (``verification``, written by onboarding) sets the verification's
    mask weight, poor-fit bound and covariance floor; the shipped model's card has none and
    keeps the defaults."""
    import json
    import shutil
    from pathlib import Path

    from posefuse.estimator.verification.verify import VerificationConfig
    from posefuse.service.settings import DEFAULT_MODEL

    default = tracker_config(Settings())
    assert default.verification.mask_weight == VerificationConfig().mask_weight
    assert default.verification.max_fit == VerificationConfig().max_fit
    model = Path(DEFAULT_MODEL)
    card = json.loads(model.with_suffix(".json").read_text())
    shutil.copy(model, tmp_path / model.name)
    if card.get("two_stage", {}).get("crop_model"):
        shutil.copy(model.parent / card["two_stage"]["crop_model"], tmp_path)
    copy = tmp_path / model.name
    settings = {"mask_weight": 0.25, "max_fit": 0.9, "refinement.floor_rotation_deg": 3.0}
    copy.with_suffix(".json").write_text(json.dumps({**card, "verification": settings}))
    config = tracker_config(Settings(model=copy))
    assert (config.verification.mask_weight, config.verification.max_fit) == (0.25, 0.9)
    assert config.refinement.floor_rotation_deg == 3.0  # the published covariance's floor
    assert default.refinement.floor_rotation_deg != 3.0
    assert config.verification.enabled and config.deferred_verification
    assert config.verification.edges == default.verification.edges
