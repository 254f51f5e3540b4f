"""Faults as a hostile or unlucky network makes them, against ``posefuse serve`` in its own
process on loopback: a camera without info, a pose that never comes, stamps in the far future
(refused on arrival),
clock steps of an hour either way, a second publisher run, a camera that goes silent,
decompression bombs, huge valid frames from many camera ids. After each fault, good frames are
processed, the counters say what happened, and the daemon's RSS stays under RSS_BOUND_MB.

The kill -9 / restart and router restart faults are in test_faults_restart.py.
"""

import time

import numpy as np
import pytest
from loopback import SECOND, FakeCamera, ServeProcess, wait_until, zenoh_peer

from posefuse.service.codec import encode_image

RSS_BOUND_MB = 1024
CELL = "faults"


@pytest.fixture(scope="module")
def served():
    daemon = ServeProcess(
        "--cell",
        CELL,
        env={"POSEFUSE_CAMERA_TIMEOUT_S": "3", "POSEFUSE_WAIT_MS": "500"},
    )
    try:
        with zenoh_peer(daemon.endpoint) as session:
            time.sleep(0.5)
            yield daemon, session
    finally:
        daemon.stop()


def _processed(daemon, cam_id: str) -> int:
    return daemon.stats()["cameras"].get(cam_id, {}).get("processed", 0)


def _dropped(daemon) -> dict:
    return daemon.stats()["frames_dropped"]


def test_a_camera_without_info_and_one_without_pose_block_no_one(served):
    daemon, session = served
    mute = FakeCamera(session, CELL, "mute")
    mute.image_only(5 * SECOND, np.zeros((8, 8, 3), np.uint8))  # its info never comes
    dying = FakeCamera(session, CELL, "dying")
    dying.info()
    dying.pose(5 * SECOND - 10_000_000)
    dying.image_only(5 * SECOND)  # the pose after it never comes: the camera died
    good = FakeCamera(session, CELL, "good")
    good.info()
    good.frames(5 * SECOND + 1, 8, daemon=daemon)
    wait_until(
        lambda: _processed(daemon, "good") == 8, 60, what="8 good frames", context=daemon.stats
    )
    dropped = wait_until(
        lambda: (d := _dropped(daemon)).get("no_info", 0) >= 1 and d.get("no_pose", 0) >= 1 and d,
        10,
        what="the stalled frames dropped at their deadline",
    )
    stats = daemon.stats()
    assert dropped["no_info"] == 1 and dropped["no_pose"] == 1
    assert stats["events"].get("info_requests", 0) >= 1  # the mute camera was asked
    assert stats["frames_pending"] == 0 and stats["processing_errors"] == 0
    assert daemon.rss_mb() < RSS_BOUND_MB


@pytest.mark.parametrize(
    "fault",
    ["far_future_stamp", "clock_minus_1h", "clock_plus_1h", "second_publisher_run"],
)
def test_stamp_faults_are_counted_and_recovered_from(served, fault):
    daemon, session = served
    cam = FakeCamera(session, CELL, f"cam-{fault}")
    cam.info()
    t0 = 5000 * SECOND
    cam.frames(t0, 3, daemon=daemon)
    wait_until(lambda: _processed(daemon, cam.cam_id) == 3, 60, what="3 frames before")
    before = daemon.stats()
    if fault == "far_future_stamp":
        cam.frame(2**63 - 1000)
        after = t0 + SECOND
    elif fault == "clock_minus_1h":
        after = t0 - 3600 * SECOND
    elif fault == "clock_plus_1h":
        after = t0 + 3600 * SECOND
    else:  # the same stamps again, as a publisher started a second time sends them
        after = t0
    cam.frames(after, 6, daemon=daemon)
    wait_until(lambda: _processed(daemon, cam.cam_id) >= 3 + 4, 60, what="frames after the fault")
    stats = daemon.stats()
    if fault == "clock_plus_1h":
        assert _processed(daemon, cam.cam_id) >= 3 + 6  # a jump forward needs nothing
    elif fault == "far_future_stamp":  # refused on arrival: the camera's clock is not dragged
        wait_until(lambda: _processed(daemon, cam.cam_id) == 3 + 6, 60, what="all 6 after")
        stats = daemon.stats()
        future = stats["frames_dropped"]["future_stamp"]
        assert future - before["frames_dropped"].get("future_stamp", 0) == 1
        assert (
            stats["sync_events"]["future_pose"] - before["sync_events"].get("future_pose", 0) == 1
        )
        assert stats["sync_events"].get("reanchored", 0) == before["sync_events"].get(
            "reanchored", 0
        )
        now = time.time_ns()
        assert all(o["stamp_ns"] <= now for o in daemon.objects())  # none from the future
    else:
        reanchored = stats["sync_events"]["reanchored"] - before["sync_events"].get("reanchored", 0)
        assert reanchored == 1
        late = stats["frames_dropped"]["late"] - before["frames_dropped"].get("late", 0)
        assert late == 2  # reanchor_frames - 1
    assert stats["processing_errors"] == 0
    assert daemon.rss_mb() < RSS_BOUND_MB


