"""MultiViewEstimator: per-view detections in, object tracks with pose estimates out.

One call of :meth:`MultiViewEstimator.update` per view, in stamp order. It validates the frame
(nothing in the state changes if the frame is bad), associates the view's detections with the
tracks class by class (:mod:`estimator.association`), re-estimates the translation of every
matched track from all its views (:mod:`estimator.translation`), starts tentative tracks from
the unmatched detections, and drops tracks that should have been seen but were not.

Documented skips (counted in ``skipped`` of the last update, never an exception):

- a detection of a class the catalog does not have;
- a detection whose center lies outside the image;
- an unmatched detection whose box touches the image border does not start a track: the box of
  a truncated part says nothing reliable about its depth. It may still update a track.

The estimator is deterministic: it never reads the clock and has no randomness, so the same
sequence of updates gives the same estimates.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from estimator.association import (
    AssociationConfig,
    TrackView,
    assign,
    cost_matrix,
)
from estimator.camera import Camera
from estimator.frontend.detection import Detection
from estimator.mixture import MixtureConfig, RotationMixture
from estimator.objects import Catalog
from estimator.rotation import RotationConfig, RotationMatcher
from estimator.templates import TemplateBank, TemplateConfig, build_template_bank
from estimator.translation import (
    MIN_DEPTH,
    PRIOR_DEPTH_REL_SIGMA,
    CenterObservations,
    TranslationEstimate,
    bbox_diagonal_ratio,
    estimate_translation,
    marginalize_oldest,
    predict,
    prior_from_first_view,
)

TENTATIVE = "tentative"
CONFIRMED = "confirmed"
ROTATION_UNKNOWN_VAR = np.pi**2 / 3  # variance of a rotation angle uniform on [-pi, pi]


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


@dataclass(frozen=True, eq=False)
class RotationHypothesis:
    """One mode of an object's rotation: q [x, y, z, w] in the world frame, its weight, and the
    number of views that support it."""

    q: np.ndarray  # (4,)
    weight: float
    n: int


@dataclass(frozen=True, eq=False)
class ObjectEstimate:
    """The state of one object track, as published (DESIGN section 4).

    T_world_obj: (4, 4) metres; cov: (6, 6) in the order x, y, z, rot_x, rot_y, rot_z (metres,
    radians; rotation as a left perturbation in the world frame).
    """

    stamp_ns: int
    object_id: str
    class_id: int
    class_name: str
    T_world_obj: np.ndarray
    cov: np.ndarray
    confidence: float
    hypotheses: tuple[RotationHypothesis, ...]
    n_views: int
    status: str
    frame_id: str = "world"

    @property
    def t_world_obj(self) -> np.ndarray:
        return self.T_world_obj[:3, 3]


@dataclass(frozen=True)
class TrackerConfig:
    association: AssociationConfig = AssociationConfig()
    confirm_views: int = 2  # views before a track is confirmed
    max_misses: int = 3  # consecutive views predicting a confirmed track in view, without it
    max_misses_tentative: int = 2
    border_margin_px: float = 2.0  # a box this close to the border is truncated
    prior_depth_rel_sigma: float = PRIOR_DEPTH_REL_SIGMA
    rotation: RotationConfig = RotationConfig()
    mixture: MixtureConfig = MixtureConfig()
    templates: TemplateConfig = TemplateConfig()
    # a view's rotation is measured once the depth is known to this relative std; earlier
    # views of the track wait (their images are kept for up to max_pending_views frames)
    rotation_max_depth_rel_std: float = 0.05
    max_pending_views: int = 8
    # a track keeps this many views for its translation; older ones are folded into its prior
    max_track_views: int = 30

    def __post_init__(self) -> None:
        if self.confirm_views < 1 or self.max_misses < 1 or self.max_misses_tentative < 1:
            raise ValueError(f"invalid tracker config: {self}")


@dataclass(eq=False)
class Track:
    object_id: str
    obj_id: int
    obs: CenterObservations
    prior_mean: np.ndarray
    prior_cov: np.ndarray
    estimate: TranslationEstimate
    first_stamp_ns: int
    last_stamp_ns: int
    misses: int = 0
    status: str = TENTATIVE
    detections: list[tuple[int, int]] = field(default_factory=list)  # (stamp_ns, index)
    mixture: RotationMixture | None = None
    views_seen: int = 1
    # views waiting for a good enough translation: (stamp_ns, T_cam_world, K, mask)
    pending: list[tuple[int, np.ndarray, np.ndarray, np.ndarray | None]] = field(
        default_factory=list
    )

    def view(self) -> TrackView:
        e = self.estimate
        return TrackView(e.t_world_obj, e.cov, self.obs, self.prior_mean, self.prior_cov, e.cost)


@dataclass(frozen=True)
class UpdateReport:
    """What one update did: (detection index, object_id) pairs, and skipped detections."""

    assigned: tuple[tuple[int, str], ...]
    started: tuple[tuple[int, str], ...]
    dropped: tuple[str, ...]
    skipped: tuple[tuple[int, str], ...]


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
        RotationMeasurements; the benchmarks use it for the multi-scale ablation)."""
        self.catalog = catalog
        self.config = config or TrackerConfig()
        self._matchers = {
            k: RotationMatcher(b, self.config.rotation) for k, b in (banks or {}).items()
        }
        self._matchers.update(matchers or {})
        self._template_cache_dir = template_cache_dir
        self._show_progress = show_progress
        self._images: dict[int, np.ndarray] = {}  # stamp_ns -> image, the last few frames
        self.tracks: dict[str, Track] = {}
        self._serial: dict[int, int] = {}
        self._size_ratios: dict[int, float] = {}  # per class, for the first-view depth
        self.last_report = UpdateReport((), (), (), ())
        self.last_stamp_ns: int | None = None

    # ---- public API -------------------------------------------------------------------------

    def update(self, frame: Frame, detections: list[Detection]) -> list[ObjectEstimate]:
        """Fuse one view. Returns the estimates of the tracks this view matched or started."""
        T_world_cam = validate_pose(frame.T_world_cam)
        stamp = int(frame.stamp_ns)
        cam = frame.camera
        T_cam_world = np.eye(4)
        T_cam_world[:3, :3] = T_world_cam[:3, :3].T
        T_cam_world[:3, 3] = -T_world_cam[:3, :3].T @ T_world_cam[:3, 3]
        K = cam.K

        skipped: list[tuple[int, str]] = []
        usable: list[int] = []
        centers = np.zeros((len(detections), 2))
        for j, det in enumerate(detections):
            if det.obj_id not in self.catalog:
                skipped.append((j, f"unknown class {det.obj_id}"))
                continue
            if not cam.contains(det.center_uv[None])[0]:
                skipped.append((j, "center outside the image"))
                continue
            centers[j] = cam.undistort_points(det.center_uv)  # covariance kept (local scale ~1)
            usable.append(j)

        assigned: list[tuple[int, str]] = []
        started: list[tuple[int, str]] = []
        touched: list[str] = []
        for obj_id in sorted({detections[j].obj_id for j in usable} | self._classes()):
            det_idx = [j for j in usable if detections[j].obj_id == obj_id]
            track_ids = [k for k, t in self.tracks.items() if t.obj_id == obj_id]
            tracks = [self.tracks[k] for k in track_ids]
            cost = cost_matrix(
                [t.view() for t in tracks],
                T_cam_world,
                K,
                centers[det_idx].reshape(-1, 2),
                np.array([detections[j].center_cov for j in det_idx]).reshape(-1, 2, 2),
                self.config.association,
                np.array([self._box_depth(detections[j], K) for j in det_idx]),
            )
            matched_tracks, matched_dets = set(), set()
            for i, jj in assign(cost):
                j = det_idx[jj]
                track = tracks[i]
                self._add_view(track, T_cam_world, K, centers[j], detections[j], stamp, j)
                matched_tracks.add(i)
                matched_dets.add(jj)
                assigned.append((j, track.object_id))
                touched.append(track.object_id)
            for i, track in enumerate(tracks):
                if i not in matched_tracks and self._predicted_in_view(track, T_cam_world, cam):
                    track.misses += 1
            for jj, j in enumerate(det_idx):
                if jj in matched_dets:
                    continue
                det = detections[j]
                if self._touches_border(det, cam):
                    skipped.append((j, "unmatched and truncated by the image border"))
                    continue
                track = self._start_track(T_world_cam, T_cam_world, K, centers[j], det, stamp, j)
                started.append((j, track.object_id))
                touched.append(track.object_id)

        if frame.image is not None:
            self._images[stamp] = frame.image
            for stale in sorted(self._images)[: -self.config.max_pending_views]:
                del self._images[stale]
            index_of = dict(assigned + started)
            for j, oid in assigned + started:
                track = self.tracks[oid]
                track.pending.append((stamp, T_cam_world, K, detections[j].mask))
                del track.pending[: -self.config.max_pending_views]
            for oid in index_of.values():
                self._measure_rotations(self.tracks[oid])

        dropped = []
        for key in list(self.tracks):
            t = self.tracks[key]
            limit = (
                self.config.max_misses
                if t.status == CONFIRMED
                else self.config.max_misses_tentative
            )
            if t.misses >= limit:
                dropped.append(key)
                del self.tracks[key]
        self.last_report = UpdateReport(
            tuple(assigned), tuple(started), tuple(dropped), tuple(skipped)
        )
        self.last_stamp_ns = stamp
        return [self._estimate(self.tracks[k], stamp) for k in touched if k in self.tracks]

    def estimates(self, include_tentative: bool = True) -> list[ObjectEstimate]:
        """All current tracks, in object_id order."""
        stamp = self.last_stamp_ns or 0
        return [
            self._estimate(self.tracks[k], stamp)
            for k in sorted(self.tracks)
            if include_tentative or self.tracks[k].status == CONFIRMED
        ]

    def reset(self, class_id: int | None = None, object_id: str | None = None) -> int:
        """Forget all tracks, those of one class, or one object. Returns how many were removed.

        Object ids are never reused, so a subscriber cannot confuse a new track with a forgotten
        one.
        """
        if class_id is not None and object_id is not None:
            raise ValueError("reset: give a class or an object, not both")
        if object_id is not None:
            if object_id not in self.tracks:
                raise KeyError(object_id)
            del self.tracks[object_id]
            return 1
        keys = [k for k, t in self.tracks.items() if class_id is None or t.obj_id == class_id]
        for k in keys:
            del self.tracks[k]
        return len(keys)

    # ---- internals --------------------------------------------------------------------------

    def banks(self) -> dict[int, TemplateBank]:
        """The template banks built or loaded so far (to share with other estimators)."""
        return {k: m.bank for k, m in self._matchers.items()}

    def matcher(self, obj_id: int) -> RotationMatcher:
        """The rotation matcher of a class (its template bank built or loaded on first use)."""
        if obj_id not in self._matchers:
            bank = build_template_bank(
                self.catalog[obj_id],
                self.config.templates,
                self._template_cache_dir,
                show_progress=self._show_progress,
            )
            self._matchers[obj_id] = RotationMatcher(bank, self.config.rotation)
        return self._matchers[obj_id]

    def _translation_known(self, track: Track, T_cam_world: np.ndarray) -> bool:
        t = track.estimate.t_world_obj
        p = T_cam_world[:3, :3] @ t + T_cam_world[:3, 3]
        if p[2] <= MIN_DEPTH:
            return False
        ray_world = T_cam_world[:3, :3].T @ (p / np.linalg.norm(p))
        depth_std = np.sqrt(ray_world @ track.estimate.cov @ ray_world)
        return depth_std / p[2] <= self.config.rotation_max_depth_rel_std

    def _measure_rotations(self, track: Track) -> None:
        """Measure the rotation in the track's waiting views, once its translation allows."""
        if not track.pending or not self._translation_known(track, track.pending[-1][1]):
            return
        if track.mixture is None:
            track.mixture = RotationMixture.for_model(
                self.catalog[track.obj_id], self.config.mixture
            )
        matcher = self.matcher(track.obj_id)
        t_world = track.estimate.t_world_obj
        for stamp, T_cam_world, K, mask in track.pending:
            image = self._images.get(stamp)
            if image is None:
                continue
            t_cam = T_cam_world[:3, :3] @ t_world + T_cam_world[:3, 3]
            for m in matcher.measure(image, K, t_cam, mask):
                R_world_obj = T_cam_world[:3, :3].T @ m.R_cam_obj
                track.mixture.add(R_world_obj, m.confidence)
        track.pending.clear()

    def _box_depth(self, det: Detection, K: np.ndarray) -> float:
        """The depth at which the part's expected box matches the detection's (SSD-6D)."""
        f = 0.5 * (K[0, 0] + K[1, 1])
        size = self._size_ratio(det.obj_id) * self.catalog[det.obj_id].diameter
        return f * size / det.bbox_diagonal

    def _size_ratio(self, obj_id: int) -> float:
        if obj_id not in self._size_ratios:
            model = self.catalog[obj_id]
            self._size_ratios[obj_id] = bbox_diagonal_ratio(model.points, model.diameter)
        return self._size_ratios[obj_id]

    def _classes(self) -> set[int]:
        return {t.obj_id for t in self.tracks.values()}

    def _touches_border(self, det: Detection, cam: Camera) -> bool:
        x, y, w, h = det.bbox_xywh
        m = self.config.border_margin_px
        return x <= m or y <= m or x + w >= cam.width - m or y + h >= cam.height - m

    def _predicted_in_view(self, track: Track, T_cam_world: np.ndarray, cam: Camera) -> bool:
        p = T_cam_world[:3, :3] @ track.estimate.t_world_obj + T_cam_world[:3, 3]
        if p[2] <= MIN_DEPTH:
            return False
        return bool(cam.contains(cam.project(p)[None], margin=10.0)[0])

    def _start_track(self, T_world_cam, T_cam_world, K, uv, det, stamp, index) -> Track:
        model = self.catalog[det.obj_id]
        prior_mean, prior_cov = prior_from_first_view(
            T_world_cam,
            K,
            uv,
            det.bbox_diagonal,
            model.diameter,
            self.config.prior_depth_rel_sigma,
            self._size_ratio(det.obj_id),
        )
        obs = CenterObservations.empty().append(T_cam_world, K, uv, det.center_cov, stamp)
        estimate = estimate_translation(obs, prior_mean, prior_cov)
        serial = self._serial.get(det.obj_id, 0) + 1
        self._serial[det.obj_id] = serial
        object_id = f"{model.name}-{serial:03d}"
        track = Track(object_id, det.obj_id, obs, prior_mean, prior_cov, estimate, stamp, stamp)
        track.detections.append((stamp, index))
        if self.config.confirm_views <= 1:
            track.status = CONFIRMED
        self.tracks[object_id] = track
        return track

    def _add_view(self, track, T_cam_world, K, uv, det, stamp, index) -> None:
        track.obs = track.obs.append(T_cam_world, K, uv, det.center_cov, stamp)
        track.views_seen += 1
        if len(track.obs) > self.config.max_track_views:
            track.obs, track.prior_mean, track.prior_cov = marginalize_oldest(
                track.obs, track.prior_mean, track.prior_cov, track.estimate.t_world_obj
            )
        track.estimate = estimate_translation(
            track.obs, track.prior_mean, track.prior_cov, start=track.estimate.t_world_obj
        )
        track.last_stamp_ns = stamp
        track.misses = 0
        track.detections.append((stamp, index))
        if len(track.obs) >= self.config.confirm_views:
            track.status = CONFIRMED

    def _estimate(self, track: Track, stamp: int) -> ObjectEstimate:
        T = np.eye(4)
        T[:3, 3] = track.estimate.t_world_obj
        cov = np.zeros((6, 6))
        cov[:3, :3] = track.estimate.cov
        cov[3:, 3:] = np.eye(3) * ROTATION_UNKNOWN_VAR
        confidence = 0.0
        hypotheses: tuple[RotationHypothesis, ...] = ()
        best = track.mixture.best() if track.mixture is not None else None
        if best is not None:
            T[:3, :3] = best.R_world_obj
            cov[3:, 3:] = best.cov
            weights = track.mixture.weights
            hypotheses = tuple(
                RotationHypothesis(Rotation.from_matrix(c.R_world_obj).as_quat(), float(w), c.n)
                for c, w in zip(track.mixture.components, weights, strict=True)
            )
            mean_similarity = best.confidence / best.n
            confidence = float(weights.max() * mean_similarity)
        return ObjectEstimate(
            stamp_ns=stamp,
            object_id=track.object_id,
            class_id=track.obj_id,
            class_name=self.catalog[track.obj_id].name,
            T_world_obj=T,
            cov=cov,
            confidence=confidence,
            hypotheses=hypotheses,
            n_views=track.views_seen,
            status=track.status,
        )


def predicted_center(track: Track, T_cam_world: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(2,) the track's center projected into a camera (for tools and tests)."""
    one = CenterObservations.empty().append(T_cam_world, K, np.zeros(2), np.eye(2), 0)
    return predict(track.estimate.t_world_obj, one)[0][0]
