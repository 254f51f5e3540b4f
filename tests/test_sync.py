"""Frame synchronisation: latched info, interpolated poses, stamp order, bounded queues."""

import numpy as np

from service.codec import CameraInfoMsg, CameraPoseMsg, ImageMsg
from service.sync import FrameSynchronizer, interpolate_pose
from sim.scenes import REALSENSE_1280x720 as CAM

IMG = np.zeros((2, 2, 3), np.uint8)


def _pose(x, yaw_deg=0.0):
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix()
    T[0, 3] = x
    return T


def test_interpolation_is_slerp_and_lerp():
    T = interpolate_pose(0, _pose(0.0, 0), 100, _pose(1.0, 90), 25)
    np.testing.assert_allclose(T, _pose(0.25, 22.5), atol=1e-12)


def test_images_wait_for_poses_and_leave_in_stamp_order():
    s = FrameSynchronizer(
        image_queue=4, max_pose_gap_ns=1000, pose_wait_ns=10_000, exact_tolerance_ns=0
    )
    s.add_image("a", ImageMsg(500, "a", IMG))  # before its info: waits (info is latched)
    assert s.pop() is None
    s.add_info("a", CameraInfoMsg(0, "a", CAM))
    s.add_pose("a", CameraPoseMsg(0, "a", "world", _pose(0.0)))
    assert s.pop() is None  # no pose after stamp 500 yet
    s.add_pose("a", CameraPoseMsg(1000, "a", "world", _pose(1.0)))
    f = s.pop()
    assert f.stamp_ns == 500 and f.camera_id == "a"
    np.testing.assert_allclose(f.T_world_cam[0, 3], 0.5)
    # a late image (older than what was handed out) is dropped and counted
    s.add_image("a", ImageMsg(400, "a", IMG))
    assert s.dropped["late"] == 1
    # two cameras: global stamp order
    s.add_info("b", CameraInfoMsg(0, "b", CAM))
    for cam in ("a", "b"):
        s.add_pose(cam, CameraPoseMsg(2000, cam, "world", _pose(2.0)))
    s.add_image("b", ImageMsg(1200, "b", IMG))
    s.add_image("a", ImageMsg(1100, "a", IMG))
    s.add_pose("b", CameraPoseMsg(1000, "b", "world", _pose(1.0)))
    assert [s.pop().stamp_ns, s.pop().stamp_ns] == [1100, 1200]


def test_queue_keeps_the_latest_and_gaps_are_not_bridged():
    s = FrameSynchronizer(image_queue=2, max_pose_gap_ns=100, exact_tolerance_ns=0)
    s.add_info("a", CameraInfoMsg(0, "a", CAM))
    for k in range(5):
        s.add_image("a", ImageMsg(10 + k, "a", IMG))
    assert s.dropped["queue_full"] == 3 and s.pending() == 2
    s.add_pose("a", CameraPoseMsg(0, "a", "world", _pose(0.0)))
    s.add_pose("a", CameraPoseMsg(1000, "a", "world", _pose(1.0)))  # 1 us apart: too far
    assert s.pop() is None
    assert s.dropped["no_pose"] == 2
