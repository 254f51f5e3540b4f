"""Frame synchronisation: latched info, interpolated poses, per-camera order and deadlines,
bounded queues, re-anchoring after clock steps, silent cameras, sequence gaps."""

import numpy as np
import pytest

from posefuse.estimator.core.camera import Camera
from posefuse.service.codec import CameraInfoMsg, CameraPoseMsg, ImageMsg
from posefuse.service.sync import FrameSynchronizer, SyncConfig, interpolate_pose

IMG = np.zeros((2, 2, 3), np.uint8)
CAM = Camera(np.array([[2.0, 0, 1], [0, 2.0, 1], [0, 0, 1]]), 2, 2)  # IMG's camera
MS = 1_000_000


def _pose(x, yaw_deg=0.0):
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix()
    T[0, 3] = x
    return T


def _sync(**kw) -> FrameSynchronizer:
    base = dict(max_pose_gap_ns=1000, exact_tolerance_ns=0, wait_ns=500 * MS)
    base.update(kw)
    return FrameSynchronizer(SyncConfig(**base))


def _ready_camera(s, cam, now=0):
    s.add_info(cam, CameraInfoMsg(0, cam, CAM), now)


def test_interpolation_is_slerp_and_lerp():
    T = interpolate_pose(0, _pose(0.0, 0), 100, _pose(1.0, 90), 25)
    np.testing.assert_allclose(T, _pose(0.25, 22.5), atol=1e-12)


def test_images_wait_for_poses_and_leave_oldest_first():
    s = _sync()
    s.add_image("a", ImageMsg(500, "a", IMG))  # before its info: waits (info is latched)
    assert s.pop() is None
    _ready_camera(s, "a")
    s.add_pose("a", CameraPoseMsg(0, "a", "world", _pose(0.0)))
    assert s.pop() is None  # no pose after stamp 500 yet
    s.add_pose("a", CameraPoseMsg(1000, "a", "world", _pose(1.0)))
    f = s.pop()
    assert f.stamp_ns == 500 and f.camera_id == "a"
    np.testing.assert_allclose(f.T_world_cam[0, 3], 0.5)
    # a late image (not newer than what camera a handed out) is dropped and counted
    assert not s.add_image("a", ImageMsg(400, "a", IMG))
    assert s.dropped["late"] == 1
    # two cameras, both ready: the older stamp first
    _ready_camera(s, "b")
    for cam in ("a", "b"):
        s.add_pose(cam, CameraPoseMsg(2000, cam, "world", _pose(2.0)))
    s.add_image("b", ImageMsg(1200, "b", IMG))
    s.add_image("a", ImageMsg(1100, "a", IMG))
    s.add_pose("b", CameraPoseMsg(1000, "b", "world", _pose(1.0)))
    assert [s.pop().stamp_ns, s.pop().stamp_ns] == [1100, 1200]
    # lateness is per camera: b may still send a frame older than a's last one
    s.add_pose("b", CameraPoseMsg(1300, "b", "world", _pose(1.3)))
    assert s.add_image("b", ImageMsg(1250, "b", IMG))
    assert s.pop().stamp_ns == 1250


def test_queue_keeps_the_latest_and_gaps_are_not_bridged():
    s = _sync(image_queue=2, max_pose_gap_ns=100)
    _ready_camera(s, "a")
    for k in range(5):
        s.add_image("a", ImageMsg(10 + k, "a", IMG))
    assert s.dropped["queue_full"] == 3 and s.pending() == 2
    s.add_pose("a", CameraPoseMsg(0, "a", "world", _pose(0.0)))
    s.add_pose("a", CameraPoseMsg(1000, "a", "world", _pose(1.0)))  # 1 us apart: too far
    assert s.pop(now_ns=100 * MS) is None  # a closer later pose may still come
    assert s.pending() == 2
    assert s.pop(now_ns=600 * MS) is None  # then the deadline passes
    assert s.dropped["no_pose"] == 2 and s.pending() == 0


