"""Which part of the catalog "a part" is, from the parts' LINE-2D templates across views.

A generalist front end (a model card with ``agnostic``: ``posefuse onboard --steps 0``) finds
parts without knowing which: its detections are of obj_id ``ANY_PART``. The tracker founds a
track from two views of such detections by triangulation, as for any class, and names it then
(:meth:`estimator.tracker.estimator.MultiViewEstimator.update`): in each of the two views the
part's RoI is re-cropped at the triangulated translation, as the rotation step does
(:func:`estimator.rotation.recrop.crop_roi`), once per catalog part, and that part's templates
scored there; the part whose best template stands most above the rest of its templates there
(:func:`class_similarities`), summed over the views, names it.

At the triangulated depth the crop shows the part at its true size, where one view's box
depth would make every part the box's size and leave shape alone. Named so, the tracks of the
five real meshes of the evaluation were of the right part 69% of the time in bins and 84% in
piles (docs/own-parts.md); the gear is still named the eye bolt, whose ring it resembles, in
12 of its 16 tracks. Scored one view at a time at the box depth, the detections were named
right 68% of the time (docs/lab/2026-12-06-generalist-large-parts-and-template-class.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from posefuse.estimator.rotation.matching import RotationMatcher
from posefuse.estimator.rotation.recrop import crop_roi


@dataclass(frozen=True)
class PartName:
    """What the templates say of one part: ``obj_id`` the most similar part, ``scores``
    ((obj_id, :func:`class_similarities` summed over the views), ...) of every part, best
    first, and ``views`` the number of views summed."""

    obj_id: int
    scores: tuple[tuple[int, float], ...]
    views: int

    @property
    def margin(self) -> float:
        """The best part's summed similarity less the runner-up's (inf with one part)."""
        return self.scores[0][1] - self.scores[1][1] if len(self.scores) > 1 else float("inf")


def class_similarities(
    image: np.ndarray,
    K: np.ndarray,
    t_cam_obj: np.ndarray,
    mask: np.ndarray | None,
    matchers: dict[int, RotationMatcher],
) -> dict[int, float]:
    """Per part, how far its best template's similarity stands above the mean of its bank's
    at a translation (in [0, 1]).

    The best similarity alone favours the parts whose templates resemble clutter: in piles of
    tee fittings, the screw's thread-like edges named 31 of 103 tracks the screw. Less the
    bank's mean at the same RoI, 68% of the tracks in piles and 73% in bins were named right,
    against 58% and 73% (onboarding's validation renders of the five real meshes, their tuning
    sets, before the tracker's other naming rules: docs/own-parts.md). Dividing by the bank's
    spread as well named almost all wrong.

    Args:
        image: (H, W, 3) uint8 RGB. K: (3, 3). t_cam_obj: (3,) metres, z > 0.
        mask: (H, W) bool, the detection's mask, or None.
        matchers: obj_id -> the part's rotation matcher (its template bank; anything with
            ``bank``, ``config.mask_dilation_px`` and ``scores(roi, roi_mask)``).
    """
    if not t_cam_obj[2] > 0:
        raise ValueError(f"class_similarities: the part must lie in front, got z {t_cam_obj[2]}")
    out = {}
    for obj_id in sorted(matchers):
        matcher = matchers[obj_id]
        dilation = getattr(getattr(matcher, "config", None), "mask_dilation_px", None)
        if dilation is None or not callable(getattr(matcher, "scores", None)):
            raise TypeError(
                f"class_similarities: the matcher of obj_id {obj_id} ({type(matcher).__name__}) "
                "cannot name a part: it needs scores(roi, roi_mask) and config.mask_dilation_px"
            )
        roi, roi_mask = crop_roi(image, K, t_cam_obj, matcher.bank, mask, dilation)
        scores = matcher.scores(roi, roi_mask)
        out[obj_id] = float(scores.max() - scores.mean())
    return out


def name_part(per_view: list[dict[int, float]]) -> PartName:
    """The part named by the similarities of several views (:func:`class_similarities`),
    summed; ties go to the smaller obj_id. ValueError when there is nothing to name by."""
    per_view = [v for v in per_view if v]
    if not per_view:
        raise ValueError("name_part: no view's similarities to name a part by")
    classes = sorted(per_view[0])
    if any(sorted(v) != classes for v in per_view):
        raise ValueError("name_part: the views' similarities are of different parts")
    total = {c: float(sum(v[c] for v in per_view)) for c in classes}
    ranked = tuple(sorted(total.items(), key=lambda kv: (-kv[1], kv[0])))
    return PartName(ranked[0][0], ranked, len(per_view))
