"""A camera-side publisher: replays a BOP scene as a cell's camera would, over Zenoh.

Camera info is published first (and again every ``info_every`` frames: it is latched by the
daemon anyway), and served on request: :func:`publish` answers queries on the camera's info
key, so a daemon that (re)starts asks instead of waiting. Each view becomes a JPEG image stamped
``t0 + k / rate``; images and poses carry sequence numbers, so the daemon can count any loss.
Camera poses come at another rate, with jitter: the camera dwells at each view (as a robot does
for a picture), and its pose is published a few milliseconds before and after the image
(random, seeded), plus one pose half-way to the next view, so the daemon has to buffer and
interpolate.
"""

from __future__ import annotations

import time
from collections.abc import Iterator

import numpy as np

from posefuse.service.codec import encode_camera_info, encode_camera_pose, encode_image
from posefuse.service.keys import Keys
from posefuse.service.settings import put_camera_message
from posefuse.service.sync import interpolate_pose


def scene_messages(
    dataset,
    scene_id: int,
    cell: str = "posefuse",
    cam_id: str = "cam0",
    rate_hz: float = 2.0,
    t0_ns: int = 1_000_000_000_000,
    seed: int = 0,
    jpeg_quality: int = 90,
    info_every: int = 4,
    max_views: int = 0,
) -> Iterator[tuple[float, str, bytes]]:
    """(send time offset s, key, payload) in publication order."""
    keys = Keys(cell)
    scene = dataset.scene(scene_id)
    rng = np.random.default_rng([seed, scene_id])
    period = int(1e9 / rate_hz)
    im_ids = scene.im_ids[: max_views or None]
    views = [scene.view(i) for i in im_ids]
    pose_seq = iter(range(1 << 62))
    for k, view in enumerate(views):
        stamp = t0_ns + k * period
        offset = k / rate_hz
        if k % info_every == 0:
            yield (
                offset,
                keys.camera(cam_id, "info"),
                encode_camera_info(stamp, cam_id, view.camera),
            )
        before = int(rng.uniform(5e6, 30e6))
        after = int(rng.uniform(5e6, 30e6))
        yield (
            offset,
            keys.camera(cam_id, "pose"),
            encode_camera_pose(stamp - before, cam_id, view.T_world_cam, seq=next(pose_seq)),
        )
        image = scene.load_rgb(view.im_id)
        yield (
            offset,
            keys.camera(cam_id, "image"),
            encode_image(stamp, cam_id, image, "jpeg", jpeg_quality, seq=k),
        )
        yield (
            offset + after / 1e9,
            keys.camera(cam_id, "pose"),
            encode_camera_pose(stamp + after, cam_id, view.T_world_cam, seq=next(pose_seq)),
        )
        if k + 1 < len(views):
            mid = stamp + period // 2
            T_mid = interpolate_pose(
                stamp, view.T_world_cam, stamp + period, views[k + 1].T_world_cam, mid
            )
            yield (
                offset + 0.5 / rate_hz,
                keys.camera(cam_id, "pose"),
                encode_camera_pose(mid, cam_id, T_mid, seq=next(pose_seq)),
            )


class InfoServer:
    """Answers queries on camera info keys with the latest info published there."""

    def __init__(self, session):
        self.session = session
        self.latest: dict[str, bytes] = {}
        self._queryables = []

    def publish(self, key: str, payload: bytes) -> None:
        if key not in self.latest:
            self._queryables.append(
                self.session.declare_queryable(key, lambda q, k=key: self._reply(q, k))
            )
        self.latest[key] = payload

    def _reply(self, query, key: str) -> None:
        try:
            query.reply(key, self.latest[key])
        except Exception:  # a query that went away
            pass

    def close(self) -> None:
        for q in self._queryables:
            q.undeclare()
        self._queryables = []


def publish(
    session, messages, realtime: bool = True, progress=None, serve_info: bool = True
) -> int:
    """Put the messages on the session, paced by their offsets when ``realtime``; with
    ``serve_info``, the camera info keys are answered on request while publishing."""
    start = time.monotonic()
    n = 0
    server = InfoServer(session) if serve_info else None
    try:
        for offset, key, payload in messages:
            if realtime:
                delay = start + offset - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            if server is not None and key.endswith("/info"):
                server.publish(key, payload)
            put_camera_message(session, key, payload)
            n += 1
            if progress:
                progress(key)
    finally:
        if server is not None:
            server.close()
    return n