def test_a_stalled_camera_never_blocks_another():
    """An image without info and one whose pose never comes: the other camera goes on, and
    both stalled images are dropped at their deadline with their reason."""
    s = _sync()
    s.add_image("mute", ImageMsg(1, "mute", np.zeros((8, 8, 3), np.uint8)), now_ns=0)
    _ready_camera(s, "dying")
    s.add_pose("dying", CameraPoseMsg(0, "dying", "world", _pose(0.0)))
    s.add_image("dying", ImageMsg(2, "dying", IMG), now_ns=0)  # its later pose never comes
    _ready_camera(s, "good")
    out = []
    for k in range(8):
        stamp = 10 + 100 * k
        s.add_pose("good", CameraPoseMsg(stamp, "good", "world", _pose(0.0)))
        s.add_image("good", ImageMsg(stamp, "good", IMG), now_ns=k * 50 * MS)
        while (f := s.pop(now_ns=k * 50 * MS)) is not None:
            out.append(f.camera_id)
    assert out == ["good"] * 8
    assert s.pending() == 2
    s.pop(now_ns=501 * MS)
    assert s.dropped["no_info"] == 1 and s.dropped["no_pose"] == 1 and s.pending() == 0


@pytest.mark.parametrize(
    "first_stamp", [2**63 - 1000, 3_600_000_000_000 + 10_000], ids=["far-future", "clock+1h"]
)
def test_a_future_stamp_or_a_clock_step_re_anchors_the_camera(first_stamp):
    s = _sync(reanchor_frames=3)
    _ready_camera(s, "a")
    s.add_pose("a", CameraPoseMsg(first_stamp, "a", "world", _pose(0.0)))
    s.add_image("a", ImageMsg(first_stamp, "a", IMG))
    assert s.pop().stamp_ns == first_stamp
    got = []
    for k in range(6):  # the good clock again
        stamp = 10_000 + 100 * k
        s.add_pose("a", CameraPoseMsg(stamp, "a", "world", _pose(0.0)))
        s.add_image("a", ImageMsg(stamp, "a", IMG))
        while (f := s.pop()) is not None:
            got.append(f.stamp_ns)
    assert s.dropped["late"] == 2 and s.events["reanchored"] == 1
    assert got == [10_000 + 100 * k for k in range(2, 6)]


def test_a_second_publisher_run_re_anchors_and_old_poses_are_forgotten():
    s = _sync(reanchor_frames=2)
    _ready_camera(s, "a")
    for run, x in enumerate((0.0, 5.0)):
        got = []
        for k in range(4):  # the same stamps in both runs, other poses in the second
            stamp = 1000 + 100 * k
            s.add_pose("a", CameraPoseMsg(stamp - 10, "a", "world", _pose(x)))
            s.add_image("a", ImageMsg(stamp, "a", IMG))
            s.add_pose("a", CameraPoseMsg(stamp + 10, "a", "world", _pose(x)))
            while (f := s.pop()) is not None:
                got.append((f.stamp_ns, round(f.T_world_cam[0, 3], 9)))
        expected = [(1000 + 100 * k, x) for k in range(0 if run == 0 else 1, 4)]
        assert got == expected


def test_pose_buffer_forgets_the_least_recently_received():
    s = _sync(pose_buffer=3)
    _ready_camera(s, "a")
    for stamp in (10_000, 10_100, 10_200):
        s.add_pose("a", CameraPoseMsg(stamp, "a", "world", _pose(1.0)))
    for stamp in (100, 200, 300):  # a clock stepped back: these replace the old ones
        s.add_pose("a", CameraPoseMsg(stamp, "a", "world", _pose(2.0)))
    s.add_image("a", ImageMsg(150, "a", IMG))
    f = s.pop()
    assert f is not None and f.T_world_cam[0, 3] == 2.0


def _working_camera(s, cam, now=0):
    """A camera that completed a frame: info, pose, image, handed out."""
    _ready_camera(s, cam, now)
    s.add_pose(cam, CameraPoseMsg(1, cam, "world", _pose(0.0)), now)
    s.add_image(cam, ImageMsg(1, cam, IMG), now)
    assert s.pop(now).camera_id == cam


def test_silent_cameras_are_forgotten_and_cameras_are_bounded():
    s = _sync(max_cameras=2, camera_timeout_ns=10 * 10**9)
    _working_camera(s, "a", now=0)
    _working_camera(s, "b", now=0)
    assert not s.add_image("c", ImageMsg(1, "c", IMG), now_ns=1)
    assert s.dropped["too_many_cameras"] == 1
    assert s.add_image("c", ImageMsg(1, "c", IMG), now_ns=11 * 10**9)  # a and b went silent
    assert s.cameras() == ["c"] and s.events["cameras_forgotten"] == 2