def test_a_silent_camera_keeps_its_slot_while_slots_are_free(served):
    """Silent past POSEFUSE_CAMERA_TIMEOUT_S (3 s here), a camera is not forgotten while the
    daemon has free slots, and its next frames are processed. (Forgetting at the limit, and
    going on without a new info: tests/service/test_sync.py.)"""
    daemon, session = served
    ghost = FakeCamera(session, CELL, "ghost")
    ghost.info()
    ghost.frames(7 * SECOND, 2, daemon=daemon)
    wait_until(lambda: _processed(daemon, "ghost") == 2, 60, what="ghost frames")
    forgotten = daemon.stats()["sync_events"].get("cameras_forgotten", 0)
    time.sleep(4.0)
    assert "ghost" in daemon.stats()["cameras"]
    assert daemon.stats()["sync_events"].get("cameras_forgotten", 0) == forgotten
    ghost.frames(9 * SECOND, 2, daemon=daemon)
    wait_until(lambda: _processed(daemon, "ghost") == 4, 60, what="ghost frames after a pause")


def test_bombs_and_huge_frames_are_refused_without_decoding(served):
    from posefuse.bench.bombs import image_message, jpeg_bomb, png_bomb

    daemon, session = served
    before = daemon.stats()["decode_errors_by_reason"]
    bombs = {"png": png_bomb(), "jpeg": jpeg_bomb()}
    peak = daemon.rss_mb()
    for k, (encoding, stream) in enumerate(bombs.items()):
        for declared in ((100, 100), (8192, 8192)):
            session.put(
                f"{CELL}/@v1/cam/bomber/image",
                image_message(stream, encoding, (10 + k) * SECOND, declared, "bomber"),
            )
    # valid 8192x8192 frames (a flat JPEG is small on the wire) from 12 camera ids
    huge = encode_image(11 * SECOND, "big", np.full((8192, 8192, 3), 90, np.uint8), "jpeg", 50)
    for k in range(12):
        cam = FakeCamera(session, CELL, f"big{k}")
        cam.info()
        cam.pose(11 * SECOND)
        session.put(cam.key("image"), huge)
        peak = max(peak, daemon.rss_mb())
    good = FakeCamera(session, CELL, "after-bombs")
    good.info()
    good.frames(12 * SECOND, 4, daemon=daemon)
    wait_until(lambda: _processed(daemon, "after-bombs") == 4, 60, what="good frames after")
    peak = max(peak, daemon.rss_mb())
    reasons = daemon.stats()["decode_errors_by_reason"]
    grown = {k: reasons.get(k, 0) - before.get(k, 0) for k in reasons}
    assert grown.get("image_header_mismatch", 0) == 2  # the bombs declared 100x100
    assert grown.get("image_too_large", 0) == 2 + 12  # declared 8192x8192: bombs and frames
    assert peak < RSS_BOUND_MB, f"RSS reached {peak:.0f} MB"
    assert daemon.stats()["processing_errors"] == 0
