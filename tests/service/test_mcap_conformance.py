"""Recordings read by a second, independent MCAP implementation (the TypeScript @mcap/core,
through Node.js), with every Foxglove channel validated against the published Foxglove JSON
schemas (@foxglove/schemas). The npm packages are pinned in tests/js/package-lock.json and
installed on first use."""

import json
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from loopback import wait_until

from posefuse.estimator.core.objects import load_catalog
from posefuse.estimator.tracker import MultiViewEstimator, ObjectEstimate
from posefuse.service.codec import encode_camera_pose, encode_estimate
from posefuse.service.foxglove import FoxgloveMirror
from posefuse.service.keys import Keys
from posefuse.service.recording import Recorder, read_messages
from posefuse.service.replay import replay_offline
from posefuse.service.resources import DEFAULT_CATALOG, DEFAULT_MODEL, DEFAULT_RECORDING
from posefuse.service.settings import Settings, zenoh_config
from posefuse.service.worker import EstimatorWorker, make_detector

TESTS = Path(__file__).resolve().parents[1]
JS = TESTS / "js"
FOXGLOVE_SCHEMAS = {
    "foxglove.CompressedImage",
    "foxglove.CameraCalibration",
    "foxglove.FrameTransform",
    "foxglove.SceneUpdate",
}


@pytest.fixture(scope="session")
def mcap_check():
    """A function: path -> (exit code, report) of tests/js/check_mcap.js."""
    node, npm = shutil.which("node"), shutil.which("npm")
    if node is None or npm is None:
        pytest.fail("Node.js and npm are needed to read recordings with @mcap/core")
    if not (JS / "node_modules" / "@mcap" / "core").is_dir():
        subprocess.run(
            [npm, "ci", "--no-audit", "--no-fund", "--silent"], cwd=JS, check=True, timeout=300
        )

    def check(path):
        proc = subprocess.run(
            [node, str(JS / "check_mcap.js"), str(path)],
            capture_output=True,
            text=True,
            timeout=120,
        )
        return proc.returncode, json.loads(proc.stdout)

    return check


def _raw_counts(path):
    return Counter(m.key for m in read_messages(path))


def _assert_conforms(code, report, path):
    assert report["errors"] == [] and code == 0, report["errors"]
    raw = _raw_counts(path)
    for key, n in raw.items():  # the other reader sees what ours sees
        assert report["topics"][key]["count"] == n
        assert report["topics"][key]["message_encoding"] == "msgpack"
    total = sum(t["count"] for t in report["topics"].values())
    assert report["indexed_messages"] == total == report["statistics_messages"]
    return {t["schema"]: t["count"] for t in report["topics"].values() if t["schema"]}


def test_demo_recording_is_valid_mcap_with_foxglove_channels(mcap_check):
    code, report = mcap_check(DEFAULT_RECORDING)
    schemas = _assert_conforms(code, report, DEFAULT_RECORDING)
    assert FOXGLOVE_SCHEMAS <= set(schemas)
    assert set(report["schemas"].values()) == {"jsonschema"}
    topics = report["topics"]
    assert topics["/posefuse/cam0/image"]["count"] == topics["posefuse/@v1/cam/cam0/image"]["count"]
    assert topics["/tf"]["count"] == topics["posefuse/@v1/cam/cam0/pose"]["count"]


