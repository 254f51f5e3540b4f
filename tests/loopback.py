"""Helpers of the tests that run processes on loopback: a free port, a JSON GET, a served
daemon, a Zenoh peer, a camera publishing synthetic frames."""

import json
import socket
import time
import urllib.request

import cv2
import numpy as np

from posefuse.service.codec import encode_camera_info, encode_camera_pose, encode_image
from posefuse.service.settings import put_camera_message


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def get_json(url: str, timeout: float = 5.0):
    with urllib.request.urlopen(url, timeout=timeout) as r:
        return json.loads(r.read())


class ServeProcess:
    """``posefuse serve`` in its own process on loopback ports, ready when this returns."""

    def __init__(self, *args: str, env: dict | None = None, timeout: float = 180.0):
        import os
        import subprocess
        import sys
        import time

        self.zenoh_port, self.http_port = free_port(), free_port()
        self.endpoint = f"tcp/127.0.0.1:{self.zenoh_port}"
        self.base = f"http://127.0.0.1:{self.http_port}"
        command = [sys.executable, "-m", "posefuse.cli", "serve"]
        command += ["--http-port", str(self.http_port)]
        if "--listen" not in args and "--mode" not in args:
            command += ["--listen", self.endpoint]
        self.log = open(os.devnull, "w")
        self.proc = subprocess.Popen(
            [*command, *args],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})},
        )
        deadline = time.time() + timeout
        while True:
            try:
                if get_json(f"{self.base}/readyz", 1)["status"] == "ready":
                    break
            except OSError:
                pass
            if self.proc.poll() is not None or time.time() > deadline:
                self.kill()
                raise AssertionError(f"daemon did not start:\n{self.proc.stdout.read()}")
            time.sleep(0.3)

    @property
    def pid(self) -> int:
        return self.proc.pid

    def stats(self) -> dict:
        return get_json(f"{self.base}/stats")

    def objects(self) -> list:
        return get_json(f"{self.base}/objects")

    def rss_mb(self) -> float:
        import psutil

        return psutil.Process(self.proc.pid).memory_info().rss / 2**20

    def kill(self) -> None:
        """SIGKILL: no shutdown code runs."""
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(timeout=20)

    def stop(self) -> None:
        import subprocess

        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


def wait_until(
    predicate, timeout: float = 30.0, interval: float = 0.2, what: str = "", context=None
):
    """Poll ``predicate`` until it returns a truthy value; AssertionError on timeout, with
    ``context()`` (e.g. the daemon's stats) in the message."""
    import time

    deadline = time.time() + timeout
    last = None
    while time.time() < deadline:
        last = predicate()
        if last:
            return last
        time.sleep(interval)
    extra = f"; {context()!r}" if context is not None else ""
    raise AssertionError(f"timed out waiting for {what or predicate}: last {last!r}{extra}")


def zenoh_peer(*connect: str):
    """A zenoh session (peer, no scouting, no listener) connected to the endpoints."""
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", "[]")
    conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    return zenoh.open(conf)


SECOND = 1_000_000_000

ROUTER = """
import sys, time, zenoh
conf = zenoh.Config()
conf.insert_json5("mode", '"router"')
conf.insert_json5("scouting/multicast/enabled", "false")
conf.insert_json5("listen/endpoints", '["tcp/127.0.0.1:%s"]' % sys.argv[1])
with zenoh.open(conf):
    print("router up", flush=True)
    while True:
        time.sleep(1)
"""


def start_router(port: int):
    """A Zenoh router in its own process on tcp/127.0.0.1:port (kill it when done)."""
    import subprocess
    import sys

    proc = subprocess.Popen(
        [sys.executable, "-c", ROUTER, str(port)], stdout=subprocess.PIPE, text=True
    )
    if proc.stdout.readline().strip() != "router up":
        proc.kill()
        raise AssertionError("the Zenoh router did not start")
    return proc


class FakeCamera:
    """Publishes a camera's info, poses and JPEG frames (of noise) with stamps it is given, put
    as docs/protocol.md asks of a camera driver (a busy link delays them, never drops them)."""

    def __init__(self, session, cell: str, cam_id: str, seed: int = 0):
        self.session = session
        self.cell = cell
        self.cam_id = cam_id
        # a smooth random image at the size of the shipped model's camera (small as JPEG)
        small = np.random.default_rng(seed).integers(0, 255, (9, 16, 3), np.uint8)
        self.image = cv2.resize(small, (1280, 720), interpolation=cv2.INTER_CUBIC)
        self.seq = 0
        self.info_server = None

    def key(self, kind: str) -> str:
        return f"{self.cell}/@v1/cam/{self.cam_id}/{kind}"

    def info(self, stamp: int = 0) -> None:
        """Publish the camera info, and answer the daemon's requests for it from now on."""
        from posefuse.clients.camera import InfoServer

        height, width = self.image.shape[:2]  # the info describes the images it sends
        payload = encode_camera_info(stamp, self.cam_id, _camera(width, height))
        if self.info_server is None:
            self.info_server = InfoServer(self.session)
        self.info_server.publish(self.key("info"), payload)
        put_camera_message(self.session, self.key("info"), payload)

    def pose(self, stamp: int) -> None:
        T = np.eye(4)
        T[2, 3] = -0.5
        put_camera_message(
            self.session, self.key("pose"), encode_camera_pose(stamp, self.cam_id, T)
        )

    def image_only(self, stamp: int, image=None) -> None:
        image = self.image if image is None else image
        self.seq += 1
        payload = encode_image(stamp, self.cam_id, image, "jpeg", 80, seq=self.seq)
        put_camera_message(self.session, self.key("image"), payload)

    def frame(self, stamp: int) -> None:
        """A pose at the stamp, then the image."""
        self.pose(stamp)
        self.image_only(stamp)

    def frames(
        self,
        first: int,
        n: int,
        period: int = SECOND // 10,
        pause: float = 0.05,
        daemon=None,
    ):
        """n frames ``period`` apart in stamp time; with ``daemon`` (a ServeProcess), each one
        after the previous was handled (a camera the daemon keeps up with: none dropped as
        queue_full), else ``pause`` seconds apart."""
        for k in range(n):
            handled = daemon.stats()["frames_handled"] if daemon is not None else 0
            self.frame(first + k * period)
            if daemon is not None:
                wait_until(
                    lambda h=handled: daemon.stats()["frames_handled"] > h,
                    30,
                    what=f"frame {k} of {self.cam_id} handled",
                    context=daemon.stats,
                )
            else:
                time.sleep(pause)


def _camera(width: int = 1280, height: int = 720):
    """The fake camera at 1280x720, or its intrinsics scaled to another image size."""
    import numpy as np

    from posefuse.estimator.core.camera import Camera

    sx, sy = width / 1280, height / 720
    K = np.array([[900.0 * sx, 0, 640 * sx], [0, 900.0 * sy, 360 * sy], [0, 0, 1]])
    return Camera(K, width, height)
