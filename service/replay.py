"""Offline replay: recorded messages fed, in log-time order, through the daemon's own intake
(:mod:`service.intake`: the same key and size checks, queue, decoding and synchronisation) and
worker function, without Zenoh. The same input gives the same output, bit for bit."""

from __future__ import annotations

import json
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

from posefuse.service.codec import (
    DecodeError,
    decode_reset,
    encode_estimate,
    estimate_to_dict,
)
from posefuse.service.intake import Intake
from posefuse.service.keys import Keys
from posefuse.service.recording import Recorder
from posefuse.service.settings import put_camera_message
from posefuse.service.sync import FrameSynchronizer
from posefuse.service.worker import EstimatorWorker


@dataclass
class ReplayResult:
    """published: every ObjectEstimate update in order (dicts); segments: the estimates held
    just before each reset request of the recording, and at its end."""

    published: list[dict] = field(default_factory=list)
    segments: list[list[dict]] = field(default_factory=list)


def replay_offline(
    messages: Iterable[tuple[int, str, bytes]],
    worker: EstimatorWorker,
    cell: str = "posefuse",
    sync: FrameSynchronizer | None = None,
    max_payload_bytes: int = 16 * 1024 * 1024,
    recorder: Recorder | None = None,
    max_image_pixels: int = 4096 * 4096,
) -> ReplayResult:
    """(log_time_ns, key, payload) in log-time order -> what the daemon would have published.

    Bad messages are counted in ``worker.stats.decode_errors`` and skipped, as live. A reset
    request recorded on the reset key is carried out (after the frames before it). With a
    ``recorder``, every message read and every estimate published (on its object key, at the
    log time of the message that completed the frame) is written to it.

    The log time stands for the arrival time of the live daemon: the synchroniser's waiting
    deadlines are judged in it, so a replay gives the same output on every machine.
    """
    keys = Keys(cell)
    stats = worker.stats
    intake = Intake(keys, sync or FrameSynchronizer(), stats, max_payload_bytes, max_image_pixels)
    result = ReplayResult()
    for log_time, key, payload in messages:
        if recorder is not None:
            recorder.write(key, payload, log_time)
        if key == keys.reset:
            stats.count(stats.received, key)
            try:
                request = decode_reset(payload)
            except DecodeError:
                stats.count(stats.decode_errors, key)
                continue
            if stats.processed:
                result.segments.append([estimate_to_dict(e) for e in worker.snapshot()])
            try:
                worker.reset(request.class_id, request.object_id)
            except (KeyError, ValueError):
                pass
            continue
        if keys.parse_camera(key) is None:
            # outputs and other cells' keys in a recording are not inputs (counted by key, as
            # recorded, not as the daemon's unknown keys)
            stats.count(stats.received, key)
            continue
        intake.receive(key, payload, log_time)  # the log time stands for the arrival time
        if not intake.drain():
            continue  # refused (counted): the synchroniser is not asked for frames
        while (frame := intake.pop(log_time)) is not None:
            for e in worker.process(frame):
                result.published.append(estimate_to_dict(e))
                if recorder is not None:
                    recorder.write(keys.object(e.object_id), encode_estimate(e), log_time)
    result.segments.append([estimate_to_dict(e) for e in worker.snapshot()])
    return result


def write_estimates_json(path: str | Path, published: list[dict], segments: list) -> Path:
    """Deterministic JSON: every update in order, and the state at the end of each segment."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    doc = {"updates": published, "segments": segments}
    path.write_text(json.dumps(doc, indent=1, sort_keys=True) + "\n")
    return path


def replay_live(
    messages: list[tuple[int, str, bytes]],
    session,
    cell: str = "posefuse",
    rate: float = 1.0,
    handled=None,
    progress=None,
    timeout_s: float = 30.0,
    token: str | None = None,
) -> int:
    """Publish recorded (log_time_ns, key, payload) over Zenoh.

    Paced at ``rate`` times real time; or, with ``handled`` (a function giving how many images
    the daemon has processed or dropped), in lockstep: after each pose message the next is sent
    only when every image sent so far has been dealt with (an image still waiting for a later
    pose lets the replay go on). Recorded reset requests become queries on the reset key.
    Returns the number of messages sent.
    """
    import time

    keys = Keys(cell)
    start_wall = time.monotonic()
    t0 = messages[0][0] if messages else 0
    images = 0
    sent = 0
    for log_time, key, payload in messages:
        if handled is None and rate > 0:
            delay = start_wall + (log_time - t0) / 1e9 / rate - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        if key == keys.reset:
            extra = {} if token is None else {"attachment": token.encode()}
            for _ in session.get(keys.reset, payload=payload, timeout=timeout_s, **extra):
                pass
            sent += 1
            continue
        if keys.parse_camera(key) is None:
            continue  # ground truth and outputs are not replayed
        put_camera_message(session, key, payload)
        sent += 1
        if key.endswith("/image"):
            images += 1
            if progress:
                progress()
        elif handled is not None:
            deadline = time.monotonic() + timeout_s
            last, since = handled(), time.monotonic()
            while last < images and time.monotonic() < deadline:
                time.sleep(0.01)
                now = handled()
                if now != last:
                    last, since = now, time.monotonic()
                elif time.monotonic() - since > 1.0:
                    break  # an image waits for a later pose: go on
    return sent
