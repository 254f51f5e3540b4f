"""Per-camera buffers that turn decoded messages into estimator frames, in stamp order.

- Camera info is latched: the latest one of a camera is used for all its images.
- Camera poses may come at another rate: an image's pose is interpolated (slerp / lerp) between
  the poses around its stamp, if they are at most ``max_pose_gap_ns`` apart; a pose within
  ``exact_tolerance_ns`` of the stamp is used as is.
- Images wait in a bounded queue per camera; when it is full the oldest is dropped (the latest
  frames win when the estimator falls behind).
- Frames leave in global stamp order; an image older than the last frame handed out is late and
  dropped, and one that has waited for a later pose longer than ``pose_wait_ns`` (in stamp time
  of that camera's newer images) is dropped too. Every drop is counted by reason.

Thread-safe: decoders call the ``add_*`` methods from transport threads, the worker ``pop``.
"""

from __future__ import annotations

import bisect
import threading
from collections import Counter, deque
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from estimator.camera import Camera
from service.codec import CameraInfoMsg, CameraPoseMsg, ImageMsg


@dataclass(frozen=True, eq=False)
class SyncedFrame:
    camera_id: str
    stamp_ns: int
    image: np.ndarray  # (H, W, 3) uint8 RGB
    camera: Camera
    T_world_cam: np.ndarray  # (4, 4)


def interpolate_pose(t0: int, T0: np.ndarray, t1: int, T1: np.ndarray, t: int) -> np.ndarray:
    """Pose at stamp t between (t0, T0) and (t1, T1): slerp of the rotation, lerp of t."""
    if t1 == t0:
        return T0.copy()
    a = (t - t0) / (t1 - t0)
    slerp = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([T0[:3, :3], T1[:3, :3]])))
    T = np.eye(4)
    T[:3, :3] = slerp([a]).as_matrix()[0]
    T[:3, 3] = (1 - a) * T0[:3, 3] + a * T1[:3, 3]
    return T


class _Camera:
    def __init__(self, pose_buffer: int, image_queue: int):
        self.info: CameraInfoMsg | None = None
        self.pose_stamps: list[int] = []
        self.poses: list[np.ndarray] = []
        self.pose_buffer = pose_buffer
        self.images: deque[ImageMsg] = deque()
        self.image_queue = image_queue

    def add_pose(self, stamp: int, T: np.ndarray) -> None:
        k = bisect.bisect_left(self.pose_stamps, stamp)
        if k < len(self.pose_stamps) and self.pose_stamps[k] == stamp:
            self.poses[k] = T
            return
        self.pose_stamps.insert(k, stamp)
        self.poses.insert(k, T)
        if len(self.poses) > self.pose_buffer:
            del self.pose_stamps[0], self.poses[0]

    def pose_at(self, stamp: int, max_gap: int, exact: int):
        """(T, 'ok') or (None, 'wait' | 'no_pose')."""
        s = self.pose_stamps
        if not s:
            return None, "wait"
        k = bisect.bisect_left(s, stamp)
        for j in (k - 1, k):
            if 0 <= j < len(s) and abs(s[j] - stamp) <= exact:
                return self.poses[j].copy(), "ok"
        if k == 0:
            return None, "no_pose"  # older than every pose kept
        if k == len(s):
            return None, "wait"  # no later pose yet
        if s[k] - s[k - 1] > max_gap:
            return None, "no_pose"
        return interpolate_pose(s[k - 1], self.poses[k - 1], s[k], self.poses[k], stamp), "ok"


class FrameSynchronizer:
    def __init__(
        self,
        image_queue: int = 4,
        pose_buffer: int = 200,
        max_pose_gap_ns: int = 200_000_000,
        pose_wait_ns: int = 200_000_000,
        exact_tolerance_ns: int = 1_000_000,
    ):
        self._lock = threading.Lock()
        self._cams: dict[str, _Camera] = {}
        self.image_queue = image_queue
        self.pose_buffer = pose_buffer
        self.max_pose_gap_ns = max_pose_gap_ns
        self.pose_wait_ns = pose_wait_ns
        self.exact_tolerance_ns = exact_tolerance_ns
        self.last_stamp_ns: int | None = None
        self.dropped: Counter = Counter()

    def _cam(self, cam_id: str) -> _Camera:
        if cam_id not in self._cams:
            self._cams[cam_id] = _Camera(self.pose_buffer, self.image_queue)
        return self._cams[cam_id]

    def add_info(self, cam_id: str, msg: CameraInfoMsg) -> None:
        with self._lock:
            self._cam(cam_id).info = msg

    def add_pose(self, cam_id: str, msg: CameraPoseMsg) -> None:
        with self._lock:
            self._cam(cam_id).add_pose(msg.stamp_ns, msg.T_world_cam)

    def add_image(self, cam_id: str, msg: ImageMsg) -> None:
        with self._lock:
            if self.last_stamp_ns is not None and msg.stamp_ns <= self.last_stamp_ns:
                self.dropped["late"] += 1
                return
            cam = self._cam(cam_id)
            k = bisect.bisect([m.stamp_ns for m in cam.images], msg.stamp_ns)
            cam.images.insert(k, msg)
            while len(cam.images) > cam.image_queue:
                cam.images.popleft()
                self.dropped["queue_full"] += 1

    def pending(self) -> int:
        with self._lock:
            return sum(len(c.images) for c in self._cams.values())

    def pop(self) -> SyncedFrame | None:
        """The oldest image that can be processed now, with its camera and pose; or None."""
        with self._lock:
            while True:
                candidates = [
                    (c.images[0].stamp_ns, cid) for cid, c in self._cams.items() if c.images
                ]
                if not candidates:
                    return None
                blocked = []
                for _, cid in sorted(candidates):
                    cam = self._cams[cid]
                    msg = cam.images[0]
                    if cam.info is None:
                        if len(cam.images) >= cam.image_queue:
                            cam.images.popleft()
                            self.dropped["no_info"] += 1
                            break
                        blocked.append(cid)
                        continue
                    T, status = cam.pose_at(
                        msg.stamp_ns, self.max_pose_gap_ns, self.exact_tolerance_ns
                    )
                    if status == "no_pose":
                        cam.images.popleft()
                        self.dropped["no_pose"] += 1
                        break
                    if status == "wait":
                        newest = cam.images[-1].stamp_ns
                        if newest - msg.stamp_ns > self.pose_wait_ns:
                            cam.images.popleft()
                            self.dropped["pose_timeout"] += 1
                            break
                        blocked.append(cid)
                        continue
                    if blocked:
                        # an older image of another camera waits for its pose: keep stamp order
                        return None
                    cam.images.popleft()
                    self.last_stamp_ns = msg.stamp_ns
                    return SyncedFrame(cid, msg.stamp_ns, msg.image, cam.info.camera, T)
                else:
                    return None

    def cameras(self) -> list[str]:
        with self._lock:
            return sorted(self._cams)
