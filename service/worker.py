"""The one function that turns a synchronised frame into estimates, shared by the daemon and by
offline replay, and the state the HTTP API and the queryables read.

``EstimatorWorker.process`` runs the front end and the estimator on one frame; it is only ever
called from one thread, in stamp order. ``snapshot`` is an immutable copy of the current
estimates, made on the first read after a change, that readers on other threads take without
blocking the worker for long.

The service's estimator defers its verification (:func:`tracker_config`): :meth:`fuse`
publishes the mixture's pose at once, and the tracks whose views changed wait for
:meth:`check_next`, which the daemon calls one track at a time while no frame waits; offline
replay checks every waiting track after each frame (:meth:`process`), as a daemon that is never
behind would.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections import deque

import numpy as np

from posefuse.estimator.tracker import Frame, MultiViewEstimator, ObjectEstimate, TrackerConfig
from posefuse.service.stats import Stats
from posefuse.service.sync import SyncedFrame


class EstimatorWorker:
    """Front end + estimator; the current estimates behind a lock for readers.

    Args:
        estimator: the MultiViewEstimator (owned by this worker).
        detect: image (H, W, 3) uint8 RGB, stamp_ns -> list of Detection.
    """

    def __init__(self, estimator: MultiViewEstimator, detect):
        self.estimator = estimator
        self.detect = detect
        self._lock = threading.Lock()
        # the estimates of every object, made when first asked for after a change (all of
        # them after every frame cost 5-10 ms of a frame's latency with 20 objects in view)
        self._snapshot: dict[str, ObjectEstimate] | None = {}
        self.stats = Stats()
        # the deferred verification: per waiting track, the arrival (wall clock, ns) of the
        # first frame it waits for; tracks checked; and image -> verified pose latencies
        self._waiting_since: dict[str, int] = {}
        self.checked = 0
        self.check_latencies_ms: deque = deque(maxlen=1000)

    def process(self, frame: SyncedFrame) -> list[ObjectEstimate]:
        """Front end and estimator of one frame (:meth:`detections` then :meth:`fuse`), then
        every waiting verification (:meth:`check_next`): the estimates published by a daemon
        that is never behind, the fast ones first."""
        updated = self.fuse(frame, self.detections(frame))
        while (checked := self.check_next()) is not None:
            updated.append(checked)
        return updated

    def detections(self, frame: SyncedFrame) -> list:
        """The front end of one frame; touches no state, so it may run while the previous
        frame is being fused."""
        return self.detect(frame.image, frame.stamp_ns)

    def fuse(self, frame: SyncedFrame, detections: list) -> list[ObjectEstimate]:
        """The estimator's update with one frame's detections; frames in stamp order."""
        with self._lock:
            updated = self.estimator.update(
                Frame(
                    frame.stamp_ns, frame.camera, frame.T_world_cam, frame.image, frame.camera_id
                ),
                detections,
            )
            self._snapshot = None
            # the tracks waiting now (those dropped or merged by this frame leave)
            old = self._waiting_since
            self._waiting_since = {
                k: old.get(k, frame.arrival_ns) for k in self.estimator.checks_due()
            }
            self.stats.processed += 1  # last: a reader that sees it sees the tracks waiting
        return updated

    def checks_waiting(self) -> int:
        """How many tracks wait for their verification (cheap; no lock needed to read)."""
        return len(self._waiting_since)

    def check_next(self, now_ns: int = 0) -> ObjectEstimate | None:
        """Verify the track that has waited longest (:meth:`MultiViewEstimator.check_next`);
        its estimate, or None when none waits. ``now_ns``: the wall clock its latency is
        measured against (0: not measured)."""
        with self._lock:
            due = self.estimator.checks_due()
            for gone in set(self._waiting_since) - set(due):  # dropped, merged or reset
                del self._waiting_since[gone]
            if not due:
                return None
            since = self._waiting_since.pop(due[0], 0)
            try:
                checked = self.estimator.check_next(due[0])
            finally:  # even a check that raised may have changed the track
                self._snapshot = None
            self.checked += 1
            if now_ns and since:
                self.check_latencies_ms.append((now_ns - since) / 1e6)
        return checked

    def verification_stats(self) -> dict:
        """The deferred verification in ``/stats``: on or off, tracks waiting, tracks checked,
        and the latency from an image to the verified pose of the tracks it changed."""
        latency: dict[str, float | None] = {"p50_ms": None, "p95_ms": None}
        with self._lock:
            latencies = list(self.check_latencies_ms)
        if latencies:
            a = np.array(latencies)
            latency = {"p50_ms": float(np.percentile(a, 50)), "p95_ms": float(np.percentile(a, 95))}
        return {
            "enabled": self.estimator.config.verification.enabled,
            "waiting": self.checks_waiting(),
            "checked": self.checked,
            "latency": latency,
        }

    def _current(self) -> dict[str, ObjectEstimate]:
        """The estimates by object id; call with the lock held."""
        if self._snapshot is None:
            self._snapshot = {e.object_id: e for e in self.estimator.estimates()}
        return self._snapshot

    def snapshot(self) -> list[ObjectEstimate]:
        with self._lock:
            current = self._current()
            return [current[k] for k in sorted(current)]

    def get(self, object_id: str) -> ObjectEstimate | None:
        with self._lock:
            return self._current().get(object_id)

    def nbv_inputs(self, max_components: int = 3) -> tuple[list, dict]:
        """The tracks (and held detections) as next-best-view inputs, and the appearance index
        of each of their classes with a rotation mixture (taken under the lock; the scoring
        itself runs outside it)."""
        from posefuse.estimator.nbv import appearance_index, tracks_for_nbv

        with self._lock:
            tracks = tracks_for_nbv(self.estimator, max_components)
            # only banks already loaded: loading one takes seconds, and not under this lock
            loaded = self.estimator.banks()
        wanted = {t.obj_id for t in tracks if len(t.weights) > 1}
        catalog = self.estimator.catalog
        return tracks, {
            k: appearance_index(b, catalog[k]) for k, b in loaded.items() if k in wanted
        }

    def nbv_tracks(self) -> list:
        """The tracks as next-best-view inputs, without the appearance indices (cheap)."""
        from posefuse.estimator.nbv import tracks_for_nbv

        with self._lock:
            return tracks_for_nbv(self.estimator)

    def export_state(self) -> dict:
        """The estimator's tracks as picklable data (a deep copy, taken under the lock)."""
        import copy

        with self._lock:
            return copy.deepcopy(self.estimator.export_state())

    def import_state(self, state: dict) -> None:
        with self._lock:
            self.estimator.import_state(state)
            self._snapshot = None
            self._waiting_since = dict.fromkeys(self.estimator.checks_due(), 0)

    def reset(self, class_id: int | None = None, object_id: str | None = None) -> int:
        """Forget tracks; KeyError for an unknown object, ValueError for an unknown class."""
        with self._lock:
            if class_id is not None and class_id not in self.estimator.catalog:
                raise ValueError(f"unknown class_id {class_id}")
            n = self.estimator.reset(class_id=class_id, object_id=object_id)
            self._snapshot = None
            due = set(self.estimator.checks_due())
            self._waiting_since = {k: v for k, v in self._waiting_since.items() if k in due}
            return n


