"""The estimator daemon on Zenoh: decode and enqueue in callbacks, estimate in one worker thread.

- Subscribers on ``{cell}/@v1/cam/*/*`` decode each message (:mod:`service.codec`) and hand it
  to the :class:`~service.sync.FrameSynchronizer`; a bad message is counted per key and logged,
  never raised.
- One worker thread takes frames in stamp order, runs :class:`~service.worker.EstimatorWorker`
  and publishes every updated ObjectEstimate on ``{cell}/@v1/objects/{object_id}``.
- Queryables answer ``estimator/state`` (all current estimates) and ``estimator/reset``; a
  liveliness token ``estimator/alive`` says the daemon is up.
"""

from __future__ import annotations

import logging
import queue
import threading
import time

from service.codec import (
    DecodeError,
    decode_camera_info,
    decode_camera_pose,
    decode_image,
    decode_reset,
    encode_estimate,
    encode_estimates,
    estimate_to_dict,
)
from service.keys import Keys
from service.settings import Settings, zenoh_config
from service.sync import FrameSynchronizer
from service.worker import EstimatorWorker, now_ns

log = logging.getLogger("posefuse.daemon")

DECODERS = {"info": decode_camera_info, "image": decode_image, "pose": decode_camera_pose}


class Daemon:
    def __init__(self, settings: Settings, worker: EstimatorWorker):
        self.settings = settings
        self.worker = worker
        self.keys = Keys(settings.cell)
        self.sync = FrameSynchronizer(
            image_queue=settings.image_queue,
            pose_buffer=settings.pose_buffer,
            max_pose_gap_ns=settings.max_pose_gap_ns,
            pose_wait_ns=settings.pose_wait_ns,
        )
        self.stats = worker.stats
        self._arrival: dict[int, int] = {}
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._listeners: list[queue.Queue] = []
        self._listeners_lock = threading.Lock()
        self.ready = threading.Event()
        self.session = None

    # ------------------------------------------------------------------ transport callbacks
    def on_sample(self, sample) -> None:
        key = str(sample.key_expr)
        try:
            self.stats.count(self.stats.received, key)
            parsed = self.keys.parse_camera(key)
            if parsed is None:
                raise DecodeError("key", f"{key} is not a camera input key")
            cam_id, kind = parsed
            payload = sample.payload.to_bytes()
            msg = DECODERS[kind](payload, self.settings.max_payload_bytes)
            if kind == "info":
                self.sync.add_info(cam_id, msg)
            elif kind == "pose":
                self.sync.add_pose(cam_id, msg)
            else:
                self._arrival[msg.stamp_ns] = now_ns()
                if len(self._arrival) > 1000:
                    for k in sorted(self._arrival)[:500]:
                        self._arrival.pop(k, None)
                self.sync.add_image(cam_id, msg)
            self._wake.set()
        except DecodeError as exc:
            self.stats.count(self.stats.decode_errors, key)
            log.warning("%s: %s", key, exc)
        except Exception:  # a daemon never dies of a message
            self.stats.count(self.stats.decode_errors, key)
            log.exception("%s: unexpected error while decoding", key)

    def on_state_query(self, query) -> None:
        try:
            query.reply(self.keys.state, encode_estimates(self.worker.snapshot()))
        except Exception:
            log.exception("state query failed")

    def on_reset_query(self, query) -> None:
        import msgpack

        try:
            payload = query.payload.to_bytes() if query.payload is not None else b""
            request = decode_reset(payload)
            removed = self.reset(request.class_id, request.object_id)
            reply = {"v": 1, "removed": removed}
        except (DecodeError, ValueError) as exc:
            reply = {"v": 1, "error": str(exc)}
        except KeyError as exc:
            reply = {"v": 1, "error": f"unknown object_id {exc.args[0]}"}
        try:
            query.reply(self.keys.reset, msgpack.packb(reply, use_bin_type=True))
        except Exception:
            log.exception("reset reply failed")

    # ------------------------------------------------------------------ listeners (SSE)
    def subscribe(self, maxsize: int = 256) -> queue.Queue:
        q: queue.Queue = queue.Queue(maxsize)
        with self._listeners_lock:
            self._listeners.append(q)
        return q

    def unsubscribe(self, q: queue.Queue) -> None:
        with self._listeners_lock:
            if q in self._listeners:
                self._listeners.remove(q)

    def _notify(self, item: dict) -> None:
        with self._listeners_lock:
            for q in self._listeners:
                try:
                    q.put_nowait(item)
                except queue.Full:
                    pass  # a slow reader misses updates rather than stalling the worker

    # ------------------------------------------------------------------ worker
    def _work(self, session) -> None:
        while not self._stop.is_set():
            frame = self.sync.pop()
            if frame is None:
                self._wake.wait(0.01)
                self._wake.clear()
                continue
            try:
                updated = self.worker.process(frame)
            except Exception:
                self.stats.errors += 1
                log.exception("frame %d of %s failed", frame.stamp_ns, frame.camera_id)
                continue
            arrival = self._arrival.pop(frame.stamp_ns, None)
            if arrival is not None:
                self.stats.latencies_ms.append((now_ns() - arrival) / 1e6)
            for e in updated:
                session.put(self.keys.object(e.object_id), encode_estimate(e))
                self._notify(estimate_to_dict(e))

    def reset(self, class_id=None, object_id=None) -> int:
        n = self.worker.reset(class_id, object_id)
        self._notify(
            {"v": 1, "reset": {"class_id": class_id, "object_id": object_id, "removed": n}}
        )
        return n

    def run(self) -> None:
        """Open the session, serve until :meth:`stop`."""
        import zenoh

        with zenoh.open(zenoh_config(self.settings)) as session:
            self.session = session
            subscriber = session.declare_subscriber(self.keys.camera_inputs, self.on_sample)
            state = session.declare_queryable(self.keys.state, self.on_state_query)
            reset = session.declare_queryable(self.keys.reset, self.on_reset_query)
            token = session.liveliness().declare_token(self.keys.alive)
            worker = threading.Thread(
                target=self._work, args=(session,), daemon=True, name="posefuse-worker"
            )
            worker.start()
            self.ready.set()
            try:
                while not self._stop.wait(0.2):
                    pass
            finally:
                worker.join(timeout=5)
                for entity in (token, reset, state, subscriber):
                    entity.undeclare()
                self.session = None

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()

    def stats_dict(self) -> dict:
        s = self.stats
        return {
            "frames_received": sum(v for k, v in s.received.items() if k.endswith("/image")),
            "frames_processed": s.processed,
            "frames_dropped": dict(self.sync.dropped),
            "frames_pending": self.sync.pending(),
            "received": dict(s.received),
            "decode_errors": dict(s.decode_errors),
            "processing_errors": s.errors,
            "latency": s.latency(),
            "cameras": self.sync.cameras(),
            "uptime_s": time.monotonic() - _START,
        }


_START = time.monotonic()
