"""What the service counts, and the ``/stats`` map made of it.

- :class:`Stats`: the worker's counters (messages received and refused, by key and by reason;
  frames processed and failed; latencies), per-key tables bounded so junk keys cannot grow
  memory.
- :class:`FrameCounters`: what became of the synchronised frames past the worker's totals (per
  camera processed and failed, refused by the front end by reason) and the daemon's events;
  :meth:`FrameCounters.stats_dict` gathers them with the intake's and the synchroniser's into
  the map of ``/stats`` (its keys are part of the HTTP API).
"""

from __future__ import annotations

import logging
import time
from collections import Counter, deque
from dataclasses import dataclass, field

import numpy as np

log = logging.getLogger("posefuse.daemon.stats")


@dataclass
class Stats:
    """Counters of the daemon. Per-key tables hold at most ``max_keys`` keys, the most recently
    seen: a key that leaves adds its count to ``other``, so a table's total stays exact (junk
    keys must not grow memory, nor push out for good the keys of the cameras that work)."""

    received: dict[str, int] = field(default_factory=dict)  # per key
    decode_errors: dict[str, int] = field(default_factory=dict)  # per key
    decode_reasons: dict[str, int] = field(default_factory=dict)  # per DecodeError code
    processed: int = 0
    errors: int = 0
    latencies_ms: deque = field(default_factory=lambda: deque(maxlen=1000))
    max_keys: int = 64

    def count(self, table: dict[str, int], key: str) -> None:
        if key in table:  # re-inserted: a dict keeps insertion order, so this is recency
            table[key] = table.pop(key) + 1
            return
        while len(table) >= self.max_keys:
            oldest = next((k for k in table if k != "other"), None)
            if oldest is None:
                break
            n = table.pop(oldest)
            table["other"] = table.pop("other", 0) + n
        if len(table) >= self.max_keys:  # max_keys 1: only "other" is left
            key = "other"
        table[key] = table.get(key, 0) + 1

    def latency(self) -> dict[str, float | None]:
        if not self.latencies_ms:
            return {"p50_ms": None, "p95_ms": None}
        a = np.array(self.latencies_ms)
        return {"p50_ms": float(np.percentile(a, 50)), "p95_ms": float(np.percentile(a, 95))}


class FrameCounters:
    """The daemon's counters of frames and events, beside the worker's :class:`Stats`.

    Args:
        stats: the worker's Stats (``processed`` and ``errors`` are the worker's totals).
        intake: the cell's :class:`~service.intake.Intake` (its synchroniser, queue, drops).
        max_cameras: bounds the per-camera tables (cameras forgotten leave them).
    """

    def __init__(self, stats: Stats, intake, max_cameras: int):
        self.stats = stats
        self.intake = intake
        self.max_cameras = max_cameras
        self.events: Counter = Counter()  # the daemon's events (activations, info requests...)
        # frames the front end cannot take (e.g. too small), by reason; logged at most once
        # per camera per minute
        self.unsupported: Counter = Counter()
        self._unsupported_logged: dict[str, float] = {}
        self._per_camera: Counter = Counter()  # (camera id, processed | errors)
        self._started = time.monotonic()

    # ------------------------------------------------------------------ counting
    def processed(self, frame, now_ns: int) -> None:
        """A frame fused (its estimates about to be published); ``now_ns``: the wall clock
        its latency is measured against (the frame's arrival_ns, when it has one)."""
        self._count_frame(frame.camera_id, "processed")
        if frame.arrival_ns:
            self.stats.latencies_ms.append((now_ns - frame.arrival_ns) / 1e6)

    def failed(self, frame) -> None:
        """A frame whose front end or fusion raised: counted, logged with its traceback (call
        from the ``except`` block)."""
        self.stats.errors += 1
        self._count_frame(frame.camera_id, "errors")
        log.exception("frame %d of %s failed", frame.stamp_ns, frame.camera_id)

    def refused(self, frame, exc) -> None:
        """A frame the front end cannot take (UnsupportedImage): counted by reason, one log
        line per camera per minute (a camera sending such frames sends nothing else)."""
        self.unsupported[f"unsupported_image_{exc.reason}"] += 1
        last = self._unsupported_logged.get(frame.camera_id)
        now = time.monotonic()
        if last is None or now - last > 60.0:
            self._unsupported_logged[frame.camera_id] = now
            if len(self._unsupported_logged) > 8 * self.max_cameras:
                self._unsupported_logged.clear()
            log.warning("%s: frames refused: %s", frame.camera_id, exc)

    def _count_frame(self, camera_id: str, what: str) -> None:
        """Per-camera processed / errors; cameras the synchroniser forgot leave the table once
        it holds far more than max_cameras (their counts are in the totals)."""
        self._per_camera[(camera_id, what)] += 1
        if len(self._per_camera) > 8 * self.max_cameras:
            known = set(self.intake.sync.cameras())
            for k in [k for k in self._per_camera if k[0] not in known]:
                del self._per_camera[k]

    # ------------------------------------------------------------------ reading
    def frames_handled(self) -> int:
        """Images received and dealt with: processed, failed or dropped for any reason."""
        s = self.stats
        return (
            s.processed
            + s.errors
            + sum(self.intake.sync.dropped.values())
            + sum(self.unsupported.values())
            + sum(n for k, n in s.decode_reasons.items() if k.startswith("image_"))
            + sum(n for k, n in self.intake.dropped.items() if k.startswith("image_"))
        )

    def stats_dict(
        self,
        cell: str,
        active: bool,
        in_flight: int,
        restored: int,
        objects_needing_views: list[str],
    ) -> dict:
        """The ``/stats`` map. in_flight: frames between the front end and the estimator."""
        s, sync, intake = self.stats, self.intake.sync, self.intake
        dropped = Counter(sync.dropped) + self.unsupported
        for reason, n in s.decode_reasons.items():
            kind, _, code = reason.partition("_")
            if kind == "image":
                dropped[f"decode_{code}"] += n
        for reason, n in intake.dropped.items():
            if reason.startswith("image_"):
                dropped[reason.removeprefix("image_")] += n
        cameras = sync.camera_counters()
        for cid, c in cameras.items():
            c["processed"] = self._per_camera[(cid, "processed")]
            c["errors"] = self._per_camera[(cid, "errors")]
        return {
            "cell": cell,
            "role": "active" if active else "standby",
            "frames_received": intake.images_received,
            "frames_processed": s.processed,
            "frames_handled": self.frames_handled(),
            "frames_dropped": dict(sorted(dropped.items())),
            "frames_pending": sync.pending() + in_flight,
            "queued_bytes": sync.queued_bytes(),
            "ingest_pending": intake.pending(),
            "ingest_pending_bytes": intake.pending_bytes(),
            "received": dict(s.received),
            "decode_errors": dict(s.decode_errors),
            "decode_errors_by_reason": dict(s.decode_reasons),
            "messages_dropped": dict(intake.dropped),
            "processing_errors": s.errors,
            "latency": s.latency(),
            "cameras": cameras,
            "sync_events": dict(sync.events),
            "events": dict(self.events),
            "restored_objects": restored,
            "objects_needing_views": objects_needing_views,
            "uptime_s": time.monotonic() - self._started,
        }
