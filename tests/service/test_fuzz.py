"""10,000 malformed messages on every input key (a seeded generator: random bytes, empty and
oversized payloads, every field of a valid message replaced by a wrong value, decompression
bombs): the daemon keeps running, counts them, its estimates do not change, and its memory
stays bounded."""

import math

import msgpack
import numpy as np
import pytest

from posefuse.estimator.tracker import MultiViewEstimator
from posefuse.service.codec import encode_camera_info, encode_camera_pose
from posefuse.service.daemon import Daemon
from posefuse.service.settings import Settings
from posefuse.service.sync import SyncedFrame
from posefuse.service.worker import EstimatorWorker
from posefuse.sim.scenes import REALSENSE_1280x720 as CAM
from posefuse.sim.scenes import SceneSpec
from posefuse.sim.sequences import make_sequence

N = 10_000
# the generator itself makes a thousand 17 MB payloads (the allocator keeps some); one decoded
# 20000x20000 bomb alone would add 1144 MB
RSS_GROWTH_BOUND_MB = 512


class _Payload:
    def __init__(self, data):
        self._data = data

    def to_bytes(self):
        return self._data


class _Sample:
    def __init__(self, key, data):
        self.key_expr = key
        self.payload = _Payload(data)


_BOMBS = {}


def _bomb(rng):
    from posefuse.bench.bombs import image_message, jpeg_bomb, png_bomb

    if not _BOMBS:
        _BOMBS["png"], _BOMBS["jpeg"] = png_bomb(), jpeg_bomb()
    encoding = ("png", "jpeg")[int(rng.integers(2))]
    declared = [(8, 8), (4096, 4096), (8192, 8192)][int(rng.integers(3))]
    return image_message(_BOMBS[encoding], encoding, 5, declared)


def _garbage(rng, kind):
    """Malformed payloads of many shapes for one message kind."""
    good_pose = msgpack.unpackb(encode_camera_pose(5, "cam0", np.eye(4)))
    good_info = msgpack.unpackb(encode_camera_info(5, "cam0", CAM))
    good_image = {
        "v": 1,
        "stamp_ns": 5,
        "frame_id": "cam0",
        "encoding": "rgb8",
        "width": 8,
        "height": 8,
        "data": bytes(192),
    }
    base = {"pose": good_pose, "info": good_info, "image": good_image}[kind]
    r = int(rng.integers(10))
    if r == 0:
        return rng.bytes(int(rng.integers(0, 200)))  # random bytes
    if r == 1:
        return b""
    if r == 2:
        if kind == "image" and rng.integers(2):
            return _bomb(rng)
        return b"\x00" * (17 * 1024 * 1024)  # oversized
    if r == 3:
        return msgpack.packb([1, 2, 3])
    msg = dict(base)
    field = list(msg)[int(rng.integers(len(msg)))]
    bad_values = [
        None,
        "x",
        -1,
        2**70,
        math.nan,
        math.inf,
        [],
        [math.nan] * 9,
        {"a": 1},
        b"\xff" * 3,
        [1e308] * 4,
        True,
    ]
    msg[field] = bad_values[int(rng.integers(len(bad_values)))]
    if r == 4:
        msg["v"] = 2
    if r == 5 and kind == "image":
        msg.update(encoding="jpeg", data=rng.bytes(100))
    if r == 6 and kind == "pose":
        msg["q"] = [0.0, 0.0, 0.0, 0.5]
    try:
        return msgpack.packb(msg, use_bin_type=True)
    except (OverflowError, TypeError, ValueError):
        return rng.bytes(50)


@pytest.fixture()
def daemon(robi_catalog):
    seq = make_sequence(robi_catalog, 8, SceneSpec(n_views=3))
    by_stamp = {v.frame.stamp_ns: v.detections for v in seq.views}
    worker = EstimatorWorker(MultiViewEstimator(robi_catalog), lambda im, s: by_stamp[s])
    for v in seq.views:
        f = v.frame
        worker.process(SyncedFrame("cam0", f.stamp_ns, None, f.camera, f.T_world_cam))
    return Daemon(Settings(cell="fuzz"), worker)


def _rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return 0.0


def test_malformed_messages_are_counted_and_change_nothing(daemon):
    before = {e.object_id: e.T_world_obj.copy() for e in daemon.worker.snapshot()}
    assert before
    rng = np.random.default_rng(0)
    accepted = 0
    start = _rss_mb()  # the test process holds the whole suite's data: bound the growth
    peak = start
    for kind in ("info", "image", "pose"):
        key = f"fuzz/@v1/cam/cam0/{kind}"
        for k in range(N):
            errors = daemon.stats.decode_errors.get(key, 0)
            daemon.on_sample(_Sample(key, _garbage(rng, kind)))
            daemon.drain()
            accepted += daemon.stats.decode_errors.get(key, 0) == errors
            if k % 500 == 0:
                peak = max(peak, _rss_mb())
            while daemon.sync.pop() is not None:  # the few valid ones are not processed
                pass
    # a few mutations leave a valid message (e.g. a frame_id of 'x'); all others are counted
    stats = daemon.stats_dict()
    for kind in ("info", "image", "pose"):
        assert stats["decode_errors"][f"fuzz/@v1/cam/cam0/{kind}"] >= 0.8 * N
        assert stats["received"][f"fuzz/@v1/cam/cam0/{kind}"] == N
    assert accepted < 0.2 * 3 * N
    assert stats["decode_errors_by_reason"]["image_header_mismatch"] > 0
    assert stats["decode_errors_by_reason"]["image_too_large"] > 0
    assert peak - start < RSS_GROWTH_BOUND_MB, f"RSS grew from {start:.0f} to {peak:.0f} MB"
    # unknown keys are counted as well, all under one counter however many there are
    for k in range(5000):
        daemon.on_sample(_Sample(f"fuzz/@v1/cam/cam{k}/depth", b"x"))
    assert daemon.stats.received["other"] == 5000
    assert daemon.ingest_dropped["not_an_input_key"] == 5000
    assert len(daemon.stats_dict()["received"]) <= daemon.stats.max_keys
    after = {e.object_id: e.T_world_obj for e in daemon.worker.snapshot()}
    assert after.keys() == before.keys()
    for oid in before:
        np.testing.assert_array_equal(after[oid], before[oid])
