"""Received messages waiting for a decoder: one lane per camera, one bounded queue per kind in
each lane, the lanes served fairly by the decoding time they cost.

What one camera sends never costs another camera its messages:

- Lanes share the decoders by the CPU time their messages take to decode (start-time fair
  queueing): each lane has a virtual clock advanced by the measured decoding time of each of
  its messages, and the decoders take, among the lanes not being decoded, the one whose next
  message would finish first on its clock (its clock plus that message's expected cost: the
  lane's last one of that kind, or for a lane never seen, the dearest image decoded lately,
  as known when its turn comes). A
  camera of 1280x720 JPEGs is served many times for every 4096x4096 PNG of a flooding camera,
  and a lane that was idle starts again from the current virtual time (no credit banked, no
  debt kept). A lane being decoded by one thread is not served to another, so a camera's
  messages are decoded in the order they came (per kind).
- Within a lane, infos and poses (tiny, and what images wait for) are served before images, and
  are bounded apart from them: an image flood never drops a pose. Each small kind holds at
  most ``small_per_camera`` messages and ``small_bytes_per_camera`` bytes; beyond, its oldest
  message is dropped and counted (``pose_ingest_full``, ``info_ingest_full``).
- Images: at most ``images_per_camera`` per lane (the oldest dropped: the latest frames win),
  and ``max_bytes`` of payloads waiting in all lanes together; beyond, the oldest image of the
  lane holding the most image bytes is dropped, so a flooding camera pays for its own flood.
- The images of a camera that has sent no info yet (``has_info``) are decoded only when no
  camera with its info has an image waiting: they cannot be used before their info comes,
  and a flood from camera ids that never send one costs a working camera nothing.
- All lanes together hold at most ``max_messages``; beyond, the oldest message of the lane
  holding the most messages is dropped.

Every drop is counted in ``dropped`` by ``{kind}_ingest_full``. Thread-safe: the transport's
callbacks :meth:`put`, decoder threads :meth:`get` then :meth:`done` with the decoding time.
"""

from __future__ import annotations

import heapq
import itertools
import threading
from collections import Counter, OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass

KINDS = ("info", "pose", "image")  # the order a lane serves them in
_RECENT_IMAGES = 64  # the expected cost of a new lane's image: the dearest of these


@dataclass(frozen=True)
class IngestConfig:
    images_per_camera: int = 4
    small_per_camera: int = 1024  # infos, and poses, each
    small_bytes_per_camera: int = 1024 * 1024  # infos, and poses, each
    max_bytes: int = 256 * 1024 * 1024  # payloads waiting, all lanes and kinds together
    max_messages: int = 8192
    max_lanes: int = 1024  # lanes remembered (clock, costs); idle ones seen longest ago leave

    def __post_init__(self) -> None:
        for name in self.__dataclass_fields__:
            if getattr(self, name) < 1:
                raise ValueError(f"IngestConfig.{name} must be >= 1, got {getattr(self, name)}")


class _Lane:
    __slots__ = ("queues", "bytes", "busy", "clock", "cost", "version", "serving")

    def __init__(self, clock: float):
        self.queues = {k: deque() for k in KINDS}  # (item, nbytes)
        self.bytes = {k: 0 for k in KINDS}
        self.busy = False
        self.clock = clock  # virtual time: decoding seconds served, from when it joined
        self.cost: dict[str, float] = {}  # the last decoding time of each kind
        self.version = -1  # its live entry in the heap; any other is stale
        self.serving = ""  # the kind being decoded while busy

    def size(self) -> int:
        return sum(len(q) for q in self.queues.values())

    def head(self) -> str | None:
        return next((k for k in KINDS if self.queues[k]), None)

    def pop(self, kind: str):
        item, nbytes = self.queues[kind].popleft()
        self.bytes[kind] -= nbytes
        return item, nbytes


