"""Per-camera buffers that turn decoded messages into estimator frames.

Every camera is synchronised on its own; nothing one camera does (or fails to do) holds back
another:

- Camera info is latched: the latest one of a camera is used for all its images.
- Camera poses may come at another rate: an image's pose is interpolated (slerp / lerp) between
  the poses around its stamp, if they are at most ``max_pose_gap_ns`` apart; a pose within
  ``exact_tolerance_ns`` of the stamp is used as is. The pose buffer forgets the poses received
  longest ago (not the oldest stamps), so a camera whose clock steps back keeps working.
- Images wait in a bounded queue per camera, in stamp order; when it is full the oldest is
  dropped (the latest frames win when the estimator falls behind). The decoded images of all
  queues together are bounded by ``max_queued_bytes``.
- An image waits for its camera's info and for a pose after its stamp at most ``wait_ns`` of
  arrival time, then it is dropped (``no_info`` / ``no_pose``). An image of another size than its
  camera's info says is dropped too (``size_unlike_info``): the intrinsics are not its own.
- Lateness is per camera: an image not newer than the last one handed out *of that camera* is
  late and dropped. ``reanchor_frames`` late images in a row, in increasing stamp order, mean
  that camera's clock stepped back (or a publisher restarted, or a stamp far in the future got
  through): the camera re-anchors on them and goes on (``reanchored`` counts it).
- Ready frames of different cameras leave oldest stamp first, except that a camera whose ready
  frame was passed over goes before those that were not (the one passed over most often
  first): when the estimator falls behind, every camera gets its share of the frames processed,
  where oldest-first alone would serve the cameras whose stamps come first in each cycle and
  let the others' queues drop everything. A camera waiting for its pose does not hold back
  another one's ready frame.
- At most ``max_cameras`` are kept; a camera silent for ``camera_timeout_ns`` is forgotten when
  its slot is needed, never while a slot is free (a camera that pauses keeps its info). At
  the limit, a new camera takes the slot of one that never completed a frame (no frame handed
  out: those that sent fewer of an info, a pose and an image first, then the least recently
  seen), and only then of a silent one: junk camera ids, even with a valid
  info and pose, never lock a real camera out (``cameras_evicted``), and a working camera that
  pauses keeps its slot while junk holds one.
- With ``max_future_ns``, images and poses stamped further ahead of ``now_ns`` are refused
  (``future_stamp``, ``future_pose``): no estimate carries a stamp from the future, and a
  camera's clock cannot be dragged ahead of the daemon's.
- Sequence numbers (optional ``seq`` of images and poses) expose loss upstream of the daemon:
  per camera and kind, ``lost`` counts the numbers skipped, ``restarts`` a sequence that began
  again.

Times: message stamps are the cameras' clocks; ``now_ns`` (arrival time, passed in by the
caller: wall clock live, log time in replay) is the daemon's. Nothing here reads a clock.
Thread-safe: decoders call the ``add_*`` methods, the worker ``pop``.
"""

from __future__ import annotations

import bisect
import threading
from collections import Counter
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from posefuse.estimator.core.camera import Camera
from posefuse.service.codec import CameraInfoMsg, CameraPoseMsg, ImageMsg


@dataclass(frozen=True, eq=False)
class SyncedFrame:
    camera_id: str
    stamp_ns: int
    image: np.ndarray  # (H, W, 3) uint8 RGB
    camera: Camera
    T_world_cam: np.ndarray  # (4, 4)
    arrival_ns: int = 0  # when the image arrived (the caller's clock)


@dataclass(frozen=True)
class SyncConfig:
    image_queue: int = 2  # images buffered per camera (more only adds latency when behind)
    pose_buffer: int = 200  # poses kept per camera for interpolation
    max_pose_gap_ns: int = 200_000_000  # poses further apart are not interpolated
    exact_tolerance_ns: int = 1_000_000  # a pose this close to the stamp is used as is
    wait_ns: int = 500_000_000  # arrival time an image may wait for its info and pose
    reanchor_frames: int = 3  # late images in a row (increasing stamps) that re-anchor a camera
    camera_timeout_ns: int = 60_000_000_000  # silent this long, forgotten when a slot is needed
    max_cameras: int = 16
    max_queued_bytes: int = 512 * 1024 * 1024  # decoded images waiting, all cameras together
    max_future_ns: int | None = None  # stamps further ahead of now_ns are refused (None: any)

    def __post_init__(self) -> None:
        for name in ("image_queue", "pose_buffer", "reanchor_frames", "max_cameras"):
            if getattr(self, name) < 1:
                raise ValueError(f"SyncConfig.{name} must be >= 1, got {getattr(self, name)}")
        for name in ("max_pose_gap_ns", "wait_ns", "camera_timeout_ns", "max_queued_bytes"):
            if getattr(self, name) <= 0:
                raise ValueError(f"SyncConfig.{name} must be > 0, got {getattr(self, name)}")
        if self.max_future_ns is not None and self.max_future_ns <= 0:
            raise ValueError(f"SyncConfig.max_future_ns must be > 0, got {self.max_future_ns}")


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


