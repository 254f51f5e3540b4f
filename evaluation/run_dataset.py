"""Runs the estimator over a BOP dataset, one view at a time in im_id order, and measures it.

Each scene gets a fresh :class:`MultiViewEstimator`. After the views listed in ``checkpoints``
(2, 4, 8 by default: a track is founded on two views) every confirmed track is scored against
the ground truth: its instance is the one most of its detections came from (the front end's
labels know it), and its translation error is measured in the world frame and relative to the
distance from the last camera.
"""

from __future__ import annotations

import csv
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from posefuse.estimator.tracker import CONFIRMED, Frame, MultiViewEstimator, TrackerConfig
from posefuse.evaluation.ambiguity import AmbiguityRow, ambiguity_rows
from posefuse.evaluation.fates import InstanceFate, TrackPose, instance_fates
from posefuse.evaluation.oracle import OracleFrontend
from posefuse.evaluation.scores import PoseResult
from posefuse.evaluation.tracking import (
    AssociationScore,
    association_score,
    nees,
    pose_nees,
    track_identities,
    update_members,
)

CHECKPOINTS = (2, 4, 8)  # a track needs two views (estimator.translation.founding)


class LabelledNetworkFrontend:
    """A learned front end run on a dataset's images, its detections labelled with the ground
    truth they lie on (same class, center within ``max_px``; -1 otherwise) for scoring only:
    the labels never reach the estimator."""

    def __init__(self, dataset, network, max_px: float = 15.0):
        self.dataset = dataset
        self.network = network
        self.max_px = max_px
        self._last = None  # (scene_id, im_id), image

    def _image(self, view):
        """The view's image, read once for both calls of a view."""
        key = (view.scene_id, view.im_id)
        if self._last is None or self._last[0] != key:
            self._last = (key, self.dataset.scene(view.scene_id).load_rgb(view.im_id))
        return self._last[1]

    def detect_with_truth(self, view):
        image = self._image(view)
        dets = self.network.detect(image)
        return self._labelled(dets, view)

    def detect_expected_with_truth(self, view, expected):
        """Stage two where the tracks expect parts the detections miss
        (:meth:`NetworkFrontend.detect_at`), labelled as :meth:`detect_with_truth`'s."""
        image = self._image(view)
        dets = self.network.detect_at(image, expected)
        return self._labelled(dets, view)

    def _labelled(self, dets, view):
        from posefuse.evaluation.frontend_metrics import match_to_truth

        # a generalist's "a part" lies on a part of any class (the tracker names it later)
        any_class = bool(getattr(self.network.card, "agnostic", False))
        gts, _, pairs = match_to_truth(dets, view, self.max_px, any_class=any_class)
        labels = [gts[pairs[i]].gt_idx if i in pairs else -1 for i in range(len(dets))]
        return list(zip(dets, labels, strict=True))


@dataclass(frozen=True)
class TranslationRow:
    scene_id: int
    n_views: int
    object_id: str
    obj_id: int
    gt_idx: int
    error_m: float
    rel_error: float  # error / distance from the camera of the last view
    nees: float
    status: str
    # as the track was published at the checkpoint: confirmed, or tentative when no pose of
    # the part fits its views or its centre lies outside the bin the cell knows
    published: str = ""


@dataclass(frozen=True)
class DatasetRun:
    """rows: translation errors; association: its score; results: per checkpoint, the pose
    estimates expressed in the checkpoint's view (BOP results), and targets: the views scored;
    fates: where each scored instance ended at each checkpoint (with the rotation step)."""

    rows: tuple[TranslationRow, ...]
    association: AssociationScore
    results: dict[int, list[PoseResult]]
    targets: dict[int, list[tuple[int, int]]]
    fates: tuple[InstanceFate, ...] = ()
    # per checkpoint, the NEES (translation, rotation) of each published pose of a confirmed
    # track against its instance (visib_fract > 0.75), with the rotation step
    pose_nees: dict[int, list[tuple[float, float]]] = field(default_factory=dict)
    # per checkpoint, of the same poses: how each was published and how it fared
    ambiguity: dict[int, list[AmbiguityRow]] = field(default_factory=dict)


