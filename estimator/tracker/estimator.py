"""MultiViewEstimator: per-view detections in, object tracks with pose estimates out.

One call of :meth:`MultiViewEstimator.update` per view, in stamp order. It validates the frame
(nothing in the state changes if the frame is bad), then walks the method's steps:

0. detections of "a part" (a generalist front end's, obj_id ``ANY_PART``) named where they
   can be (:meth:`MultiViewEstimator.name_parts`); the rest are held as "a part", and a track
   they found is named by the parts' templates (:mod:`estimator.rotation.naming`);
1. association, class by class, of the view's detections with the tracks
   (:mod:`estimator.translation.association`), each matched track's translation estimated again
   from all its views (:mod:`estimator.translation.gaussian`); unmatched detections are held
   and found tracks in pairs of views (:mod:`estimator.translation.founding`);
2. views a track cannot explain split off, tracks that converged merge
   (:mod:`estimator.tracker.tracks`);
3. the pose stage of every track the view touched: rotation measurement and fusion,
   verification and refinement (:mod:`estimator.tracker.pose_stage`);
4. tracks that should have been seen but were not, too often, are dropped, and the touched
   tracks' estimates are published (:mod:`estimator.tracker.published`).

Documented skips (counted in ``skipped`` of the last update, never an exception):

- a detection of a class the catalog does not have;
- a detection of "a part" in a frame without an image, when no track names it (the templates
  need the pixels);
- a detection whose center lies outside the image;
- an unmatched detection whose box touches the image border does not start a track: the box of
  a truncated part says nothing reliable about its depth. It may still update a track.

The estimator is deterministic: it never reads the clock and has no randomness, so the same
sequence of updates gives the same estimates.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from posefuse.estimator.core.camera import Camera
from posefuse.estimator.core.geometry import invert
from posefuse.estimator.core.objects import Catalog
from posefuse.estimator.frontend.detection import ANY_PART, Detection, ExpectedPart
from posefuse.estimator.rotation.matching import RotationMatcher
from posefuse.estimator.rotation.templates import TemplateBank
from posefuse.estimator.tracker import snapshot
from posefuse.estimator.tracker.config import TrackerConfig
from posefuse.estimator.tracker.naming import any_part_size, name_by_tracks, name_pair, size_spread
from posefuse.estimator.tracker.pose_stage import PoseStage
from posefuse.estimator.tracker.published import ObjectEstimate, published_estimate
from posefuse.estimator.tracker.tracks import (
    CONFIRMED,
    PendingView,
    Track,
    TrackBook,
    ViewRef,
)
from posefuse.estimator.translation.association import assign, cost_matrix
from posefuse.estimator.translation.founding import HeldDetection, choose_pairs
from posefuse.estimator.translation.gaussian import (
    MIN_DEPTH,
    CenterObservations,
    bbox_diagonal_ratio,
    predict,
)
from posefuse.estimator.verification.kernels import compile_kernels
from posefuse.estimator.verification.refinement import RefineConfig


@dataclass(frozen=True, eq=False)
class Frame:
    """One image's context: capture time, camera intrinsics, camera pose and (optionally) pixels.

    T_world_cam: (4, 4) metres; image: (H, W, 3) uint8 RGB or None.
    """

    stamp_ns: int
    camera: Camera
    T_world_cam: np.ndarray
    image: np.ndarray | None = None
    camera_id: str = "cam0"


@dataclass(frozen=True)
class UpdateReport:
    """What one update did: (detection index, object_id) pairs of this view's detections that
    joined a track or founded one, tracks dropped (unseen, or merged into another: ``merged``
    has (absorbed, survivor) pairs), tracks split off (new object_id, from object_id), held
    detections (this view's, waiting for a partner) and skipped detections."""

    assigned: tuple[tuple[int, str], ...]
    started: tuple[tuple[int, str], ...]
    dropped: tuple[str, ...]
    skipped: tuple[tuple[int, str], ...]
    held: tuple[int, ...] = ()
    merged: tuple[tuple[str, str], ...] = ()
    split: tuple[tuple[str, str], ...] = ()


@dataclass(frozen=True, eq=False)
class ViewDetections:
    """One view, ready for association.

    T_cam_world: (4, 4); K: (3, 3); detections: all of the view's; centers: (D, 2) their
    centers undistorted (rows of skipped detections are zero); usable: indices of those not
    skipped; box_depths: per usable index, the depth its box implies (metres).
    """

    stamp_ns: int
    view_serial: int
    camera: Camera
    T_cam_world: np.ndarray
    detections: list[Detection]
    centers: np.ndarray
    usable: tuple[int, ...]
    box_depths: dict[int, float]

    @property
    def K(self) -> np.ndarray:
        return self.camera.K


@dataclass
class _Changes:
    """What an update has done so far: (detection, object_id) pairs assigned and started, the
    view's detections held, and the tracks touched, in the order it happened."""

    assigned: list[tuple[int, str]] = field(default_factory=list)
    started: list[tuple[int, str]] = field(default_factory=list)
    held: list[int] = field(default_factory=list)
    touched: list[str] = field(default_factory=list)


def validate_pose(T: np.ndarray, name: str = "T_world_cam") -> np.ndarray:
    """(4, 4) float64 rigid transform or ValueError naming what is wrong."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"{name}: expected a 4x4 matrix, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise ValueError(f"{name}: contains non-finite values")
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0.5:
        raise ValueError(f"{name}: the rotation part is not a rotation matrix")
    if not np.allclose(T[3], [0, 0, 0, 1]):
        raise ValueError(f"{name}: the last row must be [0, 0, 0, 1]")
    return T


class MultiViewEstimator:
    """Incremental multi-view pose estimator over a catalog (see the module docstring)."""

    STATE_VERSION = snapshot.STATE_VERSION

    def __init__(
        self,
        catalog: Catalog,
        config: TrackerConfig | None = None,
        banks: dict[int, TemplateBank] | None = None,
        template_cache_dir: str | None = None,
        show_progress: bool = False,
        matchers: dict | None = None,
    ):
        """banks: template banks per obj_id (built, or loaded from the cache, when missing).
        matchers: rotation matchers per obj_id replacing the default RotationMatcher of the
        bank (anything with ``.bank`` and ``measure(image, K, t_cam_obj, mask)`` giving
        RotationMeasurements; the benchmarks use it for the multi-scale ablation; to name a
        generalist's "a part", also ``scores(roi, roi_mask)`` and ``config.mask_dilation_px``,
        else that naming raises a TypeError naming the part)."""
        self.catalog = catalog
        self.config = config or TrackerConfig()
        self.book = TrackBook(catalog, self.config)
        self.poses = PoseStage(
            catalog, self.config, banks, template_cache_dir, show_progress, matchers
        )
        self._size_ratios: dict[int, float] = {}  # per class, for the box depth
        self._part_sizes: dict[int, float] | None = None  # per class, for "a part" (_sizes)
        self.last_report = UpdateReport((), (), (), ())
        self.last_stamp_ns: int | None = None

    @property
    def tracks(self) -> dict[str, Track]:
        """The live tracks by object_id, in the order they were made."""
        return self.book.tracks

    # ---- public API -------------------------------------------------------------------------

    def update(self, frame: Frame, detections: list[Detection]) -> list[ObjectEstimate]:
        """Fuse one view. Returns the estimates of the tracks this view matched or started."""
        T_world_cam = validate_pose(frame.T_world_cam)
        detections = self.name_parts(frame, detections)
        view, skipped = self._view_detections(frame, invert(T_world_cam), detections)
        changes = _Changes()
        if frame.image is not None:  # before the founding, which may name a part by it
            self.poses.keep_image(view.stamp_ns, frame.image)
        walked = {detections[j].obj_id for j in view.usable} | self.book.classes()
        if self.book.held.get(ANY_PART):  # "a part" held: aged, and paired, every view
            walked.add(ANY_PART)
        for obj_id in sorted(walked):
            self._associate_class(view, obj_id, changes)

        split = self.book.split_tracks(sorted(set(changes.touched)))
        touched = changes.touched + [new_id for new_id, _ in split]
        merged = self.book.merge_tracks()
        absorbed = {a for a, _ in merged}
        touched = [k for k in dict.fromkeys(touched) if k not in absorbed]

        if frame.image is not None:
            for j, oid in changes.assigned:
                if oid in self.tracks:
                    track = self.tracks[oid]
                    det = detections[j]
                    pending = PendingView(
                        view.stamp_ns,
                        view.T_cam_world,
                        view.K,
                        det.mask,
                        det.mask_kind == "silhouette",
                    )
                    track.pending.append(pending)
                    del track.pending[: -self.config.max_pending_views]
            for oid in touched:
                self.poses.measure_rotations(self.tracks[oid], view.view_serial)

        dropped = [a for a, _ in merged] + self.book.drop_missed()
        self.last_report = UpdateReport(
            tuple(changes.assigned),
            tuple(changes.started),
            tuple(dropped),
            tuple(skipped),
            tuple(changes.held),
            tuple(merged),
            tuple(split),
        )
        self.last_stamp_ns = view.stamp_ns
        return [self._estimate(self.tracks[k], view.stamp_ns) for k in touched if k in self.tracks]

    def name_parts(self, frame: Frame, detections: list[Detection]) -> list[Detection]:
        """The detections of "a part" (obj_id ``ANY_PART``, a generalist front end's) that can
        be named now, named (:func:`estimator.tracker.naming.name_by_tracks`); the others as
        they are. A catalog that has a part of obj_id ``ANY_PART`` names none. The frame's pose
        must be valid (:meth:`update` checks it first)."""
        if ANY_PART in self.catalog or all(d.obj_id != ANY_PART for d in detections):
            return detections  # nothing to name: no work on a labelled front end's frames
        T_cam_world = invert(validate_pose(frame.T_world_cam))
        tracks = list(self.tracks.values())
        return name_by_tracks(
            detections,
            frame.camera,
            T_cam_world,
            tracks,
            sorted(self.catalog),
            self.config.association,
        )

    def checks_due(self) -> list[str]:
        """With ``deferred_verification``: the tracks waiting for their verification, the
        longest waiting first (then in object id order)."""
        waiting = [(t.check_since, k) for k, t in self.tracks.items() if t.check_since is not None]
        return [k for _, k in sorted(waiting)]

    def check_next(self, object_id: str | None = None) -> ObjectEstimate | None:
        """Verify (and refine) the track that has waited longest, or ``object_id``; its
        estimate afterwards, or None when no track waits (or ``object_id`` does not)."""
        due = self.checks_due()
        if object_id is None:
            object_id = due[0] if due else None
        if object_id not in due:
            return None
        track = self.tracks[object_id]
        self.poses.check_due(track)
        return self._estimate(track, self.last_stamp_ns or 0)

    def check_all(self) -> list[ObjectEstimate]:
        """Every waiting track's verification, the longest waiting first; their estimates."""
        return [e for k in self.checks_due() if (e := self.check_next(k)) is not None]

    def estimates(self, include_tentative: bool = True) -> list[ObjectEstimate]:
        """All current tracks, in object_id order; without ``include_tentative``, those
        published as confirmed (a confirmed track whose verified pose fits its views poorly is
        published as tentative, ``VerificationConfig.max_fit``)."""
        stamp = self.last_stamp_ns or 0
        estimates = [
            self._estimate(self.tracks[k], stamp)
            for k in sorted(self.tracks)
            if include_tentative or self.tracks[k].status == CONFIRMED
        ]
        return [e for e in estimates if include_tentative or e.status == CONFIRMED]

    def expected_parts(
        self,
        camera: Camera,
        T_world_cam: np.ndarray,
        detections: list[Detection] = (),
        covered_frac: float = 0.5,
        max_std_frac: float = 0.25,
    ) -> list[ExpectedPart]:
        """Where the confirmed tracks should show in a view that the detections do not
        cover, for a front end to look there too (:meth:`NetworkFrontend.detect_at`).

        A track is expected where its translation projects, inside the image, with the side
        its box has at that depth (the class's box-size ratio, as for the box depth); not
        where a detection of its class lies within ``covered_frac`` of that side, nor when its
        translation's standard deviation (sqrt of the trace of its covariance) projects to more
        than ``max_std_frac`` of the side (a crop there would not be centred on the part).

        Args:
            camera: the view's intrinsics; T_world_cam: (4, 4); detections: the view's.
        """
        T_cam_world = invert(validate_pose(T_world_cam))
        f = 0.5 * (camera.K[0, 0] + camera.K[1, 1])
        out = []
        for oid in sorted(self.tracks):
            track = self.tracks[oid]
            if track.status != CONFIRMED:
                continue
            p = T_cam_world[:3, :3] @ track.estimate.t_world_obj + T_cam_world[:3, 3]
            if p[2] <= MIN_DEPTH:
                continue
            uv = camera.project(p)
            if not camera.contains(uv[None])[0]:
                continue
            model = self.catalog[track.obj_id]
            side = f * self._size_ratio(track.obj_id) * model.diameter / p[2] / np.sqrt(2.0)
            if f * np.sqrt(np.trace(track.estimate.cov)) / p[2] > max_std_frac * side:
                continue
            if any(
                d.obj_id in (track.obj_id, ANY_PART)
                and np.linalg.norm(d.center_uv - uv) < covered_frac * side
                for d in detections
            ):
                continue
            out.append(ExpectedPart(oid, track.obj_id, uv, float(side)))
        return out

    def held(self) -> list[HeldDetection]:
        """The detections waiting for a partner view to found a track, oldest first per class
        (parts seen in one view only)."""
        return [h for obj_id in sorted(self.book.held) for h in self.book.held[obj_id]]

    def reset(self, class_id: int | None = None, object_id: str | None = None) -> int:
        """Forget all tracks, those of one class, or one object. Returns how many were removed.

        Object ids are never reused, so a subscriber cannot confuse a new track with a forgotten
        one.
        """
        return self.book.reset(class_id, object_id)

    def export_state(self) -> dict:
        """The tracks and the counters that go with them, as plain picklable data: translation
        Gaussians, rotation mixtures, the views kept. Frames' images are not included (views
        still waiting for their rotation lose them). Restored by :meth:`import_state`."""
        return snapshot.export_state(self.tracks, self.book, self._size_ratios, self.last_stamp_ns)

    def import_state(self, state: dict) -> None:
        """Replace the tracks by those of :meth:`export_state` (this version's or the one
        before, :func:`estimator.tracker.snapshot.upgrade`); ValueError if the state is of
        another version or names a class this catalog does not have."""
        state = snapshot.upgrade(state)
        unknown = {t.obj_id for t in state["tracks"].values()} - set(self.catalog)
        if unknown:
            raise ValueError(f"estimator state: classes {sorted(unknown)} not in the catalog")
        self.book.tracks = dict(state["tracks"])
        self.book.serial = dict(state["serial"])
        self._size_ratios = dict(state["size_ratios"])
        self.book.held = dict(state["held"])
        self.book.view_serial = int(state["view_serial"])
        self.last_stamp_ns = state["last_stamp_ns"]
        self.poses.images = {}

    def banks(self) -> dict[int, TemplateBank]:
        """The template banks built or loaded so far (to share with other estimators)."""
        return self.poses.banks()

    def prepare_templates(self, workers: int = 2, progress=None) -> None:
        """Load or build every class's template bank now, building missing ones in ``workers``
        processes (see :func:`estimator.rotation.templates.build_template_banks`)."""
        self.poses.prepare_templates(workers, progress)

    def warm_up(self) -> None:
        """Everything a class needs before its first frame: its template bank (built or loaded)
        and its box-size ratio (~50 ms a class), and the verification's compiled kernels, so no
        frame pays for them."""
        if self.config.verification.enabled:
            compile_kernels()
        for obj_id in self.catalog:
            self.matcher(obj_id)
            self._size_ratio(obj_id)
            if self.config.verification.enabled:
                self.poses.model_edges(obj_id)

    def matcher(self, obj_id: int) -> RotationMatcher:
        """The rotation matcher of a class (its template bank built or loaded on first use)."""
        return self.poses.matcher(obj_id)

    def refinement_config(self, obj_id: int) -> RefineConfig:
        """The refinement's settings for a class (:meth:`PoseStage.refinement_config`)."""
        return self.poses.refinement_config(obj_id)

    # ---- the steps of an update -------------------------------------------------------------

    def _view_detections(
        self, frame: Frame, T_cam_world: np.ndarray, detections: list[Detection]
    ) -> tuple[ViewDetections, list[tuple[int, str]]]:
        """The view's detections checked (the skipped ones with why) and their centers
        undistorted; counts the view."""
        cam = frame.camera
        skipped: list[tuple[int, str]] = []
        usable: list[int] = []
        centers = np.zeros((len(detections), 2))
        for j, det in enumerate(detections):
            if det.obj_id not in self.catalog and not (
                det.obj_id == ANY_PART and frame.image is not None
            ):
                why = "a part with no image to name it by" if det.obj_id == ANY_PART else ""
                skipped.append((j, why or f"unknown class {det.obj_id}"))
                continue
            if not cam.contains(det.center_uv[None])[0]:
                skipped.append((j, "center outside the image"))
                continue
            centers[j] = cam.undistort_points(det.center_uv)  # covariance kept (local scale ~1)
            usable.append(j)
        self.book.view_serial += 1
        box_depths = {j: self._box_depth(detections[j], cam.K) for j in usable}
        view = ViewDetections(
            int(frame.stamp_ns),
            self.book.view_serial,
            cam,
            T_cam_world,
            detections,
            centers,
            tuple(usable),
            box_depths,
        )
        return view, skipped

    def _associate_class(self, view: ViewDetections, obj_id: int, changes: _Changes) -> None:
        """One class's detections against its tracks: matches join their track, tracks in view
        and unmatched count a miss, the rest are held and found tracks in pairs."""
        detections = view.detections
        det_idx = [j for j in view.usable if detections[j].obj_id == obj_id]
        tracks = self.book.of_class(obj_id)
        cost = cost_matrix(
            [t.view() for t in tracks],
            view.T_cam_world,
            view.K,
            view.centers[det_idx].reshape(-1, 2),
            np.array([detections[j].center_cov for j in det_idx]).reshape(-1, 2, 2),
            self.config.association,
        )
        matched_tracks, matched_dets = set(), set()
        for i, jj in assign(cost):
            j = det_idx[jj]
            track = tracks[i]
            ref = ViewRef(view.stamp_ns, j, view.box_depths[j])
            self.book.add_view(
                track, view.T_cam_world, view.K, view.centers[j], detections[j].center_cov, ref
            )
            matched_tracks.add(i)
            matched_dets.add(jj)
            changes.assigned.append((j, track.object_id))
            changes.touched.append(track.object_id)
        for i, track in enumerate(tracks):
            if i not in matched_tracks and self._predicted_in_view(track, view):
                track.misses += 1
                track.missed_views += 1
                self.book.review_support(track)
        new: list[HeldDetection] = []
        for jj, j in enumerate(det_idx):
            if jj in matched_dets:
                continue
            det = detections[j]
            # a box truncated by the image border says nothing of the depth: such a
            # detection is held, but founds a track only by triangulation
            truncated = self._touches_border(det, view.camera)
            new.append(
                HeldDetection(
                    obj_id,
                    view.stamp_ns,
                    view.view_serial,
                    view.T_cam_world,
                    view.K,
                    view.centers[j],
                    det.center_cov,
                    float("nan") if truncated else view.box_depths[j],
                    j,
                    det.mask,
                    det.mask_kind == "silhouette",
                )
            )
        pool = self.book.held.get(obj_id, [])
        founding = self.config.founding
        unnamed = obj_id == ANY_PART and ANY_PART not in self.catalog
        if unnamed:  # the box of "a part" bounds its depth only as loosely as the sizes differ
            spread = size_spread(self._sizes())
            founding = replace(founding, box_depth_factor=founding.box_depth_factor * spread)
        pairs = choose_pairs(pool, new, founding)
        named = pairs
        if unnamed:  # "a part": named as founded (estimator.tracker.naming)
            matchers = {c: self.matcher(c) for c in sorted(self.catalog)}
            both = [
                (p, name_pair(p, self.poses.images, matchers, self._sizes(), self.config.founding))
                for p in pairs
            ]
            pairs = [p for p, q in both if q is not None]
            named = [q for _, q in both if q is not None]
        paired = {id(p.older) for p in pairs} | {id(p.newer) for p in pairs}
        for pair in named:
            track = self.book.found_track(pair)
            changes.started.append((pair.newer.index, track.object_id))
            changes.touched.append(track.object_id)
        pool = [h for h in pool if id(h) not in paired]
        for h in new:
            if id(h) not in paired:
                pool.append(h)
                changes.held.append(h.index)
        # the tracks founded so far in this update, of every class walked yet, may take the
        # class's held detections
        scale = None
        if unnamed:  # an absorbed "a part" takes the box depth of the part its track is
            typical = any_part_size(self._sizes())
            scale = {c: size / typical for c, size in self._sizes().items()}
        pool = self.book.absorb_held(pool, [self.tracks[o] for _, o in changes.started], scale)
        self.book.keep_held(obj_id, pool)

    def _estimate(self, track: Track, stamp: int) -> ObjectEstimate:
        unasked = None
        if track.verdict is not None:
            self.poses.model_edges(track.obj_id)  # made by the verification (or a restore)
            unasked = self.poses.unasked[track.obj_id]
        allowance = None
        if self.config.bin is not None:  # how far outside the bin its centre may lie, metres
            margin = self.config.bin_margin_frac * self.catalog[track.obj_id].diameter
            allowance = (self.config.bin, margin)
        return published_estimate(
            track,
            stamp,
            self.catalog[track.obj_id].name,
            self.config.verification,
            unasked,
            allowance,
        )

    def _box_depth(self, det: Detection, K: np.ndarray) -> float:
        """The depth at which the part's expected box matches the detection's (SSD-6D); for
        "a part", that of a part of the catalog's typical size (``naming.any_part_size``)."""
        f = 0.5 * (K[0, 0] + K[1, 1])
        if det.obj_id == ANY_PART:
            size = any_part_size(self._sizes())
        else:
            size = self._size_ratio(det.obj_id) * self.catalog[det.obj_id].diameter
        return f * size / det.bbox_diagonal

    def _sizes(self) -> dict[int, float]:
        """Per class, its expected box diagonal at 1 m (metres); made once (the catalog is
        fixed)."""
        if self._part_sizes is None:
            self._part_sizes = {
                c: self._size_ratio(c) * self.catalog[c].diameter for c in sorted(self.catalog)
            }
        return self._part_sizes

    def _size_ratio(self, obj_id: int) -> float:
        if obj_id not in self._size_ratios:
            model = self.catalog[obj_id]
            self._size_ratios[obj_id] = bbox_diagonal_ratio(model.points, model.diameter)
        return self._size_ratios[obj_id]

    def _touches_border(self, det: Detection, cam: Camera) -> bool:
        x, y, w, h = det.bbox_xywh
        m = self.config.border_margin_px
        return x <= m or y <= m or x + w >= cam.width - m or y + h >= cam.height - m

    @staticmethod
    def _predicted_in_view(track: Track, view: ViewDetections) -> bool:
        T_cam_world, cam = view.T_cam_world, view.camera
        p = T_cam_world[:3, :3] @ track.estimate.t_world_obj + T_cam_world[:3, 3]
        if p[2] <= MIN_DEPTH:
            return False
        return bool(cam.contains(cam.project(p)[None], margin=10.0)[0])


def predicted_center(track: Track, T_cam_world: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(2,) the track's center projected into a camera (for tools and tests)."""
    one = CenterObservations.empty().append(T_cam_world, K, np.zeros(2), np.eye(2), 0)
    return predict(track.estimate.t_world_obj, one)[0][0]
