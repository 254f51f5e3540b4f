"""The estimator daemon on Zenoh: enqueue in callbacks, decode in a small pool, estimate in one
worker thread.

- The subscriber on ``{cell}/@v1/cam/*/*`` only checks the key and the payload size and queues
  the bytes in the camera's lane of :class:`~service.ingest.FairIngest`: bounded per camera and
  kind, served to the decoder threads in turn, infos and poses before images, so one camera's
  flood costs another camera nothing; what a full queue drops is counted. Nothing is decoded on
  the transport's threads.
- Decoders turn bytes into messages (:mod:`service.codec`; image sizes checked on the stream's
  header before decoding) and give them to the :class:`~service.sync.FrameSynchronizer`. A bad
  message is counted by key and by reason, and logged, never raised.
- A camera whose images come without camera info is asked for it: a get on its info key
  (``clients/camera.py`` answers it), at most every ``info_request_s``; at start, every camera.
- A two-stage pipeline keeps both cores busy: the front-end thread takes synchronised frames
  and runs the network and voting (:meth:`~service.worker.EstimatorWorker.detections`) while
  the worker thread fuses the previous frame (:meth:`~service.worker.EstimatorWorker.fuse`)
  and publishes every updated ObjectEstimate on ``{cell}/@v1/objects/{object_id}``. One
  thread per stage and a one-frame queue between them: frames reach the estimator in the
  order they left the synchroniser, so the estimates do not depend on timing.
- Queryables answer ``estimator/state`` and ``estimator/reset`` (with ``api_token`` set, a
  reset needs the token as the query's attachment); a liveliness token ``estimator/alive``
  says the daemon is up.
- With a ``state_dir``, the tracks are snapshotted every ``state_interval_s`` and at a clean
  stop (after the frame in flight is fused), and restored at start (:mod:`service.state`).
- Several daemons may serve one cell: liveliness tokens elect the one that produces its
  estimates (:mod:`service.election`); the others stand by with nothing subscribed and take
  over from the last snapshot when it disappears. :meth:`Daemon.serve` runs a cell on an open
  session, so one process serves several cells (:mod:`service.cells`).
"""

from __future__ import annotations

import hmac
import logging
import queue
import threading
import time
from collections import Counter

import numpy as np

from posefuse.estimator.frontend.network import UnsupportedImage
from posefuse.service.codec import (
    DecodeError,
    NbvRequest,
    decode_nbv_request,
    decode_reset,
    decoders,
    encode_estimate,
    encode_estimates,
    estimate_to_dict,
    nbv_reply,
)
from posefuse.service.ingest import FairIngest
from posefuse.service.keys import Keys
from posefuse.service.settings import Settings, ingest_config, sync_config, zenoh_config
from posefuse.service.sync import FrameSynchronizer
from posefuse.service.worker import EstimatorWorker, now_ns

log = logging.getLogger("posefuse.daemon")


