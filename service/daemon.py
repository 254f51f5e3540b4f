"""The estimator daemon on Zenoh: enqueue in callbacks, decode in a small pool, estimate in one
worker thread. This module wires the parts, runs the threads and keeps the lifecycle:

- Intake (:mod:`service.intake`, the same code offline replay feeds): the subscriber on
  ``{cell}/@v1/cam/*/*`` only checks the key and the payload size and queues the bytes in the
  camera's lane of :class:`~service.ingest.FairIngest` (bounded per camera and kind, served in
  turn, so one camera's flood costs another camera nothing); nothing is decoded on the
  transport's threads. Decoder threads turn bytes into messages and give them to the
  :class:`~service.sync.FrameSynchronizer`; a bad message is counted, logged, never raised.
- A camera whose images come without camera info is asked for it: a get on its info key
  (``clients/camera.py`` answers it), at most every ``info_request_s``; at start, every camera
  (:class:`~service.queries.InfoRequests`).
- A two-stage pipeline keeps both cores busy: the front-end thread takes synchronised frames
  and runs the network and voting (:meth:`~service.worker.EstimatorWorker.detections`) while
  the worker thread fuses the previous frame (:meth:`~service.worker.EstimatorWorker.fuse`)
  and publishes every updated ObjectEstimate on ``{cell}/@v1/objects/{object_id}``
  (:mod:`service.publishing`). One thread per stage and a one-frame queue between them:
  frames reach the estimator in the order they left the synchroniser, so the estimates do not
  depend on timing.
- Queryables answer ``estimator/state``, ``estimator/reset`` (with ``api_token`` set, a reset
  needs the token as the query's attachment) and ``estimator/nbv`` (:mod:`service.queries`);
  a liveliness token ``estimator/alive`` says the daemon is up. The counters and the
  ``/stats`` map are :mod:`service.stats`.
- With a ``state_dir``, the tracks are snapshotted every ``state_interval_s`` and at a clean
  stop (after the frame in flight is fused), and restored at start (:mod:`service.state`).
- Several daemons may serve one cell: liveliness tokens elect the one that produces its
  estimates (:mod:`service.election`); the others stand by with nothing subscribed and take
  over from the last snapshot when it disappears. :meth:`Daemon.serve` runs a cell on an open
  session, so one process serves several cells (:mod:`service.cells`).
"""

from __future__ import annotations

import logging
import queue
import threading
import time

from posefuse.estimator.frontend.network import UnsupportedImage
from posefuse.service.codec import NbvRequest
from posefuse.service.intake import Intake
from posefuse.service.keys import Keys
from posefuse.service.publishing import Publisher
from posefuse.service.queries import InfoRequests, Queries
from posefuse.service.settings import Settings, ingest_config, sync_config, zenoh_config
from posefuse.service.stats import FrameCounters
from posefuse.service.sync import FrameSynchronizer
from posefuse.service.worker import EstimatorWorker, now_ns

log = logging.getLogger("posefuse.daemon")

# the checks owed while frames wait, at most (a burst of frames owes no more than this)
MAX_CHECK_CREDIT_S = 0.2