def run_dataset(
    dataset,
    frontend: OracleFrontend,
    config: TrackerConfig | None = None,
    checkpoints: tuple[int, ...] = CHECKPOINTS,
    scene_ids: tuple[int, ...] | None = None,
    show_progress: bool = True,
    rotation: bool = False,
    estimator_factory=None,
    track_crops: bool = False,
) -> DatasetRun:
    """Run scene by scene. With ``rotation`` the images are read and the rotation step runs
    too (the front end must give masks); ``estimator_factory`` makes each scene's estimator
    (default: ``MultiViewEstimator(dataset.catalog, config)``). With ``track_crops`` the front
    end (a :class:`LabelledNetworkFrontend`) also looks where the tracks expect parts that its
    detections miss (:meth:`MultiViewEstimator.expected_parts`)."""
    rows: list[TranslationRow] = []
    fates: list[InstanceFate] = []
    results: dict[int, list[PoseResult]] = {n: [] for n in checkpoints}
    covariance: dict[int, list[tuple[float, float]]] = {n: [] for n in checkpoints}
    ambiguity: dict[int, list[AmbiguityRow]] = {n: [] for n in checkpoints}
    targets: dict[int, list[tuple[int, int]]] = {n: [] for n in checkpoints}
    members_all: dict[str, list[int]] = {}
    confirmed_all: set[str] = set()
    n_true = 0
    scene_ids = dataset.scene_ids if scene_ids is None else scene_ids
    n_views_total = sum(len(dataset.scene(s).im_ids) for s in scene_ids)
    bar = tqdm(total=n_views_total, desc="views", unit="view", disable=not show_progress)
    for scene_id in scene_ids:
        scene = dataset.scene(scene_id)
        estimator = (
            estimator_factory()
            if estimator_factory
            else MultiViewEstimator(dataset.catalog, config)
        )
        members: dict[str, list[int]] = defaultdict(list)
        labels: dict[int, list[int]] = {}  # stamp -> the instance of each detection
        for count, im_id in enumerate(scene.im_ids, start=1):
            view = scene.view(im_id)
            pairs = frontend.detect_with_truth(view)
            if track_crops:
                expected = estimator.expected_parts(
                    view.camera, view.T_world_cam, [d for d, _ in pairs]
                )
                pairs += frontend.detect_expected_with_truth(view, expected)
            n_true += sum(k >= 0 for _, k in pairs)
            image = scene.load_rgb(im_id) if rotation else None
            stamp = count * 100_000_000
            labels[stamp] = [k for _, k in pairs]
            estimator.update(
                Frame(stamp, view.camera, view.T_world_cam, image), [d for d, _ in pairs]
            )
            update_members(members, estimator.tracks, estimator.last_report.merged, labels)
            bar.update(1)
            if count not in checkpoints:
                continue
            targets[count].append((scene_id, im_id))
            poses = []
            estimates = estimator.estimates(include_tentative=True)
            published = {e.object_id: e.status for e in estimates}
            for e in estimates:
                reported = bool(e.hypotheses) and (count == 1 or e.status == CONFIRMED)
                T_cam_obj = view.T_cam_world @ e.T_world_obj if reported else None
                poses.append(TrackPose(e.object_id, e.class_id, e.confidence, T_cam_obj))
                if reported:
                    results[count].append(
                        PoseResult(scene_id, im_id, e.class_id, e.confidence, T_cam_obj)
                    )
            if rotation:
                fates += instance_fates(
                    view,
                    dataset.catalog,
                    count,
                    poses,
                    dict(members),
                    detected=Counter(k for seen in labels.values() for k in set(seen) if k >= 0),
                )
            identity = track_identities(members)
            if rotation:
                covariance[count] += _published_nees(estimates, view, identity, dataset.catalog)
                ambiguity[count] += ambiguity_rows(
                    _scored(estimates, view, identity), dataset.catalog, count
                )
            cam_centre = view.T_world_cam[:3, 3]
            for oid, track in sorted(estimator.tracks.items()):
                gt_idx = identity.get(oid, -1)
                if gt_idx < 0 or (count > 1 and track.status != CONFIRMED):
                    continue
                gt = view.gts[gt_idx]
                t_true = (view.T_world_cam @ gt.T_cam_obj)[:3, 3]
                error = track.estimate.t_world_obj - t_true
                rows.append(
                    TranslationRow(
                        scene_id,
                        count,
                        oid,
                        track.obj_id,
                        gt_idx,
                        float(np.linalg.norm(error)),
                        float(np.linalg.norm(error) / np.linalg.norm(t_true - cam_centre)),
                        nees(error, track.estimate.cov),
                        track.status,
                        published.get(oid, ""),
                    )
                )
        for oid, m in members.items():  # instance indices made unique across scenes
            members_all[f"{scene_id}/{oid}"] = [-1 if x < 0 else (scene_id, x) for x in m]
        confirmed_all |= {
            f"{scene_id}/{k}" for k, t in estimator.tracks.items() if t.status == CONFIRMED
        }
    bar.close()
    score = association_score(members_all, confirmed_all, n_true)
    return DatasetRun(tuple(rows), score, results, targets, tuple(fates), covariance, ambiguity)


