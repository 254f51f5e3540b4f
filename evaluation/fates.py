"""Where every miss comes from: one fate per scored instance after n views.

The front end's detections carry the index of the true instance they came from (-1 for a false
positive; known to the oracle, and to the labelled network front end of ``run_dataset``), and
the estimator reports which track took each detection. From these and the estimates, each
annotated instance with ``visib_fract > min_visib`` in the checkpoint's view gets the first fate
that applies, in this order:

1. ``correct``: an estimate found it (ADD-sym < 0.1 d, BOP's matching, as the reports count);
2. ``not detected``: fewer than ``min_views`` of its detections taken by tracks so far (a track
   needs two). Beside the fate, each instance carries how many views so far detected it at
   all (``detected_views``, held detections included): a part never detected is the front
   end's miss; one detected in a view or more that never found a track is the founding's
   (:func:`not_detected_table`);
3. ``split``: its detections went to two or more of the tracks alive at the checkpoint, none of
   them holding most of them (a track dropped since, such as one founded on a wrong pairing and
   later let go, holds nothing: its detections count only towards rule 2). Where one live track
   holds most of them, that is the instance's track, and a stray detection or two elsewhere
   (a wrong founding pair, a false association) is not what its pose is judged by;
4. ``merged``: its track holds as many detections of another instance as of its own, or the
   estimate of its track was matched to another instance;
5. ``no pose``: its track has no reported pose (not confirmed, or no rotation measured yet), or
   every track that took its detections has been dropped;
6. ``translation off``: the track's translation alone, with the true rotation, fails ADD-sym;
7. ``rotation flipped``: the rotation is off by at least 135 degrees from the closest symmetric
   equivalent of the truth (the part seen end over end, a symmetry-like flip);
8. ``rotation off``: any other rotation error.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from posefuse.evaluation import pose_error
from posefuse.evaluation.eval_points import eval_points
from posefuse.evaluation.pose_error import eval_symmetries
from posefuse.evaluation.scores import error_matrix, match_estimates

FATES = (
    "correct",
    "not detected",
    "split",
    "merged",
    "no pose",
    "translation off",
    "rotation flipped",
    "rotation off",
)
FLIP_DEG = 135.0


@dataclass(frozen=True, eq=False)
class TrackPose:
    """One track at a checkpoint: its class, score, and pose in the checkpoint's camera frame
    (T_cam_obj (4, 4), None when it reports no pose)."""

    object_id: str
    obj_id: int
    score: float
    T_cam_obj: np.ndarray | None


@dataclass(frozen=True)
class InstanceFate:
    scene_id: int
    im_id: int
    n_views: int
    obj_id: int
    gt_idx: int
    fate: str
    detected_views: int = 0  # views so far whose front end detected it (held ones included)


def _rotation_residual_deg(model, T_est: np.ndarray, T_gt: np.ndarray) -> float:
    """The rotation angle between the estimate and the truth's symmetric equivalent closest to
    it by ADD, degrees."""
    candidates = T_gt @ eval_symmetries(model)  # (S, 4, 4)
    errors = [pose_error.add(T_est, T, eval_points(model)) for T in candidates]
    R = T_est[:3, :3].T @ candidates[int(np.argmin(errors))][:3, :3]
    return float(np.degrees(Rotation.from_matrix(R).magnitude()))


def instance_fates(
    view,
    catalog,
    n_views: int,
    tracks: list[TrackPose],
    members: dict[str, list[int]],
    min_views: int = 2,
    min_visib: float = 0.75,
    threshold: float = 0.1,
    detected: dict[int, int] | None = None,
) -> list[InstanceFate]:
    """The fate of each scored instance of ``view`` (a BopView) after ``n_views`` views.

    tracks: every track of the estimator (with or without a pose); members: object_id -> the
    instance index of each detection the track took (-1 for false positives), for dropped
    tracks too; detected: instance index -> how many views so far detected it, whether a
    track took the detection or not (None: not counted, 0 each).
    """
    posed = [t for t in tracks if t.T_cam_obj is not None]
    correct: set[int] = set()
    matched_elsewhere: set[str] = set()
    for obj_id in {g.obj_id for g in view.gts}:
        gt_idx = [k for k, g in enumerate(view.gts) if g.obj_id == obj_id]
        est = sorted((t for t in posed if t.obj_id == obj_id), key=lambda t: -t.score)
        if not est:
            continue
        model = catalog[obj_id]
        errors = error_matrix(
            model,
            np.stack([t.T_cam_obj for t in est]),
            np.stack([view.gts[k].T_cam_obj for k in gt_idx]),
            "add_sym",
        )
        for e, g in match_estimates(errors, threshold * model.diameter):
            correct.add(gt_idx[g])
            matched_elsewhere.add(est[e].object_id)
    by_id = {t.object_id: t for t in tracks}
    holdings: dict[int, Counter] = {}
    for oid, labels in members.items():
        for x in labels:
            if x >= 0:
                holdings.setdefault(x, Counter())[oid] += 1
    out = []
    for k, gt in enumerate(view.gts):
        if gt.visib_fract <= min_visib:
            continue
        held = holdings.get(k, Counter())
        fate = _fate(
            k,
            gt,
            view,
            catalog,
            held,
            by_id,
            members,
            correct,
            matched_elsewhere,
            min_views,
            threshold,
        )
        seen = (detected or {}).get(k, 0)
        out.append(InstanceFate(view.scene_id, view.im_id, n_views, gt.obj_id, k, fate, seen))
    return out


def _fate(
    k,
    gt,
    view,
    catalog,
    held,
    by_id,
    members,
    correct,
    matched_elsewhere,
    min_views,
    threshold,
) -> str:
    """held: track -> how many of the instance's detections it took, dropped tracks included;
    by_id: the tracks alive now, by object_id."""
    if k in correct:
        return "correct"
    if sum(held.values()) < min_views:
        return "not detected"
    held_alive = Counter({oid: n for oid, n in held.items() if oid in by_id})
    if not held_alive:
        return "no pose"
    main, n_main = held_alive.most_common(1)[0]
    if 2 * n_main <= sum(held_alive.values()):  # no live track holds most of them
        return "split"
    others = Counter(x for x in members.get(main, []) if x >= 0 and x != k)
    if others and others.most_common(1)[0][1] >= n_main:
        return "merged"
    track = by_id.get(main)
    if track is None or track.T_cam_obj is None:
        return "no pose"
    if main in matched_elsewhere:
        return "merged"
    model = catalog[gt.obj_id]
    limit = threshold * model.diameter
    T_true_rotation = gt.T_cam_obj.copy()
    T_true_rotation[:3, 3] = track.T_cam_obj[:3, 3]
    if error_matrix(model, T_true_rotation[None], gt.T_cam_obj[None], "add_sym")[0, 0] >= limit:
        return "translation off"
    if _rotation_residual_deg(model, track.T_cam_obj, gt.T_cam_obj) >= FLIP_DEG:
        return "rotation flipped"
    return "rotation off"


def _by_views_and_part(fates: list[InstanceFate], catalog):
    """(views, part name, its fates) per number of views and part that has any, each number of
    views closed by ("**all**", every part's fates)."""
    for n in sorted({f.n_views for f in fates}):
        at_n = [f for f in fates if f.n_views == n]
        groups = [(catalog[o].name, [f for f in at_n if f.obj_id == o]) for o in catalog]
        for name, rows in [*groups, ("**all**", at_n)]:
            if rows:
                yield n, name, rows


def fate_table(fates: list[InstanceFate], catalog, profile: str) -> str:
    """Markdown: per part and number of views, how many instances met each fate."""
    lines = [
        f"| profile | object | views | instances | {' | '.join(FATES)} |",
        "|---|---|---|---|" + "---|" * len(FATES),
    ]
    for n, name, rows in _by_views_and_part(fates, catalog):
        counts = Counter(f.fate for f in rows)
        cells = " | ".join(str(counts.get(fate, 0)) for fate in FATES)
        lines.append(f"| {profile} | {name} | {n} | {len(rows)} | {cells} |")
    return "\n".join(lines)


def not_detected_table(fates: list[InstanceFate], catalog, profile: str) -> str:
    """Markdown: per part and number of views, the instances ``not detected``, by how many
    views detected them at all: never (the front end's miss), in one view (no second view to
    found a track with), or in two or more (detections that founded no track, or too few)."""
    lines = [
        "| profile | object | views | not detected | never detected | in one view "
        "| in two or more views |",
        "|---|---|---|---|---|---|---|",
    ]
    missed = [f for f in fates if f.fate == "not detected"]
    for n, name, rows in _by_views_and_part(missed, catalog):
        views = Counter(min(f.detected_views, 2) for f in rows)
        lines.append(
            f"| {profile} | {name} | {n} | {len(rows)} | {views[0]} | {views[1]} | {views[2]} |"
        )
    return "\n".join(lines)
