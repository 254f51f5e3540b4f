"""`posefuse record` ends with a valid file when it is told to stop (SIGTERM as SIGINT) and when
the disk fills up (a 2 MB tmpfs in a private mount namespace): it says how many messages the
file holds, and the file reads back to exactly those."""

import os
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
from loopback import free_port, wait_until, zenoh_peer

from posefuse.service.codec import encode_camera_pose, encode_image
from posefuse.service.keys import Keys
from posefuse.service.recording import read_messages

KEYS = Keys("posefuse")


def _wait_for_subscriber(session, key: str) -> None:
    publisher = session.declare_publisher(key)
    try:
        wait_until(lambda: publisher.matching_status.matching, 30, what=f"a subscriber of {key}")
    finally:
        publisher.undeclare()


def _publish(endpoint: str, n_images: int, size: int = 200) -> None:
    rng = np.random.default_rng(0)
    with zenoh_peer(endpoint) as session:
        # until the recorder's subscription is known here: a put before it would be lost
        _wait_for_subscriber(session, KEYS.camera("cam0", "image"))
        for k in range(n_images):
            image = rng.integers(0, 255, (size, size, 3), np.uint8)
            session.put(
                KEYS.camera("cam0", "pose"), encode_camera_pose(10**9 + k, "cam0", np.eye(4))
            )
            session.put(KEYS.camera("cam0", "image"), encode_image(10**9 + k, "cam0", image, "png"))
            time.sleep(0.02)
        time.sleep(1.0)


def test_sigterm_finishes_the_file(tmp_path):
    port = free_port()
    out = tmp_path / "cell.mcap"
    command = [sys.executable, "-m", "posefuse.cli", "record", "--out", str(out)]
    proc = subprocess.Popen(
        [*command, "--listen", f"tcp/127.0.0.1:{port}"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        assert "recording" in proc.stdout.readline()
        _publish(f"tcp/127.0.0.1:{port}", 5, size=16)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == 0
        assert "wrote 10 messages" in proc.stdout.read()
    finally:
        proc.kill()
    assert len(list(read_messages(out))) == 10  # read_messages raises without a footer


def test_a_full_disk_stops_the_recording_with_a_footer(tmp_path):
    if shutil.which("unshare") is None:
        raise AssertionError("this test needs util-linux's unshare (a private tmpfs)")
    port = free_port()
    disk = tmp_path / "disk"
    disk.mkdir()
    script = (
        f"mount -t tmpfs -o size=2m tmpfs {disk} && "
        f"{sys.executable} -m posefuse.cli record --out {disk}/cell.mcap "
        f"--listen tcp/127.0.0.1:{port} --duration 25; rc=$?; "
        f"cp {disk}/cell.mcap {tmp_path}/cell.mcap; exit $rc"
    )
    # as root a private mount namespace is enough; otherwise map this user to root in a user
    # namespace (where Zenoh's shared-memory transport may not reach the recorder)
    as_root = [] if os.geteuid() == 0 else ["--map-root-user"]
    proc = subprocess.Popen(
        ["unshare", "--mount", *as_root, "sh", "-c", script],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        cwd=os.getcwd(),
    )
    try:
        assert "recording" in proc.stdout.readline()
        _publish(f"tcp/127.0.0.1:{port}", 60)  # 60 x ~120 kB PNG of noise: 7 MB
        code = proc.wait(timeout=60)
        output = proc.stdout.read()
    finally:
        proc.kill()
    assert code == 1, output
    assert "writing failed" in output and "the file is finished and readable" in output
    held = int(output.split(" after ")[1].split(" messages")[0])
    assert 0 < held < 120
    messages = list(read_messages(tmp_path / "cell.mcap"))
    assert len(messages) == held
