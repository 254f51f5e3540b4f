"""Estimates out: every updated ObjectEstimate on ``{cell}/@v1/objects/{object_id}``, with a
ROS 2 layout also as a Detection3DArray and a TFMessage (:mod:`service.ros2`), and to every
event subscriber (the HTTP API's ``/events`` stream).

A failed put is logged, never raised; a slow event subscriber misses updates rather than
stalling the estimator.
"""

from __future__ import annotations

import hashlib
import logging
import queue
import threading

from posefuse.service.codec import encode_estimate, estimate_to_dict
from posefuse.service.keys import Keys

log = logging.getLogger("posefuse.daemon.publishing")


class Publisher:
    """The cell's outputs.

    Args:
        keys: the cell's key space.
        ros2: the ROS 2 key layout (:class:`~service.ros2.Ros2Layout`), or None.
        catalog: the estimator's object models by class id; their bounding boxes (metres) are
            the ROS 2 detections' sizes.
    """

    def __init__(self, keys: Keys, ros2=None, catalog=None):
        self.keys = keys
        self.ros2 = ros2
        self._listeners: list[queue.Queue] = []
        self._listeners_lock = threading.Lock()
        self._box_sizes = {}
        if ros2 is not None:
            models = catalog or {}
            self._box_sizes = {k: m.points.max(0) - m.points.min(0) for k, m in models.items()}
        self._gid = b""  # the ROS 2 publisher gid of the attachments

    def identify(self, session) -> None:
        """Take the ROS 2 publisher gid of this session and cell (when producing)."""
        self._gid = hashlib.sha256(f"{session.zid()}/{self.keys.root}".encode()).digest()

    # ------------------------------------------------------------------ event subscribers
    def subscribe(self, maxsize: int = 256) -> queue.Queue:
        q: queue.Queue = queue.Queue(maxsize)
        with self._listeners_lock:
            self._listeners.append(q)
        return q

    def unsubscribe(self, q: queue.Queue) -> None:
        with self._listeners_lock:
            if q in self._listeners:
                self._listeners.remove(q)

    def notify(self, item: dict) -> None:
        with self._listeners_lock:
            for q in self._listeners:
                try:
                    q.put_nowait(item)
                except queue.Full:
                    pass  # a slow reader misses updates rather than stalling the worker

    # ------------------------------------------------------------------ estimates
    def publish(self, session, stamp_ns: int, updated) -> None:
        """The estimates one frame (stamped ``stamp_ns``) updated, on every output."""
        for e in updated:
            try:
                session.put(self.keys.object(e.object_id), encode_estimate(e))
            except Exception:
                log.exception("publishing %s failed", e.object_id)
            self.notify(estimate_to_dict(e))
        if self.ros2 is not None and updated:
            self._publish_ros2(session, stamp_ns, updated)

    def _publish_ros2(self, session, stamp_ns: int, updated) -> None:
        """The updated estimates as a Detection3DArray and a TFMessage (service/ros2.py)."""
        from posefuse.service.ros2 import DETECTIONS, TF, encode_detections, encode_tf

        cell = self.keys.cell
        try:
            out = (
                (
                    f"/posefuse/{cell}/detections",
                    DETECTIONS,
                    encode_detections(updated, cell, self._box_sizes, stamp_ns),
                ),
                ("/tf", TF, encode_tf(updated, cell)),
            )
            for topic, msgtype, data in out:
                attachment = self.ros2.attachment(topic, stamp_ns, self._gid)
                session.put(self.ros2.key(topic, msgtype), data, attachment=attachment)
        except Exception:
            log.exception("publishing the ROS 2 messages failed")