@dataclass
class _Waiting:
    msg: ImageMsg
    arrival_ns: int  # received (the latency's start)
    queued_ns: int  # reached the synchroniser (the wait for its info and pose starts here)


@dataclass
class CameraCounters:
    """What one camera sent and what became of it."""

    images: int = 0
    poses: int = 0
    infos: int = 0
    synced: int = 0  # handed to the estimator
    lost: Counter = field(default_factory=Counter)  # per kind: sequence numbers skipped
    restarts: Counter = field(default_factory=Counter)  # per kind: sequences begun again

    def as_dict(self) -> dict:
        return {
            "images": self.images,
            "poses": self.poses,
            "infos": self.infos,
            "synced": self.synced,
            "lost": dict(self.lost),
            "restarts": dict(self.restarts),
        }


class _Camera:
    def __init__(self, config: SyncConfig, now_ns: int):
        self.config = config
        self.info: CameraInfoMsg | None = None
        self.pose_stamps: list[int] = []
        self.poses: list[np.ndarray] = []
        self.pose_order: list[int] = []  # receive serial of each pose, to forget the oldest
        self.serial = 0
        self.images: list[_Waiting] = []  # stamp order
        self.last_out: int | None = None  # stamp of the last frame handed out
        self.late_run: list[int] = []  # stamps of the late images in a row
        self.late_run_serial = 0  # pose serial when that run began
        self.last_seen = now_ns
        self.last_seq: dict[str, int] = {}
        self.counters = CameraCounters()
        self.passed_over = 0  # pops that served another camera while this one had a frame ready

    def queued_bytes(self) -> int:
        return sum(w.msg.image.nbytes for w in self.images)

    def note_seq(self, kind: str, seq: int | None) -> None:
        if seq is None:
            return
        last = self.last_seq.get(kind)
        if last is not None:
            if seq > last + 1:
                self.counters.lost[kind] += seq - last - 1
            elif seq <= last:
                self.counters.restarts[kind] += 1
        self.last_seq[kind] = seq

    def add_pose(self, stamp: int, T: np.ndarray) -> None:
        self.serial += 1
        k = bisect.bisect_left(self.pose_stamps, stamp)
        if k < len(self.pose_stamps) and self.pose_stamps[k] == stamp:
            self.poses[k] = T
            self.pose_order[k] = self.serial
            return
        self.pose_stamps.insert(k, stamp)
        self.poses.insert(k, T)
        self.pose_order.insert(k, self.serial)
        if len(self.poses) > self.config.pose_buffer:
            j = int(np.argmin(self.pose_order))
            del self.pose_stamps[j], self.poses[j], self.pose_order[j]

    def forget_poses_before(self, serial: int) -> None:
        """Forget the poses received before the pose serial ``serial`` (the old clock's)."""
        keep = [j for j, o in enumerate(self.pose_order) if o > serial]
        self.pose_stamps = [self.pose_stamps[j] for j in keep]
        self.poses = [self.poses[j] for j in keep]
        self.pose_order = [self.pose_order[j] for j in keep]

    def pose_at(self, stamp: int):
        """(T, 'ok') or (None, 'wait' | 'no_pose')."""
        s = self.pose_stamps
        max_gap, exact = self.config.max_pose_gap_ns, self.config.exact_tolerance_ns
        if not s:
            return None, "wait"
        k = bisect.bisect_left(s, stamp)
        for j in (k - 1, k):
            if 0 <= j < len(s) and abs(s[j] - stamp) <= exact:
                return self.poses[j].copy(), "ok"
        if k == 0:
            return None, "no_pose"  # older than every pose kept
        if stamp - s[k - 1] > max_gap:
            return None, "no_pose"  # the pose before is too far; the next can only be further
        if k == len(s) or s[k] - s[k - 1] > max_gap:
            return None, "wait"  # a pose after the stamp, close enough, may still come
        return interpolate_pose(s[k - 1], self.poses[k - 1], s[k], self.poses[k], stamp), "ok"


