"""The tracker's naming of "a part": a generalist front end's detections (obj_id ``ANY_PART``)
made detections of the catalog's parts.

- With one part in the catalog every one is that part.
- A detection whose centre falls within the association gate of a live track's prediction
  takes its class, one detection a track (the association's minimum-cost assignment over every
  class's tracks): the track was named when it was founded, and its views need not agree again.
- The rest stay "a part": held, and paired across views by triangulation like any class's
  (:mod:`estimator.translation.founding`), their box depth that of the catalog's
  geometric-mean size (:func:`any_part_size`) and the pairs' box check widened by how far the
  sizes spread (:func:`size_spread`). A pair that would found a track is named by the parts'
  templates in both views at its translation (:mod:`estimator.rotation.naming`), and founded
  again as the named part's: its boxes checked against that part's size.

Pure functions over the tracker's state; :class:`~estimator.tracker.estimator.MultiViewEstimator`
calls them.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from posefuse.estimator.core.camera import Camera
from posefuse.estimator.frontend.detection import ANY_PART, Detection
from posefuse.estimator.rotation.naming import class_similarities, name_part
from posefuse.estimator.translation.association import AssociationConfig, assign, cost_matrix
from posefuse.estimator.translation.founding import (
    FoundingConfig,
    FoundingPair,
    triangulate_pair,
)
from posefuse.estimator.translation.gaussian import MIN_DEPTH


def any_part_size(sizes: dict[int, float]) -> float:
    """The geometric mean of the parts' expected box diagonals at 1 m (metres; obj_id ->
    size): the size the box depth of "a part" is taken at."""
    return float(np.exp(np.mean(np.log(list(sizes.values())))))


def size_spread(sizes: dict[int, float]) -> float:
    """How many times any part's size lies at most from :func:`any_part_size` (>= 1)."""
    mean = any_part_size(sizes)
    return max(max(sizes.values()) / mean, mean / min(sizes.values()))


def name_by_tracks(
    detections: list[Detection],
    camera: Camera,
    T_cam_world: np.ndarray,
    tracks: list,
    classes: list[int],
    config: AssociationConfig,
) -> list[Detection]:
    """The detections with those of "a part" named where they can be now: all of them with one
    class in ``classes``; else those a track's gate takes, one a track (see the module
    docstring). ``tracks``: the live tracks, any class; T_cam_world: (4, 4)."""
    todo = [j for j, d in enumerate(detections) if d.obj_id == ANY_PART]
    if not todo:
        return detections
    named = list(detections)
    if len(classes) == 1:
        for j in todo:
            named[j] = replace(detections[j], obj_id=classes[0])
        return named
    todo = [j for j in todo if camera.contains(detections[j].center_uv[None])[0]]
    if not todo or not tracks:
        return detections
    cost = cost_matrix(
        [t.view() for t in tracks],
        T_cam_world,
        camera.K,
        np.array([camera.undistort_points(detections[j].center_uv) for j in todo]).reshape(-1, 2),
        np.array([detections[j].center_cov for j in todo]).reshape(-1, 2, 2),
        config,
    )
    for i, jj in assign(cost):  # one detection a track, as the association will take them
        named[todo[jj]] = replace(detections[todo[jj]], obj_id=tracks[i].obj_id)
    return named


def name_pair(
    pair: FoundingPair,
    images: dict[int, np.ndarray],
    matchers: dict,
    sizes: dict[int, float],
    config: FoundingConfig,
) -> FoundingPair | None:
    """A founding pair of "a part" named: each part's templates scored in both views (those
    whose image ``images`` keeps, by stamp) at the pair's translation; the pair's detections
    then of the named part, their box depths those of its size (``sizes``, as
    :func:`any_part_size`'s), and the pair founded again as that part's
    (:func:`triangulate_pair`). None when neither view's image is kept (nothing to name it by)
    or the named part's pair is gated out."""
    per_view = []
    for h in (pair.older, pair.newer):
        image = images.get(h.stamp_ns)
        t_cam_obj = h.T_cam_world[:3, :3] @ pair.prior_mean + h.T_cam_world[:3, 3]
        if image is None or not t_cam_obj[2] > MIN_DEPTH:
            continue
        per_view.append(class_similarities(image, h.K, t_cam_obj, h.mask, matchers))
    if not per_view:
        return None
    obj_id = name_part(per_view).obj_id
    scale = sizes[obj_id] / any_part_size(sizes)
    older, newer = (
        replace(h, obj_id=obj_id, box_depth=h.box_depth * scale) for h in (pair.older, pair.newer)
    )
    return triangulate_pair(older, newer, config)