def _scored(estimates, view, identity, min_visib: float = 0.75):
    """(estimate, T_world_true) of the published poses of confirmed tracks whose instance
    (of their class) shows more than ``min_visib`` in ``view``."""
    gts = {gt.gt_idx: gt for gt in view.gts if gt.visib_fract > min_visib}
    for e in estimates:
        gt = gts.get(identity.get(e.object_id, -1))
        if gt is None or not e.hypotheses or e.status != CONFIRMED or gt.obj_id != e.class_id:
            continue
        yield e, view.T_world_cam @ gt.T_cam_obj


def _published_nees(estimates, view, identity, catalog, min_visib: float = 0.75):
    """(translation, rotation) NEES of each published pose of a confirmed track, among
    ``estimates`` (ObjectEstimate), whose instance shows more than ``min_visib`` in ``view``
    (:func:`evaluation.tracking.pose_nees`)."""
    out = []
    for e, T_true in _scored(estimates, view, identity, min_visib):
        model = catalog[e.class_id]
        discrete = np.concatenate([np.eye(3)[None], model.symmetries_discrete[:, :3, :3]])
        axes = np.array([c.axis for c in model.symmetries_continuous]).reshape(-1, 3)
        out.append(pose_nees(e.T_world_obj, e.cov, T_true, discrete, axes))
    return out


def write_fates(path: str | Path, fates: tuple[InstanceFate, ...]) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(["scene_id", "im_id", "n_views", "obj_id", "gt_idx", "fate", "detected_views"])
        for x in fates:
            w.writerow(
                [x.scene_id, x.im_id, x.n_views, x.obj_id, x.gt_idx, x.fate, x.detected_views]
            )
    return path


def write_rows(path: str | Path, rows: tuple[TranslationRow, ...]) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(
            [
                "scene_id",
                "n_views",
                "object_id",
                "obj_id",
                "gt_idx",
                "error_mm",
                "rel_error",
                "nees",
                "status",
                "published",
            ]
        )
        for r in rows:
            w.writerow(
                [
                    r.scene_id,
                    r.n_views,
                    r.object_id,
                    r.obj_id,
                    r.gt_idx,
                    f"{r.error_m * 1000:.4f}",
                    f"{r.rel_error:.6f}",
                    f"{r.nees:.4f}",
                    r.status,
                    r.published,
                ]
            )
    return path