class FairIngest:
    def __init__(
        self,
        config: IngestConfig | None = None,
        dropped: Counter | None = None,
        has_info: Callable[[str], bool] | None = None,
    ):
        self.config = config or IngestConfig()
        self.dropped = Counter() if dropped is None else dropped
        self._has_info = has_info  # None: every camera counts as having its info
        self._cond = threading.Condition()
        self._lanes: OrderedDict[str, _Lane] = OrderedDict()  # least recently seen first
        self._heap: list[tuple[int, float, int, str]] = []  # (rank, finish, version, cam)
        self._versions = itertools.count()  # also the order of ties
        self._now = 0.0  # the system's virtual time: the clock of the last lane served
        self._recent_images: deque[float] = deque(maxlen=_RECENT_IMAGES)
        self._bytes = 0
        self._messages = 0

    # ------------------------------------------------------------------ producers
    def put(self, cam_id: str, kind: str, item, nbytes: int) -> bool:
        """Queue one message of ``kind`` (``info``, ``pose`` or ``image``) of a camera; False
        when it was dropped at once (counted). Dropping older messages to make room for it is
        counted too, and still returns True."""
        c = self.config
        with self._cond:
            small = kind != "image"
            if nbytes > (c.small_bytes_per_camera if small else c.max_bytes):
                self.dropped[f"{kind}_ingest_full"] += 1
                return False
            lane = self._lanes.get(cam_id)
            if lane is None:
                lane = self._lanes[cam_id] = _Lane(self._now)
                self._forget_idle()
            else:
                self._lanes.move_to_end(cam_id)
                if not lane.size() and not lane.busy:
                    lane.clock = max(lane.clock, self._now)  # idle: no credit banked
            q = lane.queues[kind]
            if small:
                while q and (
                    len(q) >= c.small_per_camera
                    or lane.bytes[kind] + nbytes > c.small_bytes_per_camera
                ):
                    self._drop(lane, kind)
            else:
                while len(q) >= c.images_per_camera:
                    self._drop(lane, kind)
                while self._bytes + nbytes > c.max_bytes:
                    victim = max(
                        (v for v in self._lanes.values() if v.queues["image"]),
                        key=lambda v: v.bytes["image"],
                        default=None,
                    )
                    if victim is None:
                        break
                    self._drop(victim, "image")
            while self._messages >= c.max_messages:
                victim = max(self._lanes.values(), key=_Lane.size)
                k = next((k for k in ("image", "pose", "info") if victim.queues[k]), None)
                if k is None:
                    break
                self._drop(victim, k)
            head = lane.head()
            q.append((item, nbytes))
            lane.bytes[kind] += nbytes
            self._bytes += nbytes
            self._messages += 1
            if lane.head() != head:  # a new head (or a lane no longer empty): its turn changes
                self._schedule(cam_id, lane)
            self._cond.notify()
            return True

    def _forget_idle(self) -> None:
        """At most max_lanes lanes: the idle ones seen longest ago leave (a lane with
        messages waiting or being decoded stays, bounded by max_messages)."""
        excess = len(self._lanes) - self.config.max_lanes
        if excess <= 0:
            return
        idle = [c for c, v in self._lanes.items() if not v.busy and not v.size()][:excess]
        for cam_id in idle:
            del self._lanes[cam_id]

    def _drop(self, lane: _Lane, kind: str) -> None:
        _, nbytes = lane.pop(kind)
        self._bytes -= nbytes
        self._messages -= 1
        self.dropped[f"{kind}_ingest_full"] += 1

    def _expected(self, lane: _Lane, kind: str) -> float:
        if kind in lane.cost:
            return lane.cost[kind]
        if kind == "image":  # a lane never seen: as dear as the dearest image of late
            return max(self._recent_images, default=0.0)
        return 0.0

    def _turn(self, cam_id: str, lane: _Lane, kind: str) -> tuple[int, float]:
        """(rank, finish) of the lane's next message: rank 1 for an image of a camera that has
        sent no info yet (it cannot be used before its info comes), 0 otherwise."""
        waits = kind == "image" and self._has_info is not None and not self._has_info(cam_id)
        return int(waits), lane.clock + self._expected(lane, kind)

    def _schedule(self, cam_id: str, lane: _Lane) -> None:
        """(Re)place the lane in the heap by when its next message would finish."""
        lane.version = next(self._versions)
        kind = lane.head()
        if kind is None or lane.busy:
            return
        heapq.heappush(self._heap, (*self._turn(cam_id, lane, kind), lane.version, cam_id))

    # ------------------------------------------------------------------ consumers
    def get(self, timeout: float | None = None):
        """(cam_id, kind, item) of the lane whose turn it is, that lane now busy until
        :meth:`done`; None when nothing could be served within ``timeout`` seconds."""
        with self._cond:
            got = self._next()
            if got is None and timeout:
                self._cond.wait(timeout)
                got = self._next()
            return got

    def get_nowait(self):
        with self._cond:
            return self._next()

    def _next(self):
        while self._heap:
            rank, finish, version, cam_id = heapq.heappop(self._heap)
            lane = self._lanes.get(cam_id)
            if lane is None or version != lane.version or lane.busy:
                continue  # stale entry
            kind = lane.head()
            if kind is None:  # emptied by drops
                continue
            if self._heap and self._turn(cam_id, lane, kind) > self._heap[0][:2]:
                # expected dearer since it was queued (a new lane, once images of late were
                # found dear), or its camera's info came meanwhile: it waits for the lanes
                # that would now finish first
                self._schedule(cam_id, lane)
                continue
            item, nbytes = lane.pop(kind)
            self._bytes -= nbytes
            self._messages -= 1
            self._now = max(self._now, lane.clock)
            lane.busy = True
            lane.serving = kind
            lane.version = -1
            return cam_id, kind, item
        return None

    def done(self, cam_id: str, seconds: float = 0.0) -> None:
        """The message :meth:`get` gave of this camera is dealt with, in ``seconds`` of
        decoding time: its lane's clock advances by them and it may be served again."""
        with self._cond:
            lane = self._lanes.get(cam_id)
            if lane is None or not lane.busy:
                return
            seconds = max(0.0, float(seconds))
            lane.busy = False
            lane.clock += seconds
            lane.cost[lane.serving] = seconds
            if lane.serving == "image":
                self._recent_images.append(seconds)
            if lane.size():
                self._schedule(cam_id, lane)
                self._cond.notify()

    # ------------------------------------------------------------------ introspection
    def pending(self) -> int:
        with self._cond:
            return self._messages

    def pending_bytes(self) -> int:
        with self._cond:
            return self._bytes