def tracker_config(settings) -> TrackerConfig:
    """The service's estimator settings: verification as ``settings.verify`` says, deferred
    (the frame path never waits for it; see the module docstring), with the settings the
    model's card gives for its masks (``ModelCard.verification``), the bin of the settings
    where ``settings.bin_known``, and the turn judge as ``settings.verify_turns`` says."""
    from posefuse.estimator.frontend.network import load_card

    config = TrackerConfig.with_verification(settings.verify, deferred=True)
    config = config.with_card(load_card(settings.model).verification)
    if settings.bin_known:
        config = dataclasses.replace(config, bin=settings.bin_region())
    if settings.verify_turns:
        return config
    verification = config.verification
    turns = dataclasses.replace(verification.turns, enabled=False)
    return dataclasses.replace(config, verification=dataclasses.replace(verification, turns=turns))


def make_detector(settings, catalog):
    """The front end of the settings: the ONNX network of ``settings.model``."""
    from posefuse.estimator.frontend.network import NetworkFrontend

    network = NetworkFrontend(
        settings.model, catalog, threads=settings.onnx_threads, spin=settings.onnx_spin
    )
    return lambda image, stamp_ns: network.detect(image)


def now_ns() -> int:
    """Wall-clock time for latency statistics only (never given to the estimator)."""
    return time.time_ns()
