"""Track bookkeeping: what a track holds, and how tracks are founded, grown, split, merged and
dropped (paper, section IV; the translation itself is :mod:`estimator.translation`).

A :class:`Track` keeps its center observations and, aligned with them view by view, a
:class:`ViewRef` each (which detection of which view, and the box's depth). The views waiting
for their rotation are :class:`PendingView` records, and every detection the track ever took is
a :class:`DetectionRef`. :class:`TrackBook` owns the tracks of one estimator, the detections
held for a partner view, and the serial numbers that name new tracks.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from posefuse.estimator.core.objects import Catalog
from posefuse.estimator.frontend.detection import ANY_PART
from posefuse.estimator.rotation.mixture import RotationMixture
from posefuse.estimator.tracker.config import TrackerConfig
from posefuse.estimator.translation.association import TrackView, innovation_cost
from posefuse.estimator.translation.founding import (
    FoundingPair,
    HeldDetection,
    pair_observations,
    triangulate_pair,
)
from posefuse.estimator.translation.gaussian import (
    CenterObservations,
    TranslationEstimate,
    estimate_translation,
    marginalize_oldest,
)
from posefuse.estimator.translation.merging import MergeCandidate, merge_pairs
from posefuse.estimator.translation.splitting import outlier_views
from posefuse.estimator.verification.edge_maps import EdgeRoi, EdgeView
from posefuse.estimator.verification.refinement import Refinement
from posefuse.estimator.verification.turns import TurnJudgement, TurnScoreCache
from posefuse.estimator.verification.verify import ScoreCache, Verdict

TENTATIVE = "tentative"
CONFIRMED = "confirmed"


class DetectionRef(NamedTuple):
    """One detection: the stamp of its view and its index among the view's detections."""

    stamp_ns: int
    index: int


class ViewRef(NamedTuple):
    """A track's view, aligned with its center observations: the detection it took and the
    depth its box implies (metres; NaN for a box truncated by the image border)."""

    stamp_ns: int
    index: int
    box_depth: float


class PendingView(NamedTuple):
    """A view waiting for a translation good enough to measure its rotation: its stamp,
    T_cam_world (4, 4), K (3, 3), the detection's mask ((H, W) bool, or None) and whether that
    mask follows the part's outline (the verification reads only such a mask)."""

    stamp_ns: int
    T_cam_world: np.ndarray
    K: np.ndarray
    mask: np.ndarray | None
    silhouette: bool = True


@dataclass(eq=False)
class Track:
    """One object hypothesis. ``obs`` and ``refs`` are aligned view by view; ``prior_mean``
    (3,) and ``prior_cov`` (3, 3) hold the views folded out of ``obs``."""

    object_id: str
    obj_id: int
    obs: CenterObservations
    prior_mean: np.ndarray
    prior_cov: np.ndarray
    estimate: TranslationEstimate
    first_stamp_ns: int
    last_stamp_ns: int
    misses: int = 0  # consecutive views that predicted it in view and did not detect it
    missed_views: int = 0  # all such views (a class attribute for snapshots before it)
    status: str = TENTATIVE
    detections: list[DetectionRef] = field(default_factory=list)
    refs: list[ViewRef] = field(default_factory=list)
    mixture: RotationMixture | None = None
    views_seen: int = 1
    pending: list[PendingView] = field(default_factory=list)
    # the most recent views' edge maps (estimator.verification.edge_maps), at most
    # verification.max_views; with a deferred check, a view's warped RoI until the check makes
    # its maps
    edge_views: list[EdgeView | EdgeRoi] = field(default_factory=list)
    verdict: Verdict | None = None  # of the last verification, for the mixture as it was then
    scores: ScoreCache = field(default_factory=ScoreCache)  # per-view costs, reused
    refined: Refinement | None = None
    # which of the part's unasked near-symmetric turns the kept views show, judged after the
    # refinement (estimator.verification.turns); None: not judged, every turn open
    turns: TurnJudgement | None = None
    turn_scores: TurnScoreCache | None = None  # the judge's per-view sums, reused
    # the verified pose's mean cost in the kept views, measured after each check and kept
    # while a deferred check waits (None: not measured since a merge or a failed check, or
    # the gate is off); above VerificationConfig.max_fit the track is published as tentative
    fit: float | None = None
    # the translation prior (3,) the refinement took, and the stamps of the views the refined
    # pose has been checked against (the settled check)
    refined_t_prior: np.ndarray | None = None
    settled_stamps: frozenset = frozenset()
    # with deferred verification: the view serial since which the track waits for its check
    # (None: it does not wait), and the stamps of the views kept meanwhile
    check_since: int | None = None
    check_added: frozenset = frozenset()

    def view(self) -> TrackView:
        e = self.estimate
        return TrackView(e.t_world_obj, e.cov, self.obs)


