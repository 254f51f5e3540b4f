"""MultiViewEstimator: per-view detections in, object tracks with pose estimates out.

One call of :meth:`MultiViewEstimator.update` per view, in stamp order. It validates the frame
(nothing in the state changes if the frame is bad), associates the view's detections with the
tracks class by class (:mod:`estimator.translation.association`), re-estimates the translation of
every matched track from all its views (:mod:`estimator.translation.gaussian`), starts tentative
tracks from the unmatched detections, and drops tracks that should have been seen but were not.

Documented skips (counted in ``skipped`` of the last update, never an exception):

- a detection of a class the catalog does not have;
- a detection whose center lies outside the image;
- an unmatched detection whose box touches the image border does not start a track: the box of
  a truncated part says nothing reliable about its depth. It may still update a track.

The estimator is deterministic: it never reads the clock and has no randomness, so the same
sequence of updates gives the same estimates.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial.transform import Rotation

from posefuse.estimator.core.camera import Camera
from posefuse.estimator.core.geometry import rotation_angle
from posefuse.estimator.core.objects import Catalog
from posefuse.estimator.frontend.detection import Detection
from posefuse.estimator.rotation.matching import RotationConfig, RotationMatcher
from posefuse.estimator.rotation.mixture import MixtureConfig, RotationMixture
from posefuse.estimator.rotation.templates import (
    TemplateBank,
    TemplateConfig,
    build_template_bank,
    build_template_banks,
)
from posefuse.estimator.translation.association import (
    AssociationConfig,
    TrackView,
    assign,
    cost_matrix,
    innovation_cost,
)
from posefuse.estimator.translation.founding import (
    FoundingConfig,
    FoundingPair,
    HeldDetection,
    choose_pairs,
    pair_observations,
    triangulate_pair,
)
from posefuse.estimator.translation.gaussian import (
    MIN_DEPTH,
    CenterObservations,
    TranslationEstimate,
    bbox_diagonal_ratio,
    estimate_translation,
    marginalize_oldest,
    predict,
)
from posefuse.estimator.translation.merging import MergeCandidate, MergeConfig, merge_pairs
from posefuse.estimator.translation.splitting import SplitConfig, outlier_views
from posefuse.estimator.verification.edges import EdgeView, ModelEdges, edge_view, model_edges
from posefuse.estimator.verification.refinement import (
    RefineConfig,
    Refinement,
    accepts_translation,
    refine_pose,
)
from posefuse.estimator.verification.verify import (
    ScoreCache,
    Verdict,
    VerificationConfig,
    agrees,
    hypotheses,
    is_new_viewpoint,
    near_symmetries,
    refinement_reach_deg,
    verify,
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
    # a confirmed track is dropped after this many consecutive views that predicted it in view
    # without detecting it, or as many as it was seen in, whichever is more: in a pile a part
    # is hidden for a while as the camera moves, and evidence for it should outweigh its misses
    max_misses: int = 5
    max_misses_tentative: int = 2
    border_margin_px: float = 2.0  # a box this close to the border is truncated
    founding: FoundingConfig = FoundingConfig()
    merging: MergeConfig = MergeConfig()
    splitting: SplitConfig = SplitConfig()
    rotation: RotationConfig = RotationConfig()
    mixture: MixtureConfig = MixtureConfig()
    templates: TemplateConfig = TemplateConfig()
    # every view's hypotheses checked in all the track's views, then the pose refined over them
    verification: VerificationConfig = VerificationConfig()
    refinement: RefineConfig = RefineConfig()
    # a view's rotation is measured once the depth is known to this relative std; earlier
    # views of the track wait (their images are kept for up to max_pending_views frames)
    rotation_max_depth_rel_std: float = 0.05
    max_pending_views: int = 8
    # a track keeps this many views for its translation; older ones are folded into its prior
    max_track_views: int = 30

    def __post_init__(self) -> None:
        if self.confirm_views < 1 or self.max_misses < 1 or self.max_misses_tentative < 1:
            raise ValueError(f"invalid tracker config: {self}")

    @classmethod
    def with_verification(cls, enabled: bool) -> TrackerConfig:
        """The defaults, with the verification across views on or off."""
        return cls(verification=VerificationConfig(enabled=enabled))


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
    # per view of ``obs``, in its order: (stamp_ns, detection index, box depth in metres)
    refs: list[tuple[int, int, float]] = field(default_factory=list)
    mixture: RotationMixture | None = None
    views_seen: int = 1
    # views waiting for a good enough translation: (stamp_ns, T_cam_world, K, mask)
    pending: list[tuple[int, np.ndarray, np.ndarray, np.ndarray | None]] = field(
        default_factory=list
    )
    # the most recent views' edge maps (estimator.verification.edges), at most
    # verification.max_views
    edge_views: list[EdgeView] = field(default_factory=list)
    verdict: Verdict | None = None  # of the last verification, for the mixture as it was then
    scores: ScoreCache = field(default_factory=ScoreCache)  # per-view costs, reused
    refined: Refinement | None = None
    # the translation prior (3,) the refinement took, and the stamps of the views the refined
    # pose has been checked against (the settled check)
    refined_t_prior: np.ndarray | None = None
    settled_stamps: frozenset = frozenset()

    def view(self) -> TrackView:
        e = self.estimate
        return TrackView(e.t_world_obj, e.cov, self.obs)


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
        self._size_ratios: dict[int, float] = {}  # per class, for the box depth
        self._held: dict[int, list[HeldDetection]] = {}  # per class, waiting for a partner
        self._edges: dict[int, ModelEdges] = {}  # per class, for verification
        self._variants: dict[int, np.ndarray] = {}  # per class, near-symmetric turns
        # per class, the refinement's settings with its turn bounded by the class's basin
        self._refine_config: dict[int, RefineConfig] = {}
        self._view_serial = 0
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

        self._view_serial += 1
        assigned: list[tuple[int, str]] = []
        started: list[tuple[int, str]] = []
        held: list[int] = []
        touched: list[str] = []
        box_depths = {j: self._box_depth(detections[j], K) for j in usable}
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
            )
            matched_tracks, matched_dets = set(), set()
            for i, jj in assign(cost):
                j = det_idx[jj]
                track = tracks[i]
                self._add_view(
                    track,
                    T_cam_world,
                    K,
                    centers[j],
                    detections[j].center_cov,
                    stamp,
                    j,
                    box_depths[j],
                )
                matched_tracks.add(i)
                matched_dets.add(jj)
                assigned.append((j, track.object_id))
                touched.append(track.object_id)
            for i, track in enumerate(tracks):
                if i not in matched_tracks and self._predicted_in_view(track, T_cam_world, cam):
                    track.misses += 1
            new: list[HeldDetection] = []
            for jj, j in enumerate(det_idx):
                if jj in matched_dets:
                    continue
                det = detections[j]
                # a box truncated by the image border says nothing of the depth: such a
                # detection is held, but founds a track only by triangulation
                truncated = self._touches_border(det, cam)
                new.append(
                    HeldDetection(
                        obj_id,
                        stamp,
                        self._view_serial,
                        T_cam_world,
                        K,
                        centers[j],
                        det.center_cov,
                        float("nan") if truncated else box_depths[j],
                        j,
                        det.mask,
                    )
                )
            pool = self._held.get(obj_id, [])
            pairs = choose_pairs(pool, new, self.config.founding)
            paired = {id(p.older) for p in pairs} | {id(p.newer) for p in pairs}
            for pair in pairs:
                track = self._found_track(pair)
                started.append((pair.newer.index, track.object_id))
                touched.append(track.object_id)
            pool = [h for h in pool if id(h) not in paired]
            for h in new:
                if id(h) not in paired:
                    pool.append(h)
                    held.append(h.index)
            pool = self._absorb_held(pool, [self.tracks[o] for _, o in started])
            self._held[obj_id] = [
                h
                for h in pool
                if self._view_serial - h.view_serial <= self.config.founding.hold_views
            ]

        split = self._split_tracks(sorted(set(touched)))
        touched += [new_id for new_id, _ in split]
        merged = self._merge_tracks()
        absorbed = {a for a, _ in merged}
        touched = [k for k in dict.fromkeys(touched) if k not in absorbed]

        if frame.image is not None:
            self._images[stamp] = frame.image
            for stale in list(self._images)[: -self.config.max_pending_views]:  # oldest received
                del self._images[stale]
            for j, oid in assigned:
                if oid in self.tracks:
                    track = self.tracks[oid]
                    track.pending.append((stamp, T_cam_world, K, detections[j].mask))
                    del track.pending[: -self.config.max_pending_views]
            for oid in touched:
                self._measure_rotations(self.tracks[oid])

        dropped = [a for a, _ in merged]
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
        self.last_report = UpdateReport(
            tuple(assigned),
            tuple(started),
            tuple(dropped),
            tuple(skipped),
            tuple(held),
            tuple(merged),
            tuple(split),
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

    def held(self) -> list[HeldDetection]:
        """The detections waiting for a partner view to found a track, oldest first per class
        (parts seen in one view only)."""
        return [h for obj_id in sorted(self._held) for h in self._held[obj_id]]

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
        if object_id is None:
            self._held = {
                k: v for k, v in self._held.items() if class_id is not None and k != class_id
            }
        keys = [k for k, t in self.tracks.items() if class_id is None or t.obj_id == class_id]
        for k in keys:
            del self.tracks[k]
        return len(keys)

    STATE_VERSION = 2  # 2: tracks keep edge views, verdicts and score caches (verification)

    def export_state(self) -> dict:
        """The tracks and the counters that go with them, as plain picklable data: translation
        Gaussians, rotation mixtures, the views kept. Frames' images are not included (views
        still waiting for their rotation lose them). Restored by :meth:`import_state`."""
        return {
            "version": self.STATE_VERSION,
            "tracks": self.tracks,
            "serial": self._serial,
            "size_ratios": self._size_ratios,
            "held": self._held,
            "view_serial": self._view_serial,
            "last_stamp_ns": self.last_stamp_ns,
        }

    def import_state(self, state: dict) -> None:
        """Replace the tracks by those of :meth:`export_state`; ValueError if the state is of
        another version or names a class this catalog does not have."""
        if not isinstance(state, dict) or state.get("version") != self.STATE_VERSION:
            raise ValueError(f"estimator state: version must be {self.STATE_VERSION}")
        unknown = {t.obj_id for t in state["tracks"].values()} - set(self.catalog)
        if unknown:
            raise ValueError(f"estimator state: classes {sorted(unknown)} not in the catalog")
        self.tracks = dict(state["tracks"])
        self._serial = dict(state["serial"])
        self._size_ratios = dict(state["size_ratios"])
        self._held = dict(state["held"])
        self._view_serial = int(state["view_serial"])
        self.last_stamp_ns = state["last_stamp_ns"]
        self._images = {}

    # ---- internals --------------------------------------------------------------------------

    def banks(self) -> dict[int, TemplateBank]:
        """The template banks built or loaded so far (to share with other estimators)."""
        return {k: m.bank for k, m in self._matchers.items()}

    def prepare_templates(self, workers: int = 2, progress=None) -> None:
        """Load or build every class's template bank now, building missing ones in ``workers``
        processes (see :func:`estimator.rotation.templates.build_template_banks`)."""
        todo = [self.catalog[k] for k in self.catalog if k not in self._matchers]
        banks = build_template_banks(
            todo, self.config.templates, self._template_cache_dir, workers, progress
        )
        for obj_id, bank in banks.items():
            self._matchers[obj_id] = RotationMatcher(bank, self.config.rotation)

    def warm_up(self) -> None:
        """Everything a class needs before its first frame: its template bank (built or loaded)
        and its box-size ratio (~50 ms a class), so no frame pays for them."""
        for obj_id in self.catalog:
            self.matcher(obj_id)
            self._size_ratio(obj_id)
            if self.config.verification.enabled:
                self._model_edges(obj_id)

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
        vcfg = self.config.verification
        model = self.catalog[track.obj_id]
        added: list[int] = []  # stamps of the views kept
        for stamp, T_cam_world, K, mask in track.pending:
            image = self._images.get(stamp)
            if image is None:
                continue
            t_cam = T_cam_world[:3, :3] @ t_world + T_cam_world[:3, 3]
            for m in matcher.measure(image, K, t_cam, mask):
                R_world_obj = T_cam_world[:3, :3].T @ m.R_cam_obj
                track.mixture.add(R_world_obj, m.confidence)
            others = [v.T_cam_world for v in track.edge_views if v.stamp_ns != stamp]
            if (
                vcfg.enabled
                and t_cam[2] > MIN_DEPTH
                and is_new_viewpoint(
                    np.array(others).reshape(-1, 4, 4),
                    T_cam_world,
                    t_world,
                    vcfg.keyframe_deg,
                    vcfg.keyframe_distance_frac,
                )
            ):
                view = edge_view(
                    image, K, T_cam_world, t_cam, model.diameter, vcfg.edges, mask, stamp
                )
                track.edge_views = [v for v in track.edge_views if v.stamp_ns != stamp] + [view]
                del track.edge_views[: -vcfg.max_views]
                added.append(stamp)
        track.pending.clear()
        # verified again when a view adds to what the kept views show, unless the track is
        # settled and the view agrees with it, or when the mixture no longer has the
        # components the last verdict weighed
        verdict = track.verdict
        stale = verdict is None or len(verdict.weights) != len(track.mixture.components)
        if added and not stale and self._settled(track):
            track.settled_stamps = track.settled_stamps | set(added)
            return
        if (stale and track.edge_views) or added:
            self._verify(track, new_views=bool(added))

    def _settled(self, track: Track) -> bool:
        """Whether the track's refined pose still holds, so that verifying and refining again
        for the views just kept would change nothing (VerificationConfig.settled_margin):

        - the refinement was accepted, and the translation has moved less than
          ``settled_translation_frac`` of the diameter from the prior it took;
        - every kept view the pose has not yet been checked against agrees with it: in each,
          the pose costs at most ``settled_margin`` more than the best of the hypotheses a
          verification would ask about (:func:`estimator.verification.verify.agrees`: within each
          view, whose costs depend on what it sees, never across views).

        A settled track then costs those hypotheses scored in its new views instead of in every
        kept view, and no refinement. A mixture that changes is verified as before (keeping the
        refined pose without it lost a part on the tuning sets, docs/verification.md), and
        refined unless the winner still holds the refinement (``_verify``)."""
        vcfg = self.config.verification
        refined = track.refined
        if vcfg.settled_margin is None or refined is None or not refined.accepted:
            return False
        edges, variants = self._model_edges(track.obj_id)
        if (
            track.refined_t_prior is None
            or np.linalg.norm(track.estimate.t_world_obj - track.refined_t_prior)
            > vcfg.settled_translation_frac * edges.diameter
        ):
            return False
        new = [v for v in track.edge_views if v.stamp_ns not in track.settled_stamps]
        if len(new) == len(track.edge_views):
            return False
        if not new:
            return True
        components_R = np.array([c.R_world_obj for c in track.mixture.components])
        R_h, _, _ = hypotheses(components_R, track.mixture.weights, variants, vcfg)
        return agrees(
            edges, new, refined.R_world_obj, refined.t_world_obj, R_h, vcfg.settled_margin, vcfg
        )

    def refinement_config(self, obj_id: int) -> RefineConfig:
        """The refinement's settings for a class: the tracker's, its turn bounded by the part's
        basin (:func:`estimator.verification.verify.refinement_reach_deg`)."""
        self._model_edges(obj_id)
        return self._refine_config[obj_id]

    def _model_edges(self, obj_id: int) -> tuple[ModelEdges, np.ndarray]:
        """The class's edge samples and near-symmetric turns, and with them the refinement's
        settings for the class (:meth:`refinement_config`); computed on first use."""
        if obj_id not in self._edges:
            model = self.catalog[obj_id]
            cfg = self.config.verification
            self._edges[obj_id] = model_edges(model.mesh, model.diameter, cfg.edges)
            sym = np.concatenate([np.eye(3)[None], model.symmetries_discrete[:, :3, :3]])
            axes = np.array([c.axis for c in model.symmetries_continuous]).reshape(-1, 3)
            self._variants[obj_id] = near_symmetries(
                model.points, model.diameter, sym, axes, cfg.near_frac, cfg.max_variants
            )
            reach = refinement_reach_deg(self._variants[obj_id], sym, axes)
            rcfg = self.config.refinement
            self._refine_config[obj_id] = replace(rcfg, accept_deg=min(rcfg.accept_deg, reach))
        return self._edges[obj_id], self._variants[obj_id]

    def _verify(self, track: Track, new_views: bool = True) -> None:
        """Score the leading hypotheses in all kept views; refine the winner over them
        (:mod:`estimator.verification.verify`, :mod:`estimator.verification.refinement`).

        Without new views (the mixture gained or lost a component), a winner whose basin holds
        the last accepted refinement (within ``accept_deg``, and its translation a move from
        today's that a refinement would accept, ``refinement.accepts_translation``), at a
        translation that has moved less than
        ``settled_translation_frac`` of the diameter from that refinement's prior, keeps it: the
        kept views are the ones it was refined over or ones that agreed with it (``_settled``),
        so refining again from the same place would land where it did
        (``VerificationConfig.reuse_refinement``)."""
        mixture = track.mixture
        if mixture is None or not mixture.components or not track.edge_views:
            return
        edges, variants = self._model_edges(track.obj_id)
        vcfg = self.config.verification
        components_R = np.array([c.R_world_obj for c in mixture.components])
        verdict = verify(
            edges,
            track.edge_views,
            components_R,
            mixture.weights,
            variants,
            track.estimate.t_world_obj,
            vcfg,
            track.scores,
        )
        track.verdict = verdict
        rcfg = self.refinement_config(track.obj_id)
        previous, track.refined = track.refined, None
        if verdict is None or not rcfg.enabled:
            return
        lead = mixture.components[int(verdict.component[verdict.best])]
        R_start = verdict.R_world_obj[verdict.best]
        # the last refined pose, where it lies in the basin of today's start, is a warm start
        R_init = t_init = None
        if (
            previous is not None
            and previous.accepted
            and rotation_angle(previous.R_world_obj @ R_start.T) <= np.deg2rad(rcfg.accept_deg)
            and accepts_translation(
                previous.t_world_obj - track.estimate.t_world_obj,
                np.linalg.inv(track.estimate.cov),
                edges.diameter,
                rcfg,
            )
        ):
            R_init, t_init = previous.R_world_obj, previous.t_world_obj
        if (
            R_init is not None  # in the winner's basin, and near today's translation
            and not new_views
            and vcfg.reuse_refinement
            and track.refined_t_prior is not None
            and np.linalg.norm(track.estimate.t_world_obj - track.refined_t_prior)
            <= vcfg.settled_translation_frac * edges.diameter
        ):
            track.refined = previous
            return
        # the component's covariance, turned with its variant (a turn in the object frame
        # leaves a world-frame left perturbation as it is)
        track.refined_t_prior = track.estimate.t_world_obj.copy()
        track.settled_stamps = frozenset(v.stamp_ns for v in track.edge_views)
        track.refined = refine_pose(
            edges,
            track.edge_views,
            R_start,
            track.estimate.t_world_obj,
            track.estimate.t_world_obj,
            track.estimate.cov,
            lead.cov,
            vcfg.edges.truncate_px,
            vcfg.edges.bins,
            vcfg.crease_weight,
            vcfg.mask_weight,
            rcfg,
            R_init,
            t_init,
        )

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

    def _new_track(self, obj_id: int, obs, prior_mean, prior_cov, refs) -> Track:
        estimate = estimate_translation(obs, prior_mean, prior_cov)
        serial = self._serial.get(obj_id, 0) + 1
        self._serial[obj_id] = serial
        object_id = f"{self.catalog[obj_id].name}-{serial:03d}"
        stamps = [r[0] for r in refs]
        track = Track(
            object_id, obj_id, obs, prior_mean, prior_cov, estimate, min(stamps), max(stamps)
        )
        track.refs = list(refs)
        track.detections = [(r[0], r[1]) for r in refs]
        track.views_seen = len(refs)
        if len(obs) >= self.config.confirm_views:
            track.status = CONFIRMED
        self.tracks[object_id] = track
        return track

    def _found_track(self, pair: FoundingPair) -> Track:
        """A track from two held detections of different views
        (:mod:`estimator.translation.founding`)."""
        a, b = pair.older, pair.newer
        obs = pair_observations(a, b)
        refs = [(a.stamp_ns, a.index, a.box_depth), (b.stamp_ns, b.index, b.box_depth)]
        track = self._new_track(a.obj_id, obs, pair.prior_mean, pair.prior_cov, refs)
        for h in (a, b):
            track.pending.append((h.stamp_ns, h.T_cam_world, h.K, h.mask))
        return track

    def _absorb_held(self, pool: list[HeldDetection], tracks: list[Track]) -> list[HeldDetection]:
        """Held detections of earlier views that a just-founded track explains join it."""
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
            self._add_view(best, h.T_cam_world, h.K, h.uv, h.cov, h.stamp_ns, h.index, h.box_depth)
            best.pending.append((h.stamp_ns, h.T_cam_world, h.K, h.mask))
        return left

    def _add_view(self, track, T_cam_world, K, uv, cov, stamp, index, box_depth) -> None:
        track.obs = track.obs.append(T_cam_world, K, uv, cov, stamp)
        track.refs.append((stamp, index, box_depth))
        track.views_seen += 1
        if len(track.obs) > self.config.max_track_views:
            track.obs, track.prior_mean, track.prior_cov = marginalize_oldest(
                track.obs, track.prior_mean, track.prior_cov, track.estimate.t_world_obj
            )
            track.refs.pop(0)
        track.estimate = estimate_translation(
            track.obs, track.prior_mean, track.prior_cov, start=track.estimate.t_world_obj
        )
        track.last_stamp_ns = max(track.last_stamp_ns, stamp)
        track.misses = 0
        track.detections.append((stamp, index))
        if len(track.obs) >= self.config.confirm_views:
            track.status = CONFIRMED

    def _split_tracks(self, keys: list[str]) -> list[tuple[str, str]]:
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
            gone_ids = {(r[0], r[1]) for r in gone}
            gone_stamps = {r[0] for r in gone}
            track.edge_views = [v for v in track.edge_views if v.stamp_ns not in gone_stamps]
            track.detections = [d for d in track.detections if d not in gone_ids]
            track.views_seen -= len(gone)
            track.estimate = estimate_translation(
                track.obs, track.prior_mean, track.prior_cov, start=track.estimate.t_world_obj
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
                    gone[k][2],
                    gone[k][1],
                )
                for k in range(2)
            ]
            pair = triangulate_pair(first[0], first[1], self.config.founding)
            if pair is None:
                continue
            est = estimate_translation(split_obs, pair.prior_mean, pair.prior_cov)
            if np.any(est.chi2 > self.config.splitting.outlier_chi2):
                continue
            new = self._new_track(track.obj_id, split_obs, pair.prior_mean, pair.prior_cov, gone)
            out.append((new.object_id, key))
        return out

    def _merge_tracks(self) -> list[tuple[str, str]]:
        """Tracks of one class that converged merge into the one with more views
        (:mod:`estimator.translation.merging`). Returns (absorbed, survivor) pairs."""
        out = []
        for obj_id in sorted(self._classes()):
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
        if gone.status == CONFIRMED:
            keep.status = CONFIRMED
        keep.pending = sorted(keep.pending + gone.pending, key=lambda p: p[0])
        views = sorted(keep.edge_views + gone.edge_views, key=lambda v: v.stamp_ns)
        keep.edge_views = views[-self.config.verification.max_views :]
        keep.verdict, keep.refined = None, None  # the mixture changes: verified again next view
        keep.scores = ScoreCache()
        if gone.mixture is not None:
            if keep.mixture is None:
                keep.mixture = gone.mixture
            else:
                for comp in gone.mixture.components:
                    for R, c in comp.members:
                        keep.mixture.add(R, c)
        keep.estimate = estimate_translation(
            keep.obs, keep.prior_mean, keep.prior_cov, start=keep.estimate.t_world_obj
        )

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
            components = track.mixture.components
            R_components = np.array([c.R_world_obj for c in components])
            verdict = track.verdict
            if verdict is not None and len(verdict.weights) == len(components):
                # the verified hypothesis leads, with the refined pose when it was accepted
                lead = int(verdict.component[verdict.best])
                best = components[lead]
                weights = verdict.weights
                R_components[lead] = verdict.R_world_obj[verdict.best]
                T[:3, :3] = R_components[lead]
                cov[3:, 3:] = best.cov
                refined = track.refined
                if refined is not None and refined.accepted:
                    T[:3, :3] = R_components[lead] = refined.R_world_obj
                    T[:3, 3] = refined.t_world_obj
                    cov = refined.cov.copy()
            quats = Rotation.from_matrix(R_components).as_quat()
            hypotheses = tuple(
                RotationHypothesis(q, float(w), c.n)
                for c, w, q in zip(components, weights, quats, strict=True)
            )
            mean_similarity = best.confidence / best.n
            confidence = float(weights[components.index(best)] * mean_similarity)
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


def _T(obs: CenterObservations, k: int) -> np.ndarray:
    """(4, 4) T_cam_world of view ``k``."""
    T = np.eye(4)
    T[:3, :3] = obs.R_cam_world[k]
    T[:3, 3] = obs.t_cam_world[k]
    return T


def predicted_center(track: Track, T_cam_world: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(2,) the track's center projected into a camera (for tools and tests)."""
    one = CenterObservations.empty().append(T_cam_world, K, np.zeros(2), np.eye(2), 0)
    return predict(track.estimate.t_world_obj, one)[0][0]
