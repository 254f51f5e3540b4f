"""Soak benchmark of the daemon: overload, several cameras and decompression bombs for minutes.

python -m posefuse.bench.service_soak [--minutes 10] [--cameras 4] [--overload 2 | --rate 20]
    [--bomb-every 30]

Starts ``posefuse serve`` as its own process on loopback. The frames are those of the shipped
demo recording (1280x720 JPEG of rendered bins, with their camera info and poses), re-stamped
per camera. First the sustainable rate is measured: frames sent one at a time, each after the
previous one was handled, for ``--calibrate`` frames; its inverse mean processing time is the
rate the daemon keeps up with. Then ``--cameras`` cameras publish together at ``--overload``
times that rate in total, and every ``--bomb-every`` seconds one camera sends a hostile image,
the four kinds in turn: a PNG and a JPEG decompression bomb (20000x20000 declared 1280x720), a
progressive JPEG whose one AC scan is repeated 20,000 times (4096x4096, every header true) and
a PNG of 200,000 tiny chunks; at the same time a junk camera id that was never seen before
sends one 8x8 frame and nothing else. Printed at the end: the daemon's RSS min / max (sampled
every second), frames sent, processed, dropped by reason, whether every message sent is
accounted for (processed or dropped with a reason), the p50 / p95 latency (arrival to
estimate) of the frames processed, and the deferred verification's backlog (parts waiting,
sampled every second), checks done and image -> verified pose latency.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time
from collections import Counter

import msgpack
import numpy as np

from posefuse.bench.service_latency import _free_port, _get, _rss_mb


class Views:
    """The demo recording's views: camera info, and (image data, T_world_cam) per view."""

    def __init__(self, recording):
        from posefuse.service.codec import decode_camera_info, decode_camera_pose
        from posefuse.service.recording import read_messages

        self.info = None
        self.images: list[bytes] = []
        poses: dict[int, np.ndarray] = {}
        stamps: list[int] = []
        for m in read_messages(recording):
            if m.key.endswith("/info") and self.info is None:
                self.info = decode_camera_info(m.payload).camera
            elif m.key.endswith("/pose"):
                p = decode_camera_pose(m.payload)
                poses[p.stamp_ns] = p.T_world_cam
            elif m.key.endswith("/image"):
                msg = msgpack.unpackb(m.payload)
                self.images.append(msg["data"])
                stamps.append(msg["stamp_ns"])
        pose_stamps = np.array(sorted(poses))
        self.poses = [poses[int(pose_stamps[np.abs(pose_stamps - s).argmin()])] for s in stamps]
        self.width, self.height = self.info.width, self.info.height


class Camera:
    """One publishing camera: info first, then pose + image per frame, with sequence numbers."""

    def __init__(self, session, cell: str, cam_id: str, views: Views, offset: int):
        from posefuse.service.codec import encode_camera_info

        self.session, self.views, self.k = session, views, offset
        self.root = f"{cell}/@v1/cam/{cam_id}"
        self.cam_id = cam_id
        self.stamp = 1_000_000_000_000
        self.sent = 0
        session.put(f"{self.root}/info", encode_camera_info(0, cam_id, views.info))

    def frame(self, period_ns: int) -> None:
        from posefuse.service.codec import _pack, encode_camera_pose

        v = self.views
        i = self.k % len(v.images)
        self.k += 1
        self.stamp += period_ns
        self.session.put(
            f"{self.root}/pose", encode_camera_pose(self.stamp, self.cam_id, v.poses[i])
        )
        image = {
            "stamp_ns": self.stamp,
            "frame_id": self.cam_id,
            "encoding": "jpeg",
            "width": v.width,
            "height": v.height,
            "data": v.images[i],
            "seq": self.sent,
        }
        self.session.put(f"{self.root}/image", _pack(image))
        self.sent += 1

    def bomb(self, stream: bytes, encoding: str, declared: tuple[int, int] | None) -> None:
        from posefuse.bench.bombs import image_message

        self.stamp += 1
        size = declared or (self.views.width, self.views.height)
        payload = image_message(stream, encoding, self.stamp, size, self.cam_id)
        self.session.put(f"{self.root}/image", payload)


def junk_camera(session, cell: str, cam_id: str) -> None:
    """One valid 8x8 frame from a camera id never seen before, and nothing else from it."""
    import cv2

    from posefuse.bench.bombs import image_message

    ok, png = cv2.imencode(".png", np.zeros((8, 8, 3), np.uint8))
    session.put(f"{cell}/@v1/cam/{cam_id}/image", image_message(png.tobytes(), "png", 1, (8, 8)))


