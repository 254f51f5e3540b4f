"""Offline replay: recorded messages fed, in order, through the daemon's own decoding,
synchronisation and worker function, without Zenoh. The same input gives the same output,
bit for bit."""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path

from service.codec import DecodeError, estimate_to_dict
from service.daemon import DECODERS
from service.keys import Keys
from service.sync import FrameSynchronizer
from service.worker import EstimatorWorker


def replay_offline(
    messages: Iterable[tuple[str, bytes]],
    worker: EstimatorWorker,
    cell: str = "posefuse",
    sync: FrameSynchronizer | None = None,
    max_payload_bytes: int = 16 * 1024 * 1024,
) -> list[dict]:
    """(key, payload) pairs in log-time order -> every published ObjectEstimate, as dicts.

    Bad messages are counted in ``worker.stats.decode_errors`` and skipped, as live.
    """
    keys = Keys(cell)
    sync = sync or FrameSynchronizer()
    published: list[dict] = []
    for key, payload in messages:
        worker.stats.count(worker.stats.received, key)
        parsed = keys.parse_camera(key)
        if parsed is None:
            continue  # outputs and other cells' keys in a recording are not inputs
        cam_id, kind = parsed
        try:
            msg = DECODERS[kind](payload, max_payload_bytes)
        except DecodeError:
            worker.stats.count(worker.stats.decode_errors, key)
            continue
        {"info": sync.add_info, "pose": sync.add_pose, "image": sync.add_image}[kind](cam_id, msg)
        while (frame := sync.pop()) is not None:
            published.extend(estimate_to_dict(e) for e in worker.process(frame))
    return published


def write_estimates_json(path: str | Path, published: list[dict], final: list[dict]) -> Path:
    """Deterministic JSON: every update in order, and the final state."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    doc = {"updates": published, "final": final}
    path.write_text(json.dumps(doc, indent=1, sort_keys=True) + "\n")
    return path
