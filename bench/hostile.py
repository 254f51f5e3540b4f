"""What hostile and overloaded senders do to ``posefuse serve``, measured on loopback.

python -m posefuse.bench.hostile --scene DIR:SCENE [--busy 2] [--runs 3] [--rows ROW,...]

Each row starts fresh ``posefuse serve`` processes on loopback ports and plays one case against
them from this process; the good cameras put their messages as docs/protocol.md asks of a
camera driver, the hostile ones as fast as Zenoh takes them. Rows (all by default):

- ``overload``: 4 cameras at 2 Hz for 20 s, publishing in the same order each cycle (so the
  same camera always has the oldest stamp), the views of ``--scene`` (a pile: more than the
  estimator keeps up with), with ``--busy`` processes spinning beside the daemon: frames
  processed per camera, and the largest share's distance from the mean;
- ``flood``: on ``--runs`` fresh daemons, 30 valid 4096x4096 PNGs from 15 camera ids that
  never send an info, while cam0 sends 10 good frames 0.5 s apart: cam0's frames lost;
- ``junk``: a working camera sends frames then pauses; 15 camera ids send one valid info and
  pose each and never an image (16 slots in all); a new camera then sends a frame a second:
  seconds until its first frame is processed, its frames refused ``too_many_cameras``, and
  whether the paused camera kept its slot;
- ``events``: 3 open ``/events`` streams, then SIGTERM: seconds to exit, traceback lines;
- ``infos``: camera infos with fx 1e-300 and 1e300, skew 1e300, a distortion of 1e12, and a
  640x480 info beside 1280x720 images, each followed by frames: what was refused and why, the
  frames of those cameras processed, numpy warnings in the daemon's log.

Prints one line per row and measurement; ``--json`` writes them too.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time

import cv2
import msgpack
import numpy as np

from posefuse.bench.bombs import image_message
from posefuse.bench.service_latency import _free_port, _get, peer_config
from posefuse.estimator.core.camera import Camera
from posefuse.service.codec import VERSION, encode_camera_info, encode_camera_pose, encode_image
from posefuse.service.settings import put_camera_message

CELL = "hostile"
SECOND = 1_000_000_000


class Served:
    """``posefuse serve`` in its own process, its output in a file; ready when built."""

    def __init__(self, *args: str, cell: str = CELL):
        self.zport, hport = _free_port(), _free_port()
        self.base = f"http://127.0.0.1:{hport}"
        self.log = tempfile.NamedTemporaryFile("w+", suffix=".log", delete=False)
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "posefuse.cli", "serve", "--cell", cell]
            + ["--listen", f"tcp/127.0.0.1:{self.zport}", "--http-port", str(hport), *args],
            stdout=self.log,
            stderr=subprocess.STDOUT,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline and self.proc.poll() is None:
            try:
                if _get(f"{self.base}/readyz")["status"] == "ready":
                    return
            except OSError:
                pass
            time.sleep(0.3)
        self.stop()
        raise RuntimeError(f"posefuse serve did not start; its log: {self.log.name}")

    def stats(self) -> dict:
        return _get(f"{self.base}/stats")

    def camera(self, cam_id: str) -> dict:
        return self.stats()["cameras"].get(cam_id, {})

    def stop(self) -> float:
        """SIGTERM; the seconds until the process exited."""
        t0 = time.monotonic()
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        return time.monotonic() - t0

    def output(self) -> str:
        with open(self.log.name) as f:
            return f.read()

    def close(self) -> None:
        self.stop()
        os.unlink(self.log.name)


def _wait(predicate, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.1)
    return False


def _camera(width: int = 1280, height: int = 720) -> Camera:
    K = np.array([[900.0 * width / 1280, 0, width / 2], [0, 900.0 * height / 720, height / 2]])
    return Camera(np.vstack([K, [0, 0, 1]]), width, height)


class GoodCamera:
    """A camera driver that puts as docs/protocol.md asks: its info, then a pose and an image
    per frame (a smooth noise image, or the frames it is given)."""

    def __init__(self, session, cam_id: str, frames=None, seed: int = 0):
        self.session, self.cam_id, self.seq = session, cam_id, 0
        if frames is None:
            small = np.random.default_rng(seed).integers(0, 255, (9, 16, 3), np.uint8)
            image = cv2.resize(small, (1280, 720), interpolation=cv2.INTER_CUBIC)
            frames = [(_camera(), _T_world_cam(), encode_image(0, cam_id, image, "jpeg", 80))]
        self.frames = frames  # [(Camera, T_world_cam (4, 4), encoded image)]

    def put(self, kind: str, payload: bytes) -> None:
        put_camera_message(self.session, f"{CELL}/@v1/cam/{self.cam_id}/{kind}", payload)

    def info(self) -> None:
        self.put("info", encode_camera_info(0, self.cam_id, self.frames[0][0]))

    def frame(self, stamp: int, k: int = 0) -> None:
        camera, T_world_cam, encoded = self.frames[k % len(self.frames)]
        self.seq += 1
        self.put("pose", encode_camera_pose(stamp, self.cam_id, T_world_cam))
        msg = msgpack.unpackb(encoded)
        msg.update(stamp_ns=stamp, camera_id=self.cam_id, seq=self.seq)
        self.put("image", msgpack.packb(msg, use_bin_type=True))


def _T_world_cam() -> np.ndarray:
    T = np.eye(4)
    T[2, 3] = -0.5
    return T


def _scene_frames(spec: str) -> list:
    from posefuse.evaluation.dataset import load_dataset

    path, _, scene_id = spec.rpartition(":")
    scene = load_dataset(path).scene(int(scene_id))
    out = []
    for im_id in scene.im_ids:
        view = scene.view(im_id)
        encoded = encode_image(0, "cam", scene.load_rgb(im_id), "jpeg", 90)
        out.append((view.camera, view.T_world_cam, encoded))
    return out


def spin(stop) -> None:
    """A busy process: spins until ``stop`` (a multiprocessing Event) is set."""
    while not stop.is_set():
        sum(range(10_000))


# ---------------------------------------------------------------------------------- rows
def row_overload(args, report) -> None:
    frames = _scene_frames(args.scene)
    stop = multiprocessing.Event()
    busy = [multiprocessing.Process(target=spin, args=(stop,)) for _ in range(args.busy)]
    daemon = Served()
    try:
        import zenoh

        with zenoh.open(peer_config(daemon.zport)) as session:
            time.sleep(1.0)
            cams = [GoodCamera(session, f"cam{c}", frames[c::4] or frames) for c in range(4)]
            for cam in cams:
                cam.info()
            for p in busy:
                p.start()
            start, stamp = time.monotonic(), 100 * SECOND
            for k in range(40):  # 20 s at 2 Hz, every camera in the same order each cycle
                time.sleep(max(0.0, start + k / 2.0 - time.monotonic()))
                for c, cam in enumerate(cams):
                    cam.frame(stamp + k * SECOND // 2 + c * 1_000_000, k)
            _wait(lambda: daemon.stats()["frames_pending"] == 0, 30)
            time.sleep(2.0)
            cameras = daemon.stats()["cameras"]
    finally:
        stop.set()
        for p in busy:
            p.join()
        daemon.close()
    processed = [cameras.get(f"cam{c}", {}).get("processed", 0) for c in range(4)]
    mean = float(np.mean(processed))
    spread = max(abs(p - mean) for p in processed) / mean if mean else float("nan")
    report(
        "overload",
        f"4 cameras at 2 Hz, same order each cycle, {args.busy} busy processes beside: "
        f"processed {' / '.join(map(str, processed))} of 40; largest distance from the mean "
        f"{100 * spread:.0f}%",
        processed=processed,
        spread=spread,
    )


def row_flood(args, report) -> None:
    flat = np.full((4096, 4096, 3), 77, np.uint8)
    png = cv2.imencode(".png", flat, [cv2.IMWRITE_PNG_COMPRESSION, 9])[1].tobytes()
    lost = []
    for _ in range(args.runs):
        daemon = Served()
        try:
            import zenoh

            with zenoh.open(peer_config(daemon.zport)) as session:
                time.sleep(1.0)
                cam0 = GoodCamera(session, "cam0")
                cam0.info()
                stamp = 100 * SECOND
                for k in range(30):
                    cam = f"flood{k % 15}"
                    message = image_message(png, "png", stamp, (4096, 4096), cam)
                    session.put(f"{CELL}/@v1/cam/{cam}/image", message)
                for k in range(10):
                    cam0.frame(stamp + k * SECOND // 2)
                    time.sleep(0.5)
                _wait(lambda d=daemon: d.camera("cam0").get("processed", 0) >= 10, 60)
                _wait(lambda d=daemon: d.stats()["ingest_pending"] == 0, 120)
                lost.append(10 - daemon.camera("cam0").get("processed", 0))
        finally:
            daemon.close()
    report(
        "flood",
        f"30 PNGs of 4096x4096 from 15 ids without info: cam0 lost {', '.join(map(str, lost))} "
        f"of its 10 good frames on {args.runs} fresh daemons",
        lost=lost,
    )


def row_junk(args, report) -> None:
    daemon = Served()
    try:
        import zenoh

        with zenoh.open(peer_config(daemon.zport)) as session:
            time.sleep(1.0)
            stamp = 100 * SECOND
            work = GoodCamera(session, "work", seed=1)
            work.info()
            for k in range(3):
                work.frame(stamp + k * SECOND // 2)
                time.sleep(0.5)
            _wait(lambda: daemon.camera("work").get("processed", 0) >= 3, 30)
            for k in range(15):  # one valid info and pose each, never an image
                junk = GoodCamera(session, f"junk{k}")
                junk.info()
                junk.put("pose", encode_camera_pose(stamp, junk.cam_id, _T_world_cam()))
            _wait(lambda: len(daemon.stats()["cameras"]) >= 16, 30)
            before = daemon.stats()["frames_dropped"].get("too_many_cameras", 0)
            late = GoodCamera(session, "late", seed=2)
            late.info()
            t0, k = time.monotonic(), 0
            while not daemon.camera("late").get("processed", 0) and time.monotonic() - t0 < 90:
                late.frame(stamp + 10 * SECOND + k * SECOND)
                k += 1
                time.sleep(1.0)
            waited = time.monotonic() - t0 if daemon.camera("late").get("processed") else None
            stats = daemon.stats()
    finally:
        daemon.close()
    refused = stats["frames_dropped"].get("too_many_cameras", 0) - before
    kept = "work" in stats["cameras"]
    report(
        "junk",
        f"15 ids with an info and a pose, never an image: a new camera's first frame processed "
        f"after {waited:.1f} s ({refused} frames too_many_cameras); the paused working camera "
        f"{'kept' if kept else 'lost'} its slot",
        seconds=waited,
        refused=refused,
        paused_kept=kept,
    )


def row_events(args, report) -> None:
    daemon = Served()
    streams = []
    try:
        host, port = daemon.base.removeprefix("http://").split(":")
        for _ in range(3):
            s = socket.create_connection((host, int(port)), timeout=5)
            s.sendall(b"GET /events HTTP/1.1\r\nHost: x\r\nAccept: text/event-stream\r\n\r\n")
            s.recv(256)  # the headers and the stream's first comment: it is open
            streams.append(s)
        seconds = daemon.stop()
        out = daemon.output()
    finally:
        for s in streams:
            s.close()
        daemon.close()
    tracebacks = out.count("Traceback")
    cancelled = out.count("CancelledError")
    report(
        "events",
        f"a stop with 3 open /events streams: exited in {seconds:.1f} s, code "
        f"{daemon.proc.returncode}, {tracebacks} tracebacks, {cancelled} CancelledError lines",
        seconds=seconds,
        tracebacks=tracebacks,
        returncode=daemon.proc.returncode,
    )


def _info_payload(cam_id: str, width: int, height: int, K, D) -> bytes:
    info = {"v": VERSION, "stamp_ns": 0, "frame_id": cam_id, "width": width, "height": height}
    info.update(K=[float(x) for x in np.ravel(K)], D=[float(x) for x in D])
    return msgpack.packb(dict(info, distortion_model="plumb_bob"), use_bin_type=True)


def row_infos(args, report) -> None:
    K = np.array([[900.0, 0, 640], [0, 900.0, 360], [0, 0, 1]])
    cases = {"fx_1e-300": K.copy(), "fx_1e300": K.copy(), "skew_1e300": K.copy()}
    cases["fx_1e-300"][0, 0] = cases["fx_1e-300"][1, 1] = 1e-300
    cases["fx_1e300"][0, 0] = cases["fx_1e300"][1, 1] = 1e300
    cases["skew_1e300"][0, 1] = 1e300
    daemon = Served()
    try:
        import zenoh

        with zenoh.open(peer_config(daemon.zport)) as session:
            time.sleep(1.0)
            infos = {name: _info_payload(name, 1280, 720, k, [0] * 5) for name, k in cases.items()}
            infos["dist_1e12"] = _info_payload("dist_1e12", 1280, 720, K, [1e12, 0, 0, 0, 0])
            small = K * [[0.5], [2 / 3], [1]]  # the same lens at 640x480
            infos["640x480_info"] = _info_payload("640x480_info", 640, 480, small, [0] * 5)
            cams = {name: GoodCamera(session, name, seed=3) for name in infos}
            for name, payload in infos.items():
                cams[name].put("info", payload)
            for k in range(5):
                for cam in cams.values():
                    cam.frame(100 * SECOND + k * SECOND // 2)
                time.sleep(0.5)
            _wait(lambda: daemon.stats()["ingest_pending"] == 0, 30)
            time.sleep(2.0)
            stats = daemon.stats()
        out = daemon.output()
    finally:
        daemon.close()
    processed = sum(stats["cameras"].get(n, {}).get("processed", 0) for n in infos)
    reasons = {k: v for k, v in stats["decode_errors_by_reason"].items() if "info" in k}
    unlike = stats["frames_dropped"].get("size_unlike_info", 0)
    warnings = out.count("RuntimeWarning")
    report(
        "infos",
        f"5 implausible camera infos, 5 frames each: infos refused {reasons}, images dropped "
        f"size_unlike_info {unlike}, frames of those cameras processed {processed}, numpy "
        f"RuntimeWarnings in the log {warnings}",
        refused=reasons,
        size_unlike_info=unlike,
        processed=processed,
        warnings=warnings,
    )


ROWS = {"overload": row_overload, "flood": row_flood, "junk": row_junk, "events": row_events}
ROWS["infos"] = row_infos


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", help="DIR:SCENE of a pile, for the overload row")
    parser.add_argument("--busy", type=int, default=2, help="processes spinning beside (overload)")
    parser.add_argument("--runs", type=int, default=3, help="fresh daemons (flood)")
    parser.add_argument("--rows", default=",".join(ROWS), help=f"of {', '.join(ROWS)}")
    parser.add_argument("--json", help="write the results here too")
    args = parser.parse_args(argv)
    rows = [r for r in args.rows.split(",") if r]
    unknown = [r for r in rows if r not in ROWS]
    if unknown:
        parser.error(f"--rows: no row {unknown[0]!r} (rows: {', '.join(ROWS)})")
    if "overload" in rows and not args.scene:
        parser.error("--scene DIR:SCENE is needed for the overload row")
    results: dict = {}

    def report(row: str, line: str, **numbers) -> None:
        results[row] = numbers
        print(f"{row}: {line}", flush=True)

    for row in rows:
        ROWS[row](args, report)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
