"""A stop by signal, as systemd (SIGTERM) or a terminal (SIGINT) makes it, against
``posefuse serve --state-dir`` in its own process: the frame in flight is fused, the snapshot
written, the process exits 0, and a restart restores every object. The periodic snapshot is
made rare so that only the stop can have written it."""

import json
import signal
import time

from loopback import ServeProcess, wait_until, zenoh_peer
from test_faults_restart import _put_all

from posefuse.clients.camera import InfoServer, scene_messages
from posefuse.evaluation.dataset import load_dataset

CELL = "stops"
ENV = {"POSEFUSE_STATE_INTERVAL_S": "3600"}


def _header(state_dir) -> dict:
    with open(state_dir / "estimator.state", "rb") as f:
        return json.loads(f.readline())


def _feed_and_stop(daemon, messages, sig) -> str:
    """Publish the scene, send ``sig`` once its last frame left the synchroniser (it is in the
    front end or the estimator, or done), and wait for the process to exit; returns what it
    printed."""
    n_images = sum(m[1].endswith("/image") for m in messages)
    with zenoh_peer(daemon.endpoint) as session:
        time.sleep(0.5)
        info_server = InfoServer(session)
        synced0 = daemon.stats()["cameras"].get("cam0", {}).get("synced", 0)
        _put_all(session, messages, info_server, daemon)
        wait_until(
            lambda: (
                daemon.stats()["cameras"].get("cam0", {}).get("synced", 0) >= synced0 + n_images
            ),
            120,
            interval=0.02,
            what="the last frame in flight",
            context=daemon.stats,
        )
        daemon.proc.send_signal(sig)
        rc = daemon.proc.wait(timeout=120)
        info_server.close()
    out = daemon.proc.stdout.read()
    assert rc == 0, out
    assert f"stopped by {signal.Signals(sig).name}" in out
    return out


def test_sigterm_and_sigint_finish_the_frame_write_the_snapshot_and_exit_0(
    full_res_dataset, tmp_path
):
    state_dir = tmp_path / "state"
    args = ("--cell", CELL, "--state-dir", str(state_dir))
    t0, period = 1_000_000_000_000, 250_000_000
    messages = list(scene_messages(load_dataset(full_res_dataset), 0, CELL, "cam0", 4.0, t0_ns=t0))
    last_stamp = t0 + (sum(m[1].endswith("/image") for m in messages) - 1) * period
    daemon = ServeProcess(*args, env=ENV)
    try:
        out = _feed_and_stop(daemon, messages, signal.SIGTERM)
        assert "the bin is known" not in out  # the example bin is no cell's until it is said
        header = _header(state_dir)
        assert header["objects"] >= 1
        assert header["last_stamp_ns"] == last_stamp  # the frame in flight was fused
        n_objects = header["objects"]

        daemon = ServeProcess(*args, env=ENV)
        assert daemon.stats()["restored_objects"] == n_objects
        saved_at = (state_dir / "estimator.state").stat().st_mtime_ns
        _feed_and_stop(daemon, messages, signal.SIGINT)  # the scene again: more views
        assert (state_dir / "estimator.state").stat().st_mtime_ns > saved_at
        header = _header(state_dir)
        assert header["objects"] >= n_objects

        daemon = ServeProcess(*args, env={**ENV, "POSEFUSE_BIN_KNOWN": "1"})
        assert daemon.stats()["restored_objects"] == header["objects"]
        assert len(daemon.objects()) == header["objects"]
        daemon.stop()
        out = daemon.proc.stdout.read()
        assert "the bin is known (0.42 x 0.32 m, its floor's centre at (0, 0, 0) m" in out, out
    finally:
        daemon.stop()