def main(argv: list[str] | None = None) -> int:
    import zenoh

    from posefuse.bench.bombs import jpeg_bomb, png_bomb, png_many_chunks, progressive_scan_bomb
    from posefuse.service.resources import DEFAULT_RECORDING

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument("--cameras", type=int, default=4)
    parser.add_argument("--overload", type=float, default=2.0, help="times the sustainable rate")
    parser.add_argument(
        "--rate", type=float, help="offered frames/s over all cameras (default: --overload x)"
    )
    parser.add_argument("--bomb-every", type=float, default=30.0, help="seconds")
    parser.add_argument("--calibrate", type=int, default=12, help="frames to measure the rate")
    parser.add_argument("--recording", default=str(DEFAULT_RECORDING))
    parser.add_argument("--json", help="also write the figures to this JSON file")
    args = parser.parse_args(argv)

    views = Views(args.recording)
    zport, hport = _free_port(), _free_port()
    base = f"http://127.0.0.1:{hport}"
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "POSEFUSE_CELL": "soak"}
    daemon = subprocess.Popen(
        [sys.executable, "-m", "posefuse.cli", "serve", "--listen", f"tcp/127.0.0.1:{zport}",
         "--http-port", str(hport)],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env,
    )  # fmt: skip
    try:
        deadline = time.time() + 300
        while True:
            try:
                if _get(f"{base}/readyz")["status"] == "ready":
                    break
            except OSError:
                pass
            if daemon.poll() is not None or time.time() > deadline:
                raise SystemExit("the daemon did not start")
            time.sleep(0.5)
        conf = zenoh.Config()
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("listen/endpoints", "[]")
        conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{zport}"]))
        with zenoh.open(conf) as session:
            time.sleep(1.0)
            # 1. the sustainable rate: one frame at a time
            cal = Camera(session, "soak", "calibration", views, 0)
            t0 = time.monotonic()
            for k in range(args.calibrate):
                cal.frame(500_000_000)
                while _get(f"{base}/stats")["frames_handled"] < k + 1:
                    time.sleep(0.01)
            per_frame = (time.monotonic() - t0) / args.calibrate
            sustainable = 1.0 / per_frame
            rate = args.rate or args.overload * sustainable
            print(
                f"sustainable rate {sustainable:.2f} frames/s ({per_frame * 1000:.0f} ms a "
                f"frame, {args.calibrate} frames); soak at {rate:.2f} frames/s over "
                f"{args.cameras} cameras for {args.minutes:g} min, a bomb every "
                f"{args.bomb_every:g} s",
                flush=True,
            )
            before = _get(f"{base}/stats")
            # 2. the soak
            cams = [Camera(session, "soak", f"cam{c}", views, 7 * c) for c in range(args.cameras)]
            bombs = [
                (png_bomb(), "png", None),
                (jpeg_bomb(), "jpeg", None),
                (progressive_scan_bomb(), "jpeg", (4096, 4096)),
                (png_many_chunks(), "png", (64, 64)),
            ]
            rss: list[float] = []
            waiting: list[int] = []  # parts waiting for the deferred verification
            stop = threading.Event()

            def sample():
                while not stop.wait(1.0):
                    rss.append(_rss_mb(daemon.pid))
                    waiting.append(_get(f"{base}/stats")["verification"]["waiting"])

            sampler = threading.Thread(target=sample, daemon=True)
            sampler.start()
            period = 1.0 / rate
            cam_period_ns = int(1e9 * args.cameras / rate)
            start = time.monotonic()
            end = start + 60 * args.minutes
            next_bomb, n_bombs, k = start + args.bomb_every, 0, 0
            last_report = start
            while (now := time.monotonic()) < end:
                cams[k % len(cams)].frame(cam_period_ns)
                k += 1
                if now >= next_bomb:
                    stream, encoding, declared = bombs[n_bombs % len(bombs)]
                    cams[n_bombs % len(cams)].bomb(stream, encoding, declared)
                    junk_camera(session, "soak", f"junk{n_bombs}")
                    n_bombs += 1
                    next_bomb += args.bomb_every
                if now - last_report >= 60:
                    s = _get(f"{base}/stats")
                    print(
                        f"  {int(now - start):4d} s: sent {k}, processed "
                        f"{s['frames_processed'] - before['frames_processed']}, RSS "
                        f"{rss[-1] if rss else float('nan'):.0f} MB, parts waiting for their "
                        f"check {s['verification']['waiting']}",
                        flush=True,
                    )
                    last_report = now
                delay = start + k * period - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            # let the queues drain: until nothing is pending and every image that arrived has
            # been dealt with (at most a minute)
            drain_end = time.monotonic() + 60
            while time.monotonic() < drain_end:
                s = _get(f"{base}/stats")
                if (
                    not s["frames_pending"]
                    and s["frames_handled"] >= s["frames_received"]
                    and not s["verification"]["waiting"]
                ):
                    break
                time.sleep(0.2)
            stop.set()
            sampler.join()
            after = _get(f"{base}/stats")
    finally:
        daemon.terminate()
        try:
            daemon.wait(timeout=20)
        except subprocess.TimeoutExpired:
            daemon.kill()

    dropped = Counter(after["frames_dropped"])
    dropped.subtract(before["frames_dropped"])
    received = after["frames_received"] - before["frames_received"]
    processed = after["frames_processed"] - before["frames_processed"]
    handled = after["frames_handled"] - before["frames_handled"]
    offered = k + 2 * n_bombs  # frames, hostile images and the junk cameras' frames
    figures = {
        "minutes": args.minutes,
        "cameras": args.cameras,
        "sustainable_fps": round(sustainable, 3),
        "offered_fps": round(rate, 3),
        "frames_sent": k,
        "bombs_sent": n_bombs,
        "junk_cameras": n_bombs,
        "images_offered": offered,
        "images_received": received,
        "frames_processed": processed,
        "processing_errors": after["processing_errors"] - before["processing_errors"],
        "dropped": {r: n for r, n in sorted(dropped.items()) if n},
        "images_handled": handled,
        "unaccounted": offered - handled,
        "latency_p50_ms": after["latency"]["p50_ms"],
        "latency_p95_ms": after["latency"]["p95_ms"],
        "rss_min_mb": round(min(rss), 1),
        "rss_max_mb": round(max(rss), 1),
        "rss_last_mb": round(rss[-1], 1),
        # the deferred verification: parts waiting (sampled every second), checks done, and
        # image -> verified pose
        "verification_waiting_max": max(waiting),
        "verification_waiting_last": waiting[-1],
        "verification_waiting_after_drain": after["verification"]["waiting"],
        "verification_checked": after["verification"]["checked"]
        - before["verification"]["checked"],
        "verified_latency_p50_ms": after["verification"]["latency"]["p50_ms"],
        "verified_latency_p95_ms": after["verification"]["latency"]["p95_ms"],
    }
    print(json.dumps(figures, indent=1))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(figures, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