def _T(obs: CenterObservations, k: int) -> np.ndarray:
    """(4, 4) T_cam_world of view ``k``."""
    T = np.eye(4)
    T[:3, :3] = obs.R_cam_world[k]
    T[:3, 3] = obs.t_cam_world[k]
    return T


class TrackBook:
    """The tracks of one estimator, the detections held per class for a partner view, and the
    serial numbers that name new tracks (``{class name}-{serial:03d}``, never reused)."""

    def __init__(self, catalog: Catalog, config: TrackerConfig):
        self.catalog = catalog
        self.config = config
        self.tracks: dict[str, Track] = {}
        self.serial: dict[int, int] = {}  # per class, the last serial given
        self.held: dict[int, list[HeldDetection]] = {}  # per class, waiting for a partner
        self.view_serial = 0  # views seen, for how long a detection is held

    def _estimate(self, obj_id, obs, prior_mean, prior_cov, start=None) -> TranslationEstimate:
        return estimate_translation(
            obs,
            prior_mean,
            prior_cov,
            start=start,
            variance_prior_dof=self.config.translation_variance_dof,
            shared_std=self.shared_frac * self.catalog[obj_id].diameter,
        )

    @property
    def shared_frac(self) -> float:
        """The error the views share, a share of the diameter (TrackerConfig)."""
        return self.config.translation_shared_frac

    def classes(self) -> set[int]:
        return {t.obj_id for t in self.tracks.values()}

    def of_class(self, obj_id: int) -> list[Track]:
        """The class's tracks, in the order they were made."""
        return [t for t in self.tracks.values() if t.obj_id == obj_id]

    def new_track(self, obj_id: int, obs, prior_mean, prior_cov, refs: list[ViewRef]) -> Track:
        estimate = self._estimate(obj_id, obs, prior_mean, prior_cov)
        serial = self.serial.get(obj_id, 0) + 1
        self.serial[obj_id] = serial
        object_id = f"{self.catalog[obj_id].name}-{serial:03d}"
        stamps = [r.stamp_ns for r in refs]
        track = Track(
            object_id, obj_id, obs, prior_mean, prior_cov, estimate, min(stamps), max(stamps)
        )
        track.refs = list(refs)
        track.detections = [DetectionRef(r.stamp_ns, r.index) for r in refs]
        track.views_seen = len(refs)
        if len(obs) >= self.config.confirm_views:
            track.status = CONFIRMED
        self.tracks[object_id] = track
        return track

    def found_track(self, pair: FoundingPair) -> Track:
        """A track from two held detections of different views
        (:mod:`estimator.translation.founding`)."""
        a, b = pair.older, pair.newer
        obs = pair_observations(a, b)
        refs = [
            ViewRef(a.stamp_ns, a.index, a.box_depth),
            ViewRef(b.stamp_ns, b.index, b.box_depth),
        ]
        track = self.new_track(a.obj_id, obs, pair.prior_mean, pair.prior_cov, refs)
        for h in (a, b):
            track.pending.append(PendingView(h.stamp_ns, h.T_cam_world, h.K, h.mask, h.silhouette))
        return track

    def absorb_held(
        self,
        pool: list[HeldDetection],
        tracks: list[Track],
        box_depth_scale: dict[int, float] | None = None,
    ) -> list[HeldDetection]:
        """Held detections of earlier views that a just-founded track explains join it; the
        others are returned. box_depth_scale: per class, the factor from the box depth of a held
        "a part" (``ANY_PART``: a typical part's) to that of the joined track's class (the named
        part's size over the typical part's); None or a class not in it: 1. A labelled held
        detection keeps its own."""
        gate = self.config.association.gate_chi2
        left = []
        for h in pool:
            best, best_cost = None, gate
            for track in tracks:
                if h.stamp_ns in track.obs.stamp_ns:
                    continue
                c = innovation_cost(track.view(), h.T_cam_world, h.K, h.uv, h.cov)
                if c <= best_cost:
                    best, best_cost = track, c
            if best is None:
                left.append(h)
                continue
            depth = h.box_depth
            if h.obj_id == ANY_PART:
                depth *= (box_depth_scale or {}).get(best.obj_id, 1.0)
            self.add_view(
                best, h.T_cam_world, h.K, h.uv, h.cov, ViewRef(h.stamp_ns, h.index, depth)
            )
            best.pending.append(PendingView(h.stamp_ns, h.T_cam_world, h.K, h.mask, h.silhouette))
        return left

    def add_view(
        self,
        track: Track,
        T_cam_world: np.ndarray,
        K: np.ndarray,
        uv: np.ndarray,
        cov: np.ndarray,
        ref: ViewRef,
    ) -> None:
        """A detection joins the track: T_cam_world (4, 4), K (3, 3), its center uv (2,) in
        undistorted pixels with covariance cov (2, 2); the translation is estimated again."""
        track.obs = track.obs.append(T_cam_world, K, uv, cov, ref.stamp_ns)
        track.refs.append(ref)
        track.views_seen += 1
        if len(track.obs) > self.config.max_track_views:
            track.obs, track.prior_mean, track.prior_cov = marginalize_oldest(
                track.obs, track.prior_mean, track.prior_cov, track.estimate.t_world_obj
            )
            track.refs.pop(0)
        track.estimate = self._estimate(
            track.obj_id,
            track.obs,
            track.prior_mean,
            track.prior_cov,
            start=track.estimate.t_world_obj,
        )
        track.last_stamp_ns = max(track.last_stamp_ns, ref.stamp_ns)
        track.misses = 0
        track.detections.append(DetectionRef(ref.stamp_ns, ref.index))
        if len(track.obs) >= self.config.confirm_views:
            track.status = CONFIRMED
        self.review_support(track)

    def supported(self, track: Track) -> bool:
        """The views that predicted the track in view detected it often enough
        (``TrackerConfig.min_support``), or too few have missed it to tell."""
        missed = track.missed_views
        if self.config.min_support <= 0 or missed < self.config.support_after:
            return True
        return track.views_seen / (track.views_seen + missed) >= self.config.min_support

    def review_support(self, track: Track) -> None:
        """A confirmed track the views no longer support falls back to tentative (and is
        confirmed again once they do)."""
        if track.status == CONFIRMED and not self.supported(track):
            track.status = TENTATIVE

    def split_tracks(self, keys: list[str]) -> list[tuple[str, str]]:
        """Views a track cannot explain leave it (:mod:`estimator.translation.splitting`); two or
        more that agree with each other make a new track. Returns (new object_id, from
        object_id)."""
        out = []
        for key in keys:
            track = self.tracks[key]
            leave = outlier_views(track.estimate, self.config.splitting)
            if not leave.any():
                continue
            gone = [r for r, x in zip(track.refs, leave, strict=True) if x]
            split_obs = track.obs.select(leave)
            track.obs = track.obs.select(~leave)
            track.refs = [r for r, x in zip(track.refs, leave, strict=True) if not x]
            gone_ids = {DetectionRef(r.stamp_ns, r.index) for r in gone}
            gone_stamps = {r.stamp_ns for r in gone}
            track.edge_views = [v for v in track.edge_views if v.stamp_ns not in gone_stamps]
            track.detections = [d for d in track.detections if d not in gone_ids]
            track.views_seen -= len(gone)
            track.estimate = self._estimate(
                track.obj_id,
                track.obs,
                track.prior_mean,
                track.prior_cov,
                start=track.estimate.t_world_obj,
            )
            if len(gone) < 2:
                continue
            # the leavers as a track of their own, if they agree: prior from the first two rays
            first = [
                HeldDetection(
                    track.obj_id,
                    int(split_obs.stamp_ns[k]),
                    0,
                    _T(split_obs, k),
                    split_obs.K[k],
                    split_obs.uv[k],
                    np.linalg.inv(split_obs.info[k]),
                    gone[k].box_depth,
                    gone[k].index,
                )
                for k in range(2)
            ]
            pair = triangulate_pair(first[0], first[1], self.config.founding)
            if pair is None:
                continue
            est = self._estimate(track.obj_id, split_obs, pair.prior_mean, pair.prior_cov)
            if np.any(est.chi2 > self.config.splitting.outlier_chi2):
                continue
            new = self.new_track(track.obj_id, split_obs, pair.prior_mean, pair.prior_cov, gone)
            out.append((new.object_id, key))
        return out

    def merge_tracks(self) -> list[tuple[str, str]]:
        """Tracks of one class that converged merge into the one with more views
        (:mod:`estimator.translation.merging`). Returns (absorbed, survivor) pairs."""
        out = []
        for obj_id in sorted(self.classes()):
            keys = sorted(k for k, t in self.tracks.items() if t.obj_id == obj_id)
            cands = [
                MergeCandidate(k, t.estimate.t_world_obj, t.estimate.cov, t.obs)
                for k in keys
                if len((t := self.tracks[k]).obs) >= 2
            ]
            diameter = self.catalog[obj_id].diameter
            for ka, kb in merge_pairs(cands, diameter, self.config.merging):
                a, b = self.tracks[ka], self.tracks[kb]
                keep, gone = (a, b) if (len(a.obs), kb) >= (len(b.obs), ka) else (b, a)
                self._combine(keep, gone)
                del self.tracks[gone.object_id]
                out.append((gone.object_id, keep.object_id))
        return out

    def _combine(self, keep: Track, gone: Track) -> None:
        order = np.argsort(np.concatenate([keep.obs.stamp_ns, gone.obs.stamp_ns]), kind="stable")
        refs = keep.refs + gone.refs
        keep.obs = keep.obs.concat(gone.obs)
        keep.refs = [refs[k] for k in order]
        keep.detections = sorted(set(keep.detections) | set(gone.detections))
        keep.views_seen += gone.views_seen
        keep.first_stamp_ns = min(keep.first_stamp_ns, gone.first_stamp_ns)
        keep.last_stamp_ns = max(keep.last_stamp_ns, gone.last_stamp_ns)
        keep.misses = min(keep.misses, gone.misses)
        keep.missed_views = min(keep.missed_views, gone.missed_views)
        if gone.status == CONFIRMED:
            keep.status = CONFIRMED
        keep.pending = sorted(keep.pending + gone.pending, key=lambda p: p.stamp_ns)
        views = sorted(keep.edge_views + gone.edge_views, key=lambda v: v.stamp_ns)
        keep.edge_views = views[-self.config.verification.max_views :]
        # the mixture changes: verified again next view
        keep.verdict, keep.refined, keep.turns, keep.fit = None, None, None, None
        waiting = [s for s in (keep.check_since, gone.check_since) if s is not None]
        keep.check_since = min(waiting) if waiting else None
        keep.check_added = keep.check_added | gone.check_added
        keep.scores = ScoreCache()
        if gone.mixture is not None:
            if keep.mixture is None:
                keep.mixture = gone.mixture
            else:
                for comp in gone.mixture.components:
                    for R, c in comp.members:
                        keep.mixture.add(R, c)
        keep.estimate = self._estimate(
            keep.obj_id, keep.obs, keep.prior_mean, keep.prior_cov, start=keep.estimate.t_world_obj
        )

    def drop_missed(self) -> list[str]:
        """Drop the tracks that missed too many views in a row (``TrackerConfig.max_misses``);
        returns their object ids."""
        dropped = []
        for key in list(self.tracks):
            t = self.tracks[key]
            limit = (
                max(self.config.max_misses, t.views_seen)
                if t.status == CONFIRMED
                else self.config.max_misses_tentative
            )
            if t.misses >= limit:
                dropped.append(key)
                del self.tracks[key]
        return dropped

    def keep_held(self, obj_id: int, pool: list[HeldDetection]) -> None:
        """The class's held detections from now on, those older than ``founding.hold_views``
        views forgotten."""
        self.held[obj_id] = [
            h for h in pool if self.view_serial - h.view_serial <= self.config.founding.hold_views
        ]

    def reset(self, class_id: int | None = None, object_id: str | None = None) -> int:
        """Forget all tracks, those of one class, or one object (see
        ``MultiViewEstimator.reset``). Returns how many were removed."""
        if class_id is not None and object_id is not None:
            raise ValueError("reset: give a class or an object, not both")
        if object_id is not None:
            if object_id not in self.tracks:
                raise KeyError(object_id)
            del self.tracks[object_id]
            return 1
        # "a part" not yet named may be of the class: it goes with any class
        self.held = {
            k: v
            for k, v in self.held.items()
            if class_id is not None and k not in (class_id, ANY_PART)
        }
        keys = [k for k, t in self.tracks.items() if class_id is None or t.obj_id == class_id]
        for k in keys:
            del self.tracks[k]
        return len(keys)