def test_a_camera_that_pauses_keeps_its_slot_while_one_is_free():
    """Silent far longer than camera_timeout_ns, a camera is still known (its info latched) as
    long as no new camera needs its slot; it goes on from its next frame without a new info."""
    s = _sync(max_cameras=2, camera_timeout_ns=10 * 10**9)
    _working_camera(s, "a", now=0)
    much_later = 100 * 10**9
    assert s.pop(much_later) is None
    assert s.cameras() == ["a"] and s.events["cameras_forgotten"] == 0
    for t in (1400, 1600):
        s.add_pose("a", CameraPoseMsg(t, "a", "world", _pose(0.0)), much_later)
    s.add_image("a", ImageMsg(1500, "a", IMG), much_later)
    assert s.pop(much_later).stamp_ns == 1500  # no new info needed


def test_queued_bytes_are_bounded_latest_win():
    big = np.zeros((100, 100, 3), np.uint8)  # 30 kB
    s = _sync(max_queued_bytes=100_000, image_queue=10)
    for k, cam in enumerate("abcd" * 2):
        s.add_image(cam, ImageMsg(k + 1, cam, big))
    assert s.queued_bytes() <= 100_000 and s.dropped["memory"] == 5
    assert not s.add_image("a", ImageMsg(99, "a", np.zeros((200, 200, 3), np.uint8)))


def test_sequence_gaps_and_restarts_are_counted_per_camera():
    s = _sync()
    for seq in (0, 1, 2, 5, 6, 0, 1):
        s.add_image("a", ImageMsg(seq + 1, "a", IMG, seq=seq))
    for seq in (0, 10):
        s.add_pose("a", CameraPoseMsg(seq, "a", "world", _pose(0.0), seq=seq))
    counters = s.camera_counters()["a"]
    assert counters["lost"] == {"image": 2, "pose": 9}
    assert counters["restarts"] == {"image": 1}
    assert counters["images"] == 7 and counters["poses"] == 2 and counters["synced"] == 0


def test_a_camera_that_never_completed_a_frame_yields_its_slot():
    s = _sync(max_cameras=4)
    _working_camera(s, "real")
    _ready_camera(s, "starting", now=5)  # an info, no pose yet
    s.add_image("junk0", ImageMsg(1, "junk0", IMG), 1)  # neither info nor pose
    s.add_image("junk1", ImageMsg(1, "junk1", IMG), 2)
    # full: a new camera takes the slot of the junk seen longest ago, then of the other
    _ready_camera(s, "new", now=10)
    assert s.cameras() == ["junk1", "new", "real", "starting"]
    assert s.events["cameras_evicted"] == 1 and s.dropped["camera_evicted"] == 1
    _ready_camera(s, "new2", now=11)
    assert s.cameras() == ["new", "new2", "real", "starting"]
    # then one with an info but no pose (the least recently seen); a working one never
    assert s.add_image("late", ImageMsg(1, "late", IMG), 12)
    assert "starting" not in s.cameras() and "real" in s.cameras()
    s.add_pose("new", CameraPoseMsg(1, "new", "world", _pose(0.0)), 13)
    s.add_pose("new2", CameraPoseMsg(1, "new2", "world", _pose(0.0)), 13)
    s.add_pose("late", CameraPoseMsg(1, "late", "world", _pose(0.0)), 13)
    _ready_camera(s, "late", now=13)
    # every camera has an info and a pose now: the ones that never sent an image yield first
    assert s.add_image("more", ImageMsg(1, "more", IMG), 14)
    assert "real" in s.cameras() and "more" in s.cameras() and len(s.cameras()) == 4
    assert s.dropped["too_many_cameras"] == 0  # (working cameras only refuse: the test above)


def test_cameras_that_never_send_an_image_do_not_lock_a_real_one_out():
    """Fifteen ids that send one valid info and pose each, never an image, and one working
    camera fill the sixteen slots: a new camera with images still gets one, and the working
    camera, silent for a while, keeps its own while such ids hold slots."""
    s = _sync(max_cameras=16, camera_timeout_ns=10 * 10**9)
    _working_camera(s, "real", now=0)
    for k in range(15):
        _ready_camera(s, f"junk{k:02d}", now=k)
        s.add_pose(f"junk{k:02d}", CameraPoseMsg(1, f"junk{k:02d}", "world", _pose(0.0)), k)
    later = 20 * 10**9  # "real" has been silent longer than camera_timeout_ns
    assert s.add_image("new", ImageMsg(1, "new", IMG), later)
    assert "new" in s.cameras() and "real" in s.cameras() and "junk00" not in s.cameras()
    assert s.events["cameras_evicted"] == 1 and s.dropped["too_many_cameras"] == 0