class FrameSynchronizer:
    def __init__(self, config: SyncConfig | None = None):
        self.config = config or SyncConfig()
        self._lock = threading.Lock()
        self._cams: dict[str, _Camera] = {}
        self.dropped: Counter = Counter()  # images dropped, by reason
        self.events: Counter = Counter()  # reanchored, cameras_forgotten

    # ------------------------------------------------------------------ inputs
    def _cam(self, cam_id: str, now_ns: int) -> _Camera | None:
        cam = self._cams.get(cam_id)
        if cam is None:
            if len(self._cams) >= self.config.max_cameras:
                self._evict_unproven()
            if len(self._cams) >= self.config.max_cameras:
                self._forget_silent(now_ns)
            if len(self._cams) >= self.config.max_cameras:
                return None
            cam = self._cams[cam_id] = _Camera(self.config, now_ns)
        cam.last_seen = max(cam.last_seen, now_ns)
        return cam

    def _evict_unproven(self) -> None:
        """Free the slot of a camera that never completed a frame (none handed out): those
        that sent fewer of an info, a pose and an image first, then the least recently seen.
        A camera that sends an info and a pose but never an image holds no slot that a camera
        with images needs."""
        unproven = [
            (
                int(cam.info is not None) + int(bool(cam.poses)) + int(cam.counters.images > 0),
                cam.last_seen,
                cid,
            )
            for cid, cam in self._cams.items()
            if cam.counters.synced == 0
        ]
        if not unproven:
            return
        *_, cid = min(unproven)
        cam = self._cams.pop(cid)
        if cam.images:
            self.dropped["camera_evicted"] += len(cam.images)
        self.events["cameras_evicted"] += 1

    def _future(self, stamp: int, now_ns: int) -> bool:
        limit = self.config.max_future_ns
        return limit is not None and stamp - now_ns > limit

    def add_info(self, cam_id: str, msg: CameraInfoMsg, now_ns: int = 0) -> bool:
        """False when the camera is not taken (too many cameras)."""
        with self._lock:
            cam = self._cam(cam_id, now_ns)
            if cam is None:
                self.events["too_many_cameras"] += 1
                return False
            cam.counters.infos += 1
            cam.info = msg
            return True

    def add_pose(self, cam_id: str, msg: CameraPoseMsg, now_ns: int = 0) -> bool:
        """False when the pose is not taken (too many cameras, stamped in the future)."""
        with self._lock:
            if self._future(msg.stamp_ns, now_ns):
                self.events["future_pose"] += 1
                return False
            cam = self._cam(cam_id, now_ns)
            if cam is None:
                self.events["too_many_cameras"] += 1
                return False
            cam.counters.poses += 1
            cam.note_seq("pose", msg.seq)
            cam.add_pose(msg.stamp_ns, msg.T_world_cam)
            return True

    def add_image(
        self, cam_id: str, msg: ImageMsg, now_ns: int = 0, arrival_ns: int | None = None
    ) -> bool:
        """Queue an image; False when it was dropped at once (counted by reason).

        now_ns: the caller's clock now; the wait for the image's info and pose counts from it,
        so that the time an image spent waiting for a decoder (a flood of other cameras' images
        ahead of it) never makes it miss a pose that is on its way. arrival_ns: when it was
        received (its latency counts from it); None: ``now_ns``."""
        with self._lock:
            if self._future(msg.stamp_ns, now_ns):
                self.dropped["future_stamp"] += 1
                return False
            cam = self._cam(cam_id, now_ns)
            if cam is None:
                self.dropped["too_many_cameras"] += 1
                return False
            cam.counters.images += 1
            cam.note_seq("image", msg.seq)
            stamp = msg.stamp_ns
            if cam.last_out is not None and stamp <= cam.last_out:
                if cam.late_run and stamp <= cam.late_run[-1]:
                    cam.late_run = []
                if not cam.late_run:
                    cam.late_run_serial = cam.serial
                cam.late_run.append(stamp)
                if len(cam.late_run) < self.config.reanchor_frames:
                    self.dropped["late"] += 1
                    return False
                # the camera's clock stepped back: start again from this run
                self.events["reanchored"] += 1
                cam.last_out = None
                cam.late_run = []
                cam.forget_poses_before(cam.late_run_serial)
                self.dropped["reanchored"] += len(cam.images)
                cam.images = []
            else:
                cam.late_run = []
            need = msg.image.nbytes
            total = sum(c.queued_bytes() for c in self._cams.values())
            if need > self.config.max_queued_bytes:
                self.dropped["memory"] += 1
                return False
            while total + need > self.config.max_queued_bytes:
                victim = max(self._cams.values(), key=lambda c: c.queued_bytes())
                total -= victim.images.pop(0).msg.image.nbytes
                self.dropped["memory"] += 1
            k = bisect.bisect([w.msg.stamp_ns for w in cam.images], stamp)
            cam.images.insert(
                k, _Waiting(msg, now_ns if arrival_ns is None else arrival_ns, now_ns)
            )
            while len(cam.images) > self.config.image_queue:
                cam.images.pop(0)
                self.dropped["queue_full"] += 1
            return True

    # ------------------------------------------------------------------ output
    def pop(self, now_ns: int = 0) -> SyncedFrame | None:
        """The oldest frame that can be processed now, with its camera and pose; or None.

        Images that waited longer than ``wait_ns`` for their info or pose are dropped here. A
        silent camera is not forgotten here: only when its slot is needed (``_cam``).
        """
        with self._lock:
            ready: list[tuple[int, str, np.ndarray]] = []
            for cid, cam in self._cams.items():
                while cam.images:
                    head = cam.images[0]
                    waited = now_ns - head.queued_ns
                    if cam.info is None:
                        if waited > self.config.wait_ns:
                            cam.images.pop(0)
                            self.dropped["no_info"] += 1
                            continue
                        break
                    if head.msg.image.shape[:2] != (cam.info.camera.height, cam.info.camera.width):
                        # the info's intrinsics are for another image size: never used on this
                        cam.images.pop(0)
                        self.dropped["size_unlike_info"] += 1
                        continue
                    T, status = cam.pose_at(head.msg.stamp_ns)
                    if status == "no_pose" or (status == "wait" and waited > self.config.wait_ns):
                        cam.images.pop(0)
                        self.dropped["no_pose"] += 1
                        continue
                    if status == "ok":
                        ready.append((head.msg.stamp_ns, cid, T))
                    break
            if not ready:
                return None
            stamp, cid, T = min(ready, key=lambda r: (-self._cams[r[1]].passed_over, r[0], r[1]))
            for _, other, _ in ready:
                self._cams[other].passed_over += 1
            cam = self._cams[cid]
            cam.passed_over = 0
            head = cam.images.pop(0)
            cam.last_out = stamp
            cam.counters.synced += 1
            return SyncedFrame(cid, stamp, head.msg.image, cam.info.camera, T, head.arrival_ns)

    def _forget_silent(self, now_ns: int) -> None:
        for cid in [
            c
            for c, cam in self._cams.items()
            if now_ns - cam.last_seen > self.config.camera_timeout_ns
        ]:
            cam = self._cams.pop(cid)
            if cam.images:
                self.dropped["camera_forgotten"] += len(cam.images)
            self.events["cameras_forgotten"] += 1

    # ------------------------------------------------------------------ introspection
    def pending(self) -> int:
        with self._lock:
            return sum(len(c.images) for c in self._cams.values())

    def queued_bytes(self) -> int:
        with self._lock:
            return sum(c.queued_bytes() for c in self._cams.values())

    def has_info(self, cam_id: str) -> bool:
        with self._lock:
            cam = self._cams.get(cam_id)
            return cam is not None and cam.info is not None

    def camera(self, cam_id: str | None = None):
        """The intrinsics (Camera) of a camera, or of the first one with an info when
        ``cam_id`` is None; None when not known."""
        with self._lock:
            for cid in sorted(self._cams) if cam_id is None else [cam_id]:
                cam = self._cams.get(cid)
                if cam is not None and cam.info is not None:
                    return cam.info.camera
        return None

    def cameras(self) -> list[str]:
        with self._lock:
            return sorted(self._cams)

    def camera_counters(self) -> dict[str, dict]:
        with self._lock:
            return {cid: self._cams[cid].counters.as_dict() for cid in sorted(self._cams)}