class Daemon:
    def __init__(self, settings: Settings, worker: EstimatorWorker, state_store=None):
        self.settings = settings
        self.worker = worker
        self.keys = Keys(settings.cell)
        self.sync = FrameSynchronizer(sync_config(settings))
        self.stats = worker.stats
        self.stats.max_keys = 3 * settings.max_cameras + 8
        self.decode = decoders(settings.max_payload_bytes, settings.max_image_pixels)
        self.ingest_dropped: Counter = Counter()
        self.images_received = 0
        self._per_camera: Counter = Counter()  # (camera id, processed | errors)
        # frames the front end cannot take (e.g. too small), by reason; logged at most once
        # per camera per minute
        self.unsupported: Counter = Counter()
        self._unsupported_logged: dict[str, float] = {}
        self.events: Counter = Counter()
        self.ingest_queue = FairIngest(ingest_config(settings), dropped=self.ingest_dropped)
        self._info_asked: dict[str, float] = {}
        self._fused: queue.Queue = queue.Queue(maxsize=1)  # front end -> estimator
        self._front_done = threading.Event()  # the front end has handed over its last frame
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._listeners: list[queue.Queue] = []
        self._listeners_lock = threading.Lock()
        self.ready = threading.Event()
        self.session = None
        self.state_store = state_store
        self.snapshot_info = None
        self.restored = 0
        self._started = time.monotonic()
        self.active = False  # the election made this daemon the cell's producer
        self.election = None
        self._entities: list = []
        self._threads: list[threading.Thread] = []
        self._role_lock = threading.Lock()
        self.ros2 = None  # the ROS 2 key layout when settings.ros2 is not off
        if settings.ros2 != "off":
            from posefuse.service.ros2 import Ros2Layout

            self.ros2 = Ros2Layout(settings.ros2, settings.ros2_domain_id)
            models = getattr(getattr(worker, "estimator", None), "catalog", {}) or {}
            self._box_sizes = {k: m.points.max(0) - m.points.min(0) for k, m in models.items()}
            self._gid = b""

    # ------------------------------------------------------------------ transport callbacks
    def on_sample(self, sample) -> None:
        """Subscriber callback: check the key and the size, enqueue; never decode here."""
        try:
            self.ingest(str(sample.key_expr), sample.payload.to_bytes())
        except Exception:  # a daemon never dies of a message
            log.exception("unexpected error while receiving")

    def ingest(self, key: str, payload: bytes) -> bool:
        """Hand one received message to its decoder; False when it was dropped (counted)."""
        parsed = self.keys.parse_camera(key)
        if parsed is None:
            self.stats.count(self.stats.received, "other")
            self.ingest_dropped["not_an_input_key"] += 1
            return False
        self.stats.count(self.stats.received, key)
        if parsed[1] == "image":
            self.images_received += 1
        if len(payload) > self.settings.max_payload_bytes:
            self._decode_failed(key, parsed[1], "too_large")
            return False
        cam_id, kind = parsed
        item = (key, kind, payload, now_ns())
        return self.ingest_queue.put(cam_id, kind, item, len(payload))

    def on_ros2_sample(self, sample) -> None:
        """Subscriber callback of the ROS 2 camera topics: check, enqueue; never decode here."""
        try:
            self.ingest_ros2(str(sample.key_expr), sample.payload.to_bytes())
        except Exception:
            log.exception("unexpected error while receiving")

    def ingest_ros2(self, key: str, payload: bytes) -> bool:
        """A ROS 2 camera message (CDR) to its decoder; False when dropped (counted)."""
        parsed = self.ros2.parse_input(key, self.settings.cell) if self.ros2 else None
        if parsed is None:
            self.stats.count(self.stats.received, "other")
            self.ingest_dropped["not_an_input_key"] += 1
            return False
        cam_id, msgtype, kind = parsed
        self.stats.count(self.stats.received, key)
        if kind == "image":
            self.images_received += 1
        if len(payload) > self.settings.max_payload_bytes:
            self._decode_failed(key, kind, "too_large")
            return False
        item = (key, f"{kind}:{msgtype}", payload, now_ns())
        return self.ingest_queue.put(cam_id, kind, item, len(payload))

    def _decode_failed(self, key: str, kind: str, code: str) -> None:
        self.stats.count(self.stats.decode_errors, key)
        self.stats.count(self.stats.decode_reasons, f"{kind}_{code}")

    def _decode_loop(self) -> None:
        while not self._stop.is_set():
            got = self.ingest_queue.get(timeout=0.2)
            if got is not None:
                self._decode_one(got)

    def _decode_one(self, got) -> None:
        """Decode one message the ingest queue served; its lane is charged the CPU time."""
        cam_id, _, (key, kind, payload, arrival) = got
        t0 = time.thread_time()
        try:
            self._handle(key, cam_id, kind, payload, arrival)
        finally:
            self.ingest_queue.done(cam_id, time.thread_time() - t0)

    def drain(self) -> int:
        """Decode every queued message in this thread (tests and tools without :meth:`run`)."""
        n = 0
        while (got := self.ingest_queue.get_nowait()) is not None:
            self._decode_one(got)
            n += 1
        return n

    def _handle(self, key: str, cam_id: str, kind: str, payload: bytes, arrival: int) -> None:
        """Decode one message and give it to the synchroniser; count it if it is bad."""
        kind, _, ros_type = kind.partition(":")
        try:
            if ros_type:  # a ROS 2 message: as the native one, then the native checks
                from posefuse.service.ros2 import to_native

                payload = to_native(ros_type, payload, cam_id)
            msg = self.decode[kind](payload)
        except DecodeError as exc:
            self._decode_failed(key, kind, exc.code)
            log.warning("%s: %s", key, exc)
            return
        except Exception:
            self._decode_failed(key, kind, "unexpected")
            log.exception("%s: unexpected error while decoding", key)
            return
        if kind == "info":
            self.sync.add_info(cam_id, msg, arrival)
        elif kind == "pose":
            self.sync.add_pose(cam_id, msg, arrival)
        else:
            self.sync.add_image(cam_id, msg, arrival)
            if not self.sync.has_info(cam_id):
                self.request_info(cam_id)
        self._wake.set()

    def request_info(self, cam_id: str) -> None:
        """Ask a camera for its info (a get on its info key), at most every info_request_s."""
        session = self.session
        now = time.monotonic()
        if session is None or now - self._info_asked.get(cam_id, -1e9) < (
            self.settings.info_request_s
        ):
            return
        if len(self._info_asked) > 4 * self.settings.max_cameras:
            self._info_asked.clear()
        self._info_asked[cam_id] = now
        self.events["info_requests"] += 1
        try:
            session.get(self.keys.camera(cam_id, "info"), self._on_info_reply, timeout=2.0)
        except Exception:
            log.exception("camera info request for %s failed", cam_id)

    def _on_info_reply(self, reply) -> None:
        try:
            ok = reply.ok
            if ok is not None:
                self.events["info_replies"] += 1
                self.ingest(str(ok.key_expr), ok.payload.to_bytes())
        except Exception:
            log.exception("camera info reply")

    def on_state_query(self, query) -> None:
        try:
            query.reply(self.keys.state, encode_estimates(self.worker.snapshot()))
        except Exception:
            log.exception("state query failed")

    def authorized(self, token: bytes | str | None) -> bool:
        """True when no api_token is set or ``token`` is it (compared in constant time)."""
        expected = self.settings.api_token
        if expected is None:
            return True
        if token is None:
            return False
        if isinstance(token, str):
            token = token.encode()
        return hmac.compare_digest(token, expected.get_secret_value().encode())

    def on_reset_query(self, query) -> None:

        try:
            attachment = query.attachment.to_bytes() if query.attachment is not None else None
            if not self.authorized(attachment):
                self.events["reset_unauthorized"] += 1
                reply = {"v": 1, "error": "unauthorized: the reset query needs the API token"}
            else:
                payload = query.payload.to_bytes() if query.payload is not None else b""
                request = decode_reset(payload)
                removed = self.reset(request.class_id, request.object_id)
                reply = {"v": 1, "removed": removed}
        except (DecodeError, ValueError) as exc:
            reply = {"v": 1, "error": str(exc)}
        except KeyError as exc:
            reply = {"v": 1, "error": f"unknown object_id {exc.args[0]}"}
        except Exception:
            log.exception("reset query failed")
            reply = {"v": 1, "error": "internal error"}
        self._reply(query, self.keys.reset, reply)

    @staticmethod
    def _reply(query, key: str, reply: dict) -> None:
        """Answer a queryable with a msgpack map; a failed reply is logged, never raised."""
        import msgpack

        try:
            query.reply(key, msgpack.packb(reply, use_bin_type=True))
        except Exception:
            log.exception("reply on %s failed", key)

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
    def _front_end(self) -> None:
        """Stage 1: synchronised frames through the network; hands them to the estimator. At
        stop, the frame in the network is still handed over (the estimator fuses it)."""
        try:
            while not self._stop.is_set():
                frame = self.sync.pop(now_ns())
                if frame is None:
                    self._wake.wait(0.01)
                    self._wake.clear()
                    continue
                try:
                    detections = self.worker.detections(frame)
                except UnsupportedImage as exc:
                    self._unsupported(frame, exc)
                    continue
                except Exception:
                    self._failed(frame)
                    continue
                while True:  # the estimator drains this queue until the front end is done
                    try:
                        self._fused.put((frame, detections), timeout=0.2)
                        break
                    except queue.Full:
                        continue
        finally:
            self._front_done.set()

    def _work(self, session) -> None:
        """Stage 2: the estimator's update, then publish. At stop, the frames the front end
        still hands over are fused before the thread ends (then the snapshot is written)."""
        while not (self._stop.is_set() and self._front_done.is_set() and self._fused.empty()):
            try:
                frame, detections = self._fused.get(timeout=0.2)
            except queue.Empty:
                if self._stop.is_set() and not self._front_alive():
                    break  # a front end that never started (tests) has nothing to hand over
                continue
            try:
                updated = self.worker.fuse(frame, detections)
            except Exception:
                self._failed(frame)
                continue
            self._publish(session, frame, updated)

    def _front_alive(self) -> bool:
        return any(t.name == "posefuse-front" and t.is_alive() for t in self._threads)

    def _failed(self, frame) -> None:
        self.stats.errors += 1
        self._count_frame(frame.camera_id, "errors")
        log.exception("frame %d of %s failed", frame.stamp_ns, frame.camera_id)

    def _unsupported(self, frame, exc: UnsupportedImage) -> None:
        """A frame the front end cannot take: counted by reason, one log line per camera per
        minute (a camera sending such frames sends nothing else)."""
        self.unsupported[f"unsupported_image_{exc.reason}"] += 1
        last = self._unsupported_logged.get(frame.camera_id)
        now = time.monotonic()
        if last is None or now - last > 60.0:
            self._unsupported_logged[frame.camera_id] = now
            if len(self._unsupported_logged) > 8 * self.settings.max_cameras:
                self._unsupported_logged.clear()
            log.warning("%s: frames refused: %s", frame.camera_id, exc)

    def _count_frame(self, camera_id: str, what: str) -> None:
        """Per-camera processed / errors; cameras the synchroniser forgot leave the table once
        it holds far more than max_cameras (their counts are in the totals)."""
        self._per_camera[(camera_id, what)] += 1
        if len(self._per_camera) > 8 * self.settings.max_cameras:
            known = set(self.sync.cameras())
            for k in [k for k in self._per_camera if k[0] not in known]:
                del self._per_camera[k]

    def _publish(self, session, frame, updated) -> None:
        self._count_frame(frame.camera_id, "processed")
        if frame.arrival_ns:
            self.stats.latencies_ms.append((now_ns() - frame.arrival_ns) / 1e6)
        for e in updated:
            try:
                session.put(self.keys.object(e.object_id), encode_estimate(e))
            except Exception:
                log.exception("publishing %s failed", e.object_id)
            self._notify(estimate_to_dict(e))
        if self.ros2 is not None and updated:
            self._publish_ros2(session, frame.stamp_ns, updated)

    def _publish_ros2(self, session, stamp_ns: int, updated) -> None:
        """The updated estimates as a Detection3DArray and a TFMessage (service/ros2.py)."""
        from posefuse.service.ros2 import DETECTIONS, TF, encode_detections, encode_tf

        cell = self.settings.cell
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

    def nbv(self, request: NbvRequest) -> dict:
        """Rank candidate views (the request's, or the default hemisphere over the bin) by
        what they would teach the estimator (estimator/nbv.py). ValueError when a candidate
        has no intrinsics and no camera info is known to give them."""
        from posefuse.estimator.nbv import (
            BinRegion,
            CandidateView,
            default_candidates,
            score_candidates,
        )

        s = self.settings
        T_world_bin = np.eye(4)
        T_world_bin[:3, 3] = s.nbv_bin_center
        region = BinRegion(tuple(s.nbv_bin_size), s.nbv_bin_wall_height, T_world_bin)
        camera = self.sync.camera(request.camera_id)
        needs_camera = request.candidates is None or any(
            c.camera is None for c in request.candidates
        )
        if needs_camera and camera is None:
            which = f"camera {request.camera_id!r}" if request.camera_id else "any camera"
            raise ValueError(
                f"no camera info of {which} yet: give K, width and height with each candidate"
            )
        if request.candidates is None:
            candidates = default_candidates(camera, region, tuple(s.nbv_distances))
        else:
            candidates = [
                CandidateView(c.T_world_cam, c.camera or camera) for c in request.candidates
            ]
        tracks, indices = self.worker.nbv_inputs()
        scores = score_candidates(tracks, candidates, indices, bin_region=region)
        return nbv_reply(scores, candidates, tracks, request.top_k)

    def objects_needing_views(self) -> list[str]:
        from posefuse.estimator.nbv import needs_view

        tracks = self.worker.nbv_tracks()
        return [t.key for t in tracks if not t.key.startswith("held/") and needs_view(t)]

    def on_nbv_query(self, query) -> None:

        try:
            payload = query.payload.to_bytes() if query.payload is not None else b""
            reply = {"v": 1, **self.nbv(decode_nbv_request(payload))}
        except (DecodeError, ValueError) as exc:
            reply = {"v": 1, "error": str(exc)}
        except Exception:
            log.exception("nbv query failed")
            reply = {"v": 1, "error": "internal error"}
        self._reply(query, self.keys.nbv, reply)

    def reset(self, class_id=None, object_id=None) -> int:
        n = self.worker.reset(class_id, object_id)
        self._notify(
            {"v": 1, "reset": {"class_id": class_id, "object_id": object_id, "removed": n}}
        )
        return n

    # ------------------------------------------------------------------ state on disk
    def restore_state(self) -> int:
        """Restore the tracks of the state folder's snapshot; how many objects came back."""
        if self.state_store is None:
            return 0
        from posefuse.service.state import StateError

        try:
            state = self.state_store.load()
        except StateError as exc:
            log.warning("%s", exc)
            self.events["state_rejected"] += 1
            return 0
        if state is None:
            return 0
        try:
            self.worker.import_state(state)
        except (ValueError, KeyError, TypeError) as exc:
            log.warning("%s: not restored (%s)", self.state_store.path, exc)
            self.events["state_rejected"] += 1
            return 0
        self.restored = len(self.worker.snapshot())
        log.info("restored %d objects from %s", self.restored, self.state_store.path)
        return self.restored

    def save_state(self) -> None:
        if self.state_store is None:
            return
        try:
            self.snapshot_info = self.state_store.save(self.worker.export_state())
            self.events["state_saved"] += 1
        except Exception:  # a full disk must not stop the estimates
            self.events["state_save_failed"] += 1
            log.exception("saving the state to %s failed", self.state_store.path)

    def _snapshot_loop(self) -> None:
        while not self._stop.wait(self.settings.state_interval_s):
            if self.active:  # a standby's empty estimator must not replace the snapshot
                self.save_state()

    # ------------------------------------------------------------------ lifecycle
    def run(self) -> None:
        """Open the session, serve this cell (once the election makes it active) until
        :meth:`stop`."""
        import zenoh

        with zenoh.open(zenoh_config(self.settings)) as session:
            self.serve(session)

    def serve(self, session, primary: bool = True) -> None:
        """Serve this cell on an open session until :meth:`stop`: the threads, the election
        (:mod:`service.election`), at stop the last snapshot."""
        from posefuse.service.election import Election

        self.start(session)
        self.election = Election(
            session,
            self.keys.root,
            primary,
            self.settings.takeover_grace_s,
            self.activate,
            self.deactivate,
        )
        try:
            self.election.start()
            self.ready.set()
            while not self._stop.wait(0.2):
                pass
        finally:
            self.ready.clear()
            self.election.close()
            self.close()

    def start(self, session) -> None:
        """Start the decoder, front-end, estimator and snapshot threads on ``session``; the
        cell's inputs are subscribed by :meth:`activate`."""
        self.session = session
        self._threads = [
            threading.Thread(target=self._decode_loop, daemon=True, name=f"decode-{i}")
            for i in range(self.settings.decode_threads)
        ]
        self._threads += [
            threading.Thread(target=self._front_end, daemon=True, name="posefuse-front"),
            threading.Thread(
                target=self._work, args=(session,), daemon=True, name="posefuse-worker"
            ),
        ]
        if self.state_store is not None:
            self._threads.append(threading.Thread(target=self._snapshot_loop, daemon=True))
        for t in self._threads:
            t.start()

    def activate(self) -> None:
        """Become the cell's producer: restore the last snapshot (a takeover continues the
        previous daemon's tracks), subscribe the cameras, answer queries, ask for infos."""
        session = self.session
        with self._role_lock:
            if self.active:
                return
            self.restore_state()
            self._entities = [
                session.declare_subscriber(self.keys.camera_inputs, self.on_sample),
                session.declare_queryable(self.keys.state, self.on_state_query),
                session.declare_queryable(self.keys.reset, self.on_reset_query),
                session.declare_queryable(self.keys.nbv, self.on_nbv_query),
                session.liveliness().declare_token(self.keys.alive),
            ]
            if self.ros2 is not None:
                import hashlib

                self._gid = hashlib.sha256(f"{session.zid()}/{self.keys.root}".encode()).digest()
                self._entities.append(
                    session.declare_subscriber(
                        self.ros2.input_keys(self.settings.cell), self.on_ros2_sample
                    )
                )
            self.active = True
            self.events["activations"] += 1
        try:  # cameras already running: ask for their info rather than wait for it
            session.get(f"{self.keys.root}/cam/*/info", self._on_info_reply, timeout=2.0)
        except Exception:
            log.exception("asking the cameras for their info failed")

    def deactivate(self) -> None:
        """Stand by: another daemon produces this cell's estimates now. No snapshot is written
        (the active daemon owns it); the tracks are forgotten and restored on activation."""
        with self._role_lock:
            if not self.active:
                return
            self.active = False
            for entity in reversed(self._entities):
                entity.undeclare()
            self._entities = []
            self.events["deactivations"] += 1
            self.worker.reset()

    def close(self, timeout: float = 30.0) -> None:
        """Stop the threads (the frame in flight is fused first), then write the last snapshot
        if this daemon is the producer. ``timeout``: seconds for all threads together."""
        self._stop.set()
        self._wake.set()
        deadline = time.monotonic() + timeout
        for t in self._threads:
            t.join(timeout=max(0.1, deadline - time.monotonic()))
        with self._role_lock:
            if self.active:
                self.save_state()
                for entity in reversed(self._entities):
                    entity.undeclare()
                self._entities = []
                self.active = False
        self.session = None

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()

    def frames_handled(self) -> int:
        """Images received and dealt with: processed, failed or dropped for any reason."""
        s = self.stats
        return (
            s.processed
            + s.errors
            + sum(self.sync.dropped.values())
            + sum(self.unsupported.values())
            + sum(n for k, n in s.decode_reasons.items() if k.startswith("image_"))
            + sum(n for k, n in self.ingest_dropped.items() if k.startswith("image_"))
        )

    def stats_dict(self) -> dict:
        s = self.stats
        dropped = Counter(self.sync.dropped) + self.unsupported
        for reason, n in s.decode_reasons.items():
            kind, _, code = reason.partition("_")
            if kind == "image":
                dropped[f"decode_{code}"] += n
        for reason, n in self.ingest_dropped.items():
            if reason.startswith("image_"):
                dropped[reason.removeprefix("image_")] += n
        cameras = self.sync.camera_counters()
        for cid, c in cameras.items():
            c["processed"] = self._per_camera[(cid, "processed")]
            c["errors"] = self._per_camera[(cid, "errors")]
        return {
            "cell": self.settings.cell,
            "role": "active" if self.active else "standby",
            "frames_received": self.images_received,
            "frames_processed": s.processed,
            "frames_handled": self.frames_handled(),
            "frames_dropped": dict(sorted(dropped.items())),
            "frames_pending": self.sync.pending() + self._fused.qsize(),
            "queued_bytes": self.sync.queued_bytes(),
            "ingest_pending": self.ingest_queue.pending(),
            "ingest_pending_bytes": self.ingest_queue.pending_bytes(),
            "received": dict(s.received),
            "decode_errors": dict(s.decode_errors),
            "decode_errors_by_reason": dict(s.decode_reasons),
            "messages_dropped": dict(self.ingest_dropped),
            "processing_errors": s.errors,
            "latency": s.latency(),
            "cameras": cameras,
            "sync_events": dict(self.sync.events),
            "events": dict(self.events),
            "restored_objects": self.restored,
            "objects_needing_views": self.objects_needing_views(),
            "uptime_s": time.monotonic() - self._started,
        }