def test_frames_and_poses_stamped_ahead_of_the_clock_are_refused():
    s = _sync(max_future_ns=10 * 10**9)
    _ready_camera(s, "a")
    now = 1000 * 10**9
    assert not s.add_pose("a", CameraPoseMsg(2**63 - 1000, "a", "world", _pose(0.0)), now)
    assert not s.add_image("a", ImageMsg(2**63 - 1000, "a", IMG), now)
    assert not s.add_image("a", ImageMsg(now + 10 * 10**9 + 1, "a", IMG), now)
    assert s.dropped["future_stamp"] == 2 and s.events["future_pose"] == 1
    stamp = now + 10 * 10**9  # at the margin: taken
    s.add_pose("a", CameraPoseMsg(stamp, "a", "world", _pose(0.0)), now)
    assert s.add_image("a", ImageMsg(stamp, "a", IMG), now)
    assert s.pop(now).stamp_ns == stamp and s.pending() == 0


def test_an_image_of_another_size_than_its_info_is_dropped_and_counted():
    """The intrinsics of a 2x2 camera are never used on a 4x2 image (a camera that changed its
    resolution without a new info): the image is dropped, and counted by why."""
    s = _sync()
    _ready_camera(s, "a")
    s.add_pose("a", CameraPoseMsg(0, "a", "world", _pose(0.0)))
    s.add_pose("a", CameraPoseMsg(1000, "a", "world", _pose(1.0)))
    assert s.add_image("a", ImageMsg(100, "a", np.zeros((2, 4, 3), np.uint8)))
    assert s.pop() is None
    assert s.dropped["size_unlike_info"] == 1
    assert s.add_image("a", ImageMsg(200, "a", IMG))  # its own size passes
    assert s.pop().stamp_ns == 200


def test_every_camera_gets_its_share_when_the_estimator_falls_behind():
    """Four cameras publish in the same order every cycle and the estimator takes two frames a
    cycle: each camera gets half of its frames processed (oldest-first alone served the first
    two cameras every cycle and let the last two drop everything)."""
    s = _sync(image_queue=2)
    cams = ["a", "b", "c", "d"]
    for cam in cams:
        _ready_camera(s, cam)
        s.add_pose(cam, CameraPoseMsg(0, cam, "world", _pose(0.0)))
    served = dict.fromkeys(cams, 0)
    cycles = 40
    for cycle in range(cycles):
        base = (cycle + 1) * 1000
        for k, cam in enumerate(cams):
            for t in (base - 1, base + 500):  # poses no further apart than max_pose_gap_ns
                s.add_pose(cam, CameraPoseMsg(t, cam, "world", _pose(1.0)))
            s.add_image(cam, ImageMsg(base + k, cam, IMG))
        for _ in range(2):
            frame = s.pop()
            served[frame.camera_id] += 1
    mean = sum(served.values()) / len(cams)
    assert mean == cycles * 2 / len(cams)
    assert all(abs(n - mean) <= 0.2 * mean for n in served.values()), served


def test_the_wait_for_a_pose_counts_from_the_synchroniser_not_from_arrival():
    """An image that spent 2 s waiting for a decoder (behind another camera's flood) reaches the
    synchroniser just before its pose does: it waits for that pose, and its latency still counts
    from its arrival."""
    s = _sync()
    _ready_camera(s, "a")
    s.add_image("a", ImageMsg(500, "a", IMG), now_ns=2000 * MS, arrival_ns=0)
    assert s.pop(2010 * MS) is None and s.dropped["no_pose"] == 0
    s.add_pose("a", CameraPoseMsg(500, "a", "world", _pose(0.0)), 2020 * MS)
    frame = s.pop(2030 * MS)
    assert frame is not None and frame.arrival_ns == 0
    # the wait itself is still bounded: half a second after it reached the synchroniser
    s.add_image("a", ImageMsg(600, "a", IMG), now_ns=3000 * MS, arrival_ns=1000 * MS)
    assert s.pop(3400 * MS) is None
    assert s.pop(3600 * MS) is None and s.dropped["no_pose"] == 1
