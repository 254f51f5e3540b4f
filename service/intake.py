"""The one way in for camera messages, live and replayed: ingest -> decode -> sync.

- :meth:`Intake.receive` (native keys) and :meth:`Intake.receive_ros2` (ROS 2 camera topics)
  only check the key and the payload size, count the message and queue its bytes, as a
  :class:`Received`, in the camera's lane of :class:`~service.ingest.FairIngest`: bounded per
  camera and kind, served in turn, infos and poses before images; what a full queue drops is
  counted. Nothing is decoded there: the transport's callbacks call them.
- :meth:`Intake.decode_next` (the daemon's decoder threads) and :meth:`Intake.drain` (replay,
  tests) take what the queue serves, decode it (:mod:`service.codec`, which checks image sizes
  on the stream's header before decoding; a ROS 2 message becomes the native one first,
  :mod:`service.ros2`) and give the message to the :class:`~service.sync.FrameSynchronizer`.
  A bad message is counted by key and by reason, and logged, never raised.
- :meth:`Intake.pop` hands out the next synchronised frame.

The live daemon (:mod:`service.daemon`) receives with the wall clock as arrival time and decodes
in its threads; offline replay (:mod:`service.replay`) receives with each message's log time,
then drains and pops in its own thread, in log-time order: the same code, so replay gives what
the daemon would have, bit for bit. A message is bytes, then a :class:`Received` while it
waits, then a decoded message, then part of a :class:`~service.sync.SyncedFrame`.
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass

from posefuse.service.codec import DecodeError, decoders
from posefuse.service.ingest import FairIngest, IngestConfig
from posefuse.service.keys import Keys
from posefuse.service.sync import FrameSynchronizer, SyncedFrame

log = logging.getLogger("posefuse.daemon.intake")


@dataclass(frozen=True, eq=False)
class Received:
    """One camera message as it arrived, waiting for a decoder.

    kind: ``info``, ``pose`` or ``image``; ros_type: the ROS 2 message type when it came on a
    ROS 2 topic, else ``""``; arrival_ns: the receiver's clock (wall clock live, log time in
    replay), ns.
    """

    key: str
    camera_id: str
    kind: str
    payload: bytes
    arrival_ns: int
    ros_type: str = ""


class Intake:
    """Camera messages of one cell from bytes to synchronised frames.

    Args:
        keys: the cell's key space.
        sync: the synchroniser the decoded messages go to.
        stats: the worker's :class:`~service.stats.Stats`; ``received``, ``decode_errors`` and
            ``decode_reasons`` are counted in it.
        max_payload_bytes, max_image_pixels: the limits checked before decoding.
        ingest: the queue's bounds (None: the defaults).
        ros2: the ROS 2 key layout (:class:`~service.ros2.Ros2Layout`), or None.
        on_image_without_info: called with the camera id of an image whose camera has sent no
            info yet (the daemon asks the camera for it).
        on_decoded: called after each message given to the synchroniser (wakes the front end).
        clock: the arrival clock now (ns), read when an image reaches the synchroniser: its wait
            for a pose counts from then, not from its arrival. None (replay): the arrival time,
            where decoding takes no time on the log's clock.
    """

    def __init__(
        self,
        keys: Keys,
        sync: FrameSynchronizer,
        stats,
        max_payload_bytes: int,
        max_image_pixels: int,
        ingest: IngestConfig | None = None,
        ros2=None,
        on_image_without_info: Callable[[str], None] | None = None,
        on_decoded: Callable[[], None] | None = None,
        clock: Callable[[], int] | None = None,
    ):
        self.keys = keys
        self.sync = sync
        self.stats = stats
        self.max_payload_bytes = max_payload_bytes
        self.decode = decoders(max_payload_bytes, max_image_pixels)
        self.ros2 = ros2
        self.on_image_without_info = on_image_without_info
        self.on_decoded = on_decoded
        self.clock = clock
        self.dropped: Counter = Counter()  # messages dropped before decoding, by reason
        self.queue = FairIngest(ingest, dropped=self.dropped, has_info=sync.has_info)
        self.images_received = 0

    # ------------------------------------------------------------------ receiving
    def receive(self, key: str, payload: bytes, arrival_ns: int) -> bool:
        """Queue one received message for its decoder; False when it was dropped (counted)."""
        parsed = self.keys.parse_camera(key)
        if parsed is None:
            self.stats.count(self.stats.received, "other")
            self.dropped["not_an_input_key"] += 1
            return False
        cam_id, kind = parsed
        self.stats.count(self.stats.received, key)
        return self._queue(Received(key, cam_id, kind, payload, arrival_ns))

    def receive_ros2(self, key: str, payload: bytes, arrival_ns: int) -> bool:
        """A ROS 2 camera message (CDR) for its decoder; False when dropped (counted)."""
        parsed = self.ros2.parse_input(key, self.keys.cell) if self.ros2 else None
        if parsed is None:
            self.stats.count(self.stats.received, "other")
            self.dropped["not_an_input_key"] += 1
            return False
        cam_id, ros_type, kind = parsed
        self.stats.count(self.stats.received, key)
        return self._queue(Received(key, cam_id, kind, payload, arrival_ns, ros_type))

    def _queue(self, msg: Received) -> bool:
        if msg.kind == "image":
            self.images_received += 1
        if len(msg.payload) > self.max_payload_bytes:
            self._decode_failed(msg.key, msg.kind, "too_large")
            return False
        return self.queue.put(msg.camera_id, msg.kind, msg, len(msg.payload))

    def _decode_failed(self, key: str, kind: str, code: str) -> None:
        self.stats.count(self.stats.decode_errors, key)
        self.stats.count(self.stats.decode_reasons, f"{kind}_{code}")

    # ------------------------------------------------------------------ decoding
    def decode_next(self, timeout: float) -> None:
        """Decode the message whose turn it is, waiting at most ``timeout`` seconds for one (a
        decoder thread's loop)."""
        got = self.queue.get(timeout=timeout)
        if got is not None:
            self._decode_served(got[2])

    def drain(self) -> int:
        """Decode every queued message in this thread (replay, tests); how many reached the
        synchroniser (bad ones are counted, not given to it)."""
        n = 0
        while (got := self.queue.get_nowait()) is not None:
            n += self._decode_served(got[2])
        return n

    def _decode_served(self, msg: Received) -> bool:
        """Decode one message the queue served; its lane is charged the CPU time."""
        t0 = time.thread_time()
        try:
            return self._decode(msg)
        finally:
            self.queue.done(msg.camera_id, time.thread_time() - t0)

    def _decode(self, msg: Received) -> bool:
        """Decode one message and give it to the synchroniser (True); count it if it is bad
        (False)."""
        key, cam_id, kind = msg.key, msg.camera_id, msg.kind
        try:
            payload = msg.payload
            if msg.ros_type:  # a ROS 2 message: as the native one, then the native checks
                from posefuse.service.ros2 import to_native

                payload = to_native(msg.ros_type, payload, cam_id)
            decoded = self.decode[kind](payload)
        except DecodeError as exc:
            self._decode_failed(key, kind, exc.code)
            log.warning("%s: %s", key, exc)
            return False
        except Exception:
            self._decode_failed(key, kind, "unexpected")
            log.exception("%s: unexpected error while decoding", key)
            return False
        if kind == "info":
            self.sync.add_info(cam_id, decoded, msg.arrival_ns)
        elif kind == "pose":
            self.sync.add_pose(cam_id, decoded, msg.arrival_ns)
        else:
            now = msg.arrival_ns if self.clock is None else self.clock()
            self.sync.add_image(cam_id, decoded, now, msg.arrival_ns)
            if self.on_image_without_info is not None and not self.sync.has_info(cam_id):
                self.on_image_without_info(cam_id)
        if self.on_decoded is not None:
            self.on_decoded()
        return True

    # ------------------------------------------------------------------ output
    def pop(self, now_ns: int) -> SyncedFrame | None:
        """The oldest frame ready at ``now_ns`` (the arrival clock), or None."""
        return self.sync.pop(now_ns)

    def pending(self) -> int:
        """Messages queued for decoding."""
        return self.queue.pending()

    def pending_bytes(self) -> int:
        return self.queue.pending_bytes()