def summary_markdown(run: DatasetRun, catalog, checkpoints: tuple[int, ...] = CHECKPOINTS) -> str:
    """Median translation error per object at each checkpoint, and the association score."""
    head = " | ".join(f"{n} view{'s' if n > 1 else ''}" for n in checkpoints)
    lines = [
        f"| object | {head} |",
        "|---|" + "---|" * len(checkpoints),
    ]
    groups: dict[tuple[int, int], list[TranslationRow]] = defaultdict(list)
    for r in run.rows:
        groups[(r.obj_id, r.n_views)].append(r)

    def cell(rs: list[TranslationRow]) -> str:
        if not rs:
            return "-"
        mm = np.median([r.error_m for r in rs]) * 1000
        rel = np.median([r.rel_error for r in rs]) * 100
        return f"{mm:.1f} mm ({rel:.2f}%, n={len(rs)})"

    for obj_id, model in catalog.items():
        cells = " | ".join(cell(groups[(obj_id, n)]) for n in checkpoints)
        lines.append(f"| {model.name} | {cells} |")
    cells = " | ".join(cell([r for r in run.rows if r.n_views == n]) for n in checkpoints)
    lines.append(f"| all | {cells} |")
    last = [r.nees for r in run.rows if r.n_views == max(checkpoints)]
    a = run.association
    lines += [
        "",
        f"Association: precision {a.precision:.4f}, recall {a.recall:.4f} "
        f"({a.n_true_detections} true detections).",
    ]
    if last:
        lines.append(
            f"Mean NEES of the 3D translation after {max(checkpoints)} views: "
            f"{np.mean(last):.2f} (expected 3), median {np.median(last):.2f} (expected 2.37)."
        )
        final = [r for r in run.rows if r.n_views == max(checkpoints) and r.published]
        shown = [r.nees for r in final if r.published == CONFIRMED]
        if final:
            figures = f"mean {np.mean(shown):.2f}, median {np.median(shown):.2f}" if shown else "-"
            lines.append(
                f"Of them the {len(shown)} of {len(final)} published confirmed (the others fit "
                f"nothing their views show, or lie outside the bin the cell knows): {figures}."
            )
        by_views = [(n, [r.nees for r in run.rows if r.n_views == n]) for n in checkpoints]
        lines.append(
            "By the views fused, mean / median (a median that grows with the views is an error "
            "they share): "
            + ", ".join(
                f"{n}: {np.mean(v):.2f} / {np.median(v):.2f}" for n, v in by_views if len(v)
            )
            + "."
        )
    for n in checkpoints:
        pairs = np.array(run.pose_nees.get(n, []), float).reshape(-1, 2)
        if not len(pairs):
            continue
        inside, median = _nees_figures(pairs)
        lines.append(
            f"Published poses after {n} views ({len(pairs)}): median NEES of the "
            f"translation {median[0]:.2f}, of the rotation {median[1]:.2f} (expected 2.37); "
            f"inside their 95% ellipsoid {inside[0]:.0f}% and {inside[1]:.0f}%."
        )
        right = right_pose_nees(run, n)
        if len(right):
            inside, median = _nees_figures(right)
            lines.append(
                f"Of them right (ADD-sym < 0.1 d, {len(right)}), what a Gaussian can cover: "
                f"median {median[0]:.2f} and {median[1]:.2f}; inside {inside[0]:.0f}% and "
                f"{inside[1]:.0f}%."
            )
    return "\n".join(lines)


def right_pose_nees(run: DatasetRun, n_views: int) -> np.ndarray:
    """(K, 2) NEES (translation, rotation) after ``n_views`` views of the published poses that
    are right (ADD-sym < 0.1 d): a pose in a wrong basin is no Gaussian's to cover. Empty where
    the run has no such poses, or no ambiguity rows beside its NEES (the rows and the NEES are
    of the same poses in the same order, ``_scored``)."""
    pairs = np.array(run.pose_nees.get(n_views, []), float).reshape(-1, 2)
    rows = run.ambiguity.get(n_views, [])
    if len(rows) != len(pairs):
        return np.zeros((0, 2))
    return pairs[np.array([r.right for r in rows], bool)].reshape(-1, 2)


def right_pose_coverage(run: DatasetRun, n_views: int) -> dict | None:
    """Of the right poses after ``n_views`` views (:func:`right_pose_nees`): their count and the
    shares inside their published 95% ellipsoid, translation and rotation; None without any."""
    right = right_pose_nees(run, n_views)
    if not len(right):
        return None
    inside, _ = _nees_figures(right)
    return {
        "right_poses": len(right),
        "inside_95_translation": float(inside[0]) / 100,
        "inside_95_rotation": float(inside[1]) / 100,
    }


def _nees_figures(pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Of (N, 2) NEES (translation, rotation): the shares in percent inside the 95% ellipsoid
    (chi-squared, 3 dof) and the medians, each (2,)."""
    return np.mean(pairs <= 7.815, axis=0) * 100, np.median(pairs, axis=0)