def test_replay_output_records_the_estimates_for_foxglove(mcap_check, default_banks, tmp_path):
    catalog = load_catalog(DEFAULT_CATALOG)
    settings = Settings(model=DEFAULT_MODEL, catalog=DEFAULT_CATALOG)
    worker = EstimatorWorker(
        MultiViewEstimator(catalog, banks=default_banks), make_detector(settings, catalog)
    )
    messages = [(m.log_time_ns, m.key, m.payload) for m in read_messages(DEFAULT_RECORDING)]
    messages = messages[: len(messages) // 3]  # the first scene
    out = tmp_path / "estimates.mcap"
    with Recorder(out, mirror=FoxgloveMirror("posefuse", catalog)) as recorder:
        result = replay_offline(messages, worker, recorder=recorder)
    assert result.published
    code, report = mcap_check(out)
    schemas = _assert_conforms(code, report, out)
    assert FOXGLOVE_SCHEMAS <= set(schemas)
    n_estimates = sum(c for k, c in _raw_counts(out).items() if "/objects/" in k)
    assert n_estimates == len(result.published)
    # each estimate gives one scene entity and one transform world -> obj/{id}
    n_poses = report["topics"]["posefuse/@v1/cam/cam0/pose"]["count"]
    assert report["topics"]["/tf"]["count"] == n_poses + n_estimates
    assert report["topics"]["/posefuse/objects"]["count"] >= n_estimates


def test_the_checker_rejects_a_message_that_breaks_its_schema(mcap_check, tmp_path):
    path = tmp_path / "bad.mcap"
    good = {
        "timestamp": {"sec": 1, "nsec": 0},
        "parent_frame_id": "world",
        "child_frame_id": "cam0",
        "translation": {"x": 0.0, "y": 0.0, "z": 1.0},
        "rotation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
    }
    bad = dict(good, rotation={"x": 0.0, "y": 0.0, "z": 0.0})  # no w
    with Recorder(path) as recorder:
        recorder.write_json("/tf", "foxglove.FrameTransform", json.dumps(good).encode(), 1)
        recorder.write_json("/tf", "foxglove.FrameTransform", json.dumps(bad).encode(), 2)
    code, report = mcap_check(path)
    assert code == 1
    assert any("/tf @2" in e and "published" in e for e in report["errors"])
    assert not any("/tf @1" in e for e in report["errors"])


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _estimate_payload(object_id: str) -> bytes:
    T = np.eye(4)
    T[:3, 3] = [0.05, 0.0, 0.02]
    estimate = ObjectEstimate(
        stamp_ns=2 * 10**9,
        object_id=object_id,
        class_id=1,
        class_name="tube_fitting",
        T_world_obj=T,
        cov=np.eye(6) * 1e-4,
        confidence=0.8,
        hypotheses=(),
        n_views=3,
        status="confirmed",
    )
    return encode_estimate(estimate)


def test_record_command_writes_raw_and_foxglove_channels(mcap_check, tmp_path):
    """`posefuse record` as its own process: camera poses and an estimate published on the
    cell's keys are written raw and as Foxglove messages; a garbage message only raw."""
    import zenoh

    port = _free_port()
    out = tmp_path / "cell.mcap"
    command = [sys.executable, "-m", "posefuse.cli", "record", "--out", str(out)]
    command += ["--listen", f"tcp/127.0.0.1:{port}"]
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    keys = Keys("posefuse")
    try:
        assert "recording" in proc.stdout.readline()
        conf = zenoh_config(Settings(listen=[], mode="peer", connect=[f"tcp/127.0.0.1:{port}"]))
        with zenoh.open(conf) as session:
            # until the recorder's subscription is known here: a put before it would be lost
            probe = session.declare_publisher(keys.camera("cam0", "pose"))
            wait_until(lambda: probe.matching_status.matching, 30, what="the recorder")
            probe.undeclare()
            T = np.eye(4)
            T[:3, 3] = [0.1, 0.2, 0.8]
            for k in range(3):
                session.put(keys.camera("cam0", "pose"), encode_camera_pose(10**9 + k, "cam0", T))
            session.put(keys.object("a1"), _estimate_payload("a1"))
            session.put(keys.camera("cam0", "pose"), b"\x00garbage")
            time.sleep(1.0)  # delivery of the last puts (the recorder counts nothing we could see)
        proc.send_signal(signal.SIGTERM)  # stops as Ctrl-C: the file is finished
        assert proc.wait(timeout=30) == 0, proc.stdout.read()
    finally:
        proc.kill()
    raw = _raw_counts(out)
    assert raw[keys.camera("cam0", "pose")] == 4 and raw[keys.object("a1")] == 1
    code, report = mcap_check(out)
    _assert_conforms(code, report, out)
    assert report["topics"]["/tf"]["count"] == 3 + 1  # three camera poses and the object
    assert report["topics"]["/posefuse/objects"]["count"] == 1