class Daemon:
    def __init__(self, settings: Settings, worker: EstimatorWorker, state_store=None):
        self.settings = settings
        self.worker = worker
        self.keys = Keys(settings.cell)
        self.stats = worker.stats
        self.stats.max_keys = 3 * settings.max_cameras + 8
        self.ros2 = None  # the ROS 2 key layout when settings.ros2 is not off
        if settings.ros2 != "off":
            from posefuse.service.ros2 import Ros2Layout

            self.ros2 = Ros2Layout(settings.ros2, settings.ros2_domain_id)
        self.intake = Intake(
            self.keys,
            FrameSynchronizer(sync_config(settings)),
            self.stats,
            settings.max_payload_bytes,
            settings.max_image_pixels,
            ingest=ingest_config(settings),
            ros2=self.ros2,
            on_image_without_info=self.request_info,
            on_decoded=self._wake_front_end,
            clock=now_ns,
        )
        self.sync = self.intake.sync
        self.ingest_dropped = self.intake.dropped  # messages dropped before decoding
        self.counters = FrameCounters(self.stats, self.intake, settings.max_cameras)
        self.events = self.counters.events
        catalog = getattr(getattr(worker, "estimator", None), "catalog", None)
        self.publisher = Publisher(self.keys, self.ros2, catalog)
        self.queries = Queries(
            settings, self.keys, worker, self.sync, self.events, self.publisher.notify
        )
        self.info_requests = InfoRequests(
            self.keys, settings, self.events, lambda: self.session, self.ingest
        )
        self._fused: queue.Queue = queue.Queue(maxsize=1)  # front end -> estimator
        self._wake = threading.Event()  # a message reached the synchroniser
        self._stop = threading.Event()
        self._role_lock = threading.Lock()
        self.ready = threading.Event()
        self._threads: list[threading.Thread] = []
        self._front: threading.Thread | None = None  # the front-end thread, once started
        self.session = None
        self.state_store = state_store
        self.snapshot_info = None
        self.restored = 0
        self.active = False  # the election made this daemon the cell's producer
        self.election = None
        self._entities: list = []

    # ------------------------------------------------------------------ transport callbacks
    def on_sample(self, sample) -> None:
        """Subscriber callback: check the key and the size, enqueue; never decode here."""
        try:
            self.ingest(str(sample.key_expr), sample.payload.to_bytes())
        except Exception:  # a daemon never dies of a message
            log.exception("unexpected error while receiving")

    def ingest(self, key: str, payload: bytes) -> bool:
        """Hand one received message to its decoder; False when it was dropped (counted)."""
        return self.intake.receive(key, payload, now_ns())

    def on_ros2_sample(self, sample) -> None:
        """Subscriber callback of the ROS 2 camera topics: check, enqueue; never decode here."""
        try:
            self.ingest_ros2(str(sample.key_expr), sample.payload.to_bytes())
        except Exception:
            log.exception("unexpected error while receiving")

    def ingest_ros2(self, key: str, payload: bytes) -> bool:
        """A ROS 2 camera message (CDR) to its decoder; False when dropped (counted)."""
        return self.intake.receive_ros2(key, payload, now_ns())

    def drain(self) -> int:
        """Decode every queued message in this thread (tests and tools without :meth:`run`);
        how many reached the synchroniser."""
        return self.intake.drain()

    def request_info(self, cam_id: str) -> None:
        """Ask a camera for its info, at most every info_request_s."""
        self.info_requests.request(cam_id)

    # ------------------------------------------------------------------ queries, events
    def on_state_query(self, query) -> None:
        self.queries.on_state_query(query)

    def on_reset_query(self, query) -> None:
        self.queries.on_reset_query(query)

    def on_nbv_query(self, query) -> None:
        self.queries.on_nbv_query(query)

    def authorized(self, token: bytes | str | None) -> bool:
        """True when no api_token is set or ``token`` is it (compared in constant time)."""
        return self.queries.authorized(token)

    def reset(self, class_id=None, object_id=None) -> int:
        return self.queries.reset(class_id, object_id)

    def nbv(self, request: NbvRequest) -> dict:
        return self.queries.nbv(request)

    def objects_needing_views(self) -> list[str]:
        return self.queries.objects_needing_views()

    def subscribe(self, maxsize: int = 256) -> queue.Queue:
        """A queue of every estimate and reset event, until :meth:`unsubscribe`."""
        return self.publisher.subscribe(maxsize)

    def unsubscribe(self, q: queue.Queue) -> None:
        self.publisher.unsubscribe(q)

    # ------------------------------------------------------------------ statistics
    def frames_handled(self) -> int:
        """Images received and dealt with: processed, failed or dropped for any reason."""
        return self.counters.frames_handled()

    def stats_dict(self) -> dict:
        return {
            **self.counters.stats_dict(
                self.settings.cell,
                self.active,
                self._fused.qsize(),
                self.restored,
                self.objects_needing_views(),
            ),
            "verification": self.worker.verification_stats(),
        }

    # ------------------------------------------------------------------ threads
    def _wake_front_end(self) -> None:
        self._wake.set()

    def _decode_loop(self) -> None:
        while not self._stop.is_set():
            self.intake.decode_next(timeout=0.2)

    def _front_end(self) -> None:
        """Stage 1: synchronised frames through the network; hands them to the estimator. At
        stop, the frame in the network is still handed over (the estimator fuses it)."""
        while not self._stop.is_set():
            frame = self.intake.pop(now_ns())
            if frame is None:
                self._wake.wait(0.01)
                self._wake.clear()
                continue
            try:
                detections = self.worker.detections(frame)
            except UnsupportedImage as exc:
                self.counters.refused(frame, exc)
                continue
            except Exception:
                self.counters.failed(frame)
                continue
            while True:  # the estimator drains this queue until the front end is done
                try:
                    self._fused.put((frame, detections), timeout=0.2)
                    break
                except queue.Full:
                    continue

    def _front_end_done(self) -> bool:
        """The front end has handed over its last frame (or never ran)."""
        return self._front is None or not self._front.is_alive()

    def _work(self, session) -> None:
        """Stage 2: the estimator's update, then publish; between frames, the deferred
        verification of one waiting track at a time, its verified estimate published: always
        while no frame waits, and while frames wait, up to ``verify_share`` of the worker's
        time (so that under load the checks fall behind, but are never starved). At stop, the
        frames the front end still hands over are fused before the thread ends (then the
        snapshot is written, with the tracks still waiting for their check)."""
        share = self.settings.verify_share
        credit = 0.0  # seconds of checks owed while frames wait
        while not (self._stop.is_set() and self._front_end_done() and self._fused.empty()):
            checking = self.worker.checks_waiting() and not self._stop.is_set()
            if checking and credit > 0 and not self._fused.empty():
                start = time.perf_counter()
                self._check_one(session)
                credit -= time.perf_counter() - start
                continue
            try:
                frame, detections = self._fused.get(timeout=0.0 if checking else 0.2)
            except queue.Empty:
                if checking:
                    self._check_one(session)
                continue
            start = time.perf_counter()
            try:
                updated = self.worker.fuse(frame, detections)
            except Exception:
                self.counters.failed(frame)
                continue
            self.counters.processed(frame, now_ns())
            self.publisher.publish(session, frame.stamp_ns, updated)
            if share > 0:
                owed = (time.perf_counter() - start) * share / (1.0 - share)
                credit = min(credit + owed, MAX_CHECK_CREDIT_S)

    def _check_one(self, session) -> None:
        """One waiting track verified and refined, and its estimate published (a slice of the
        deferred verification: a frame that arrives meanwhile waits for this track only)."""
        try:
            checked = self.worker.check_next(now_ns())
        except Exception:
            self.counters.events["verification_errors"] += 1
            log.exception("the verification of a track failed")
            return
        if checked is not None:
            self.publisher.publish(session, checked.stamp_ns, [checked])

    def _snapshot_loop(self) -> None:
        while not self._stop.wait(self.settings.state_interval_s):
            if self.active:  # a standby's empty estimator must not replace the snapshot
                self.save_state()

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
        self._front = threading.Thread(target=self._front_end, daemon=True, name="posefuse-front")
        self._threads = [
            threading.Thread(target=self._decode_loop, daemon=True, name=f"decode-{i}")
            for i in range(self.settings.decode_threads)
        ]
        self._threads += [
            self._front,
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
                self.publisher.identify(session)
                self._entities.append(
                    session.declare_subscriber(
                        self.ros2.input_keys(self.settings.cell), self.on_ros2_sample
                    )
                )
            self.active = True
            self.events["activations"] += 1
        self.info_requests.request_all(session)  # cameras already running

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
