"""How well a front end finds instances and their centers, against a BOP dataset's truth.

Per view, detections are matched one-to-one to annotated instances of the same class by their
center distance (Hungarian, at most ``max_px`` image pixels). Recall counts the instances with
``visib_fract > min_visib`` that were matched; precision counts the detections matched to any
annotated instance (a detection of a barely visible part is not a false positive). Center error
and NEES (``e^T Sigma^-1 e`` with the detection's covariance; 2 expected) are over the matched
instances above ``min_visib``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment


@dataclass(frozen=True)
class FrontendScore:
    recall: float
    precision: float
    median_center_error_px: float
    mean_nees: float
    n_instances: int
    n_detections: int
    n_views: int

    def to_markdown(self) -> str:
        return "\n".join(
            [
                "| measure | value |",
                "|---|---|",
                f"| views | {self.n_views} |",
                f"| instances (visib > 0.75) | {self.n_instances} |",
                f"| detections | {self.n_detections} |",
                f"| recall | {self.recall:.4f} |",
                f"| precision | {self.precision:.4f} |",
                f"| median center error | {self.median_center_error_px:.2f} px |",
                f"| mean NEES of the 2D center | {self.mean_nees:.2f} |",
            ]
        )


def match_centers(
    dets, obj_ids, truth: np.ndarray, max_px: float = 15.0, any_class: bool = False
) -> dict[int, int]:
    """One-to-one matching of detections to annotated instances of their class by center
    distance (Hungarian, at most ``max_px``).

    Args:
        dets: the detections; obj_ids: (N,) the instances' classes; truth: (N, 2) their
            projected centers, image pixels; any_class: match regardless of class (a
            generalist's detections, which say "a part" only).
    Returns:
        {detection index: instance index}.
    """
    cost = np.full((len(dets), len(truth)), 1e9)
    for i, d in enumerate(dets):
        for j, obj_id in enumerate(obj_ids):
            if any_class or d.obj_id == obj_id:
                dist = float(np.linalg.norm(d.center_uv - truth[j]))
                if dist <= max_px:
                    cost[i, j] = dist
    if not cost.size:
        return {}
    rows, cols = linear_sum_assignment(cost)
    return {int(i): int(j) for i, j in zip(rows, cols, strict=True) if cost[i, j] < 1e9}


def match_to_truth(dets, view, max_px: float = 15.0, any_class: bool = False):
    """:func:`match_centers` against a BOP view's annotated instances.

    Returns:
        gts: the annotated instances in front of the camera; truth: (len(gts), 2) their
        projected centers; pairs: {detection index: index into gts}.
    """
    gts = [g for g in view.gts if g.T_cam_obj[2, 3] > 0]
    truth = np.array([view.camera.project(g.T_cam_obj[:3, 3]) for g in gts]).reshape(-1, 2)
    return gts, truth, match_centers(dets, [g.obj_id for g in gts], truth, max_px, any_class)


def score_frontend(
    dataset,
    detect,
    views,
    min_visib: float = 0.75,
    max_px: float = 15.0,
    any_class: bool = False,
    obj_id: int | None = None,
):
    """detect(view) -> list[Detection]; views: the BopViews to score; any_class: a detection
    may match an instance of any class (a generalist's, see ``match_centers``); obj_id: score
    that class alone (its detections against its instances; not with any_class)."""
    if obj_id is not None and any_class:
        raise ValueError("score_frontend: obj_id scores one class; a generalist's has none")
    n_inst = n_found = n_det = n_det_ok = n_views = 0
    errors, nees = [], []
    for view in views:
        n_views += 1
        dets = detect(view)
        if obj_id is not None:
            dets = [d for d in dets if d.obj_id == obj_id]
        n_det += len(dets)
        gts, truth, pairs = match_to_truth(dets, view, max_px, any_class)
        matched = {j: i for i, j in pairs.items()}
        n_det_ok += len(matched)
        for j, g in enumerate(gts):
            if g.visib_fract <= min_visib or (obj_id is not None and g.obj_id != obj_id):
                continue
            n_inst += 1
            if j in matched:
                n_found += 1
                d = dets[matched[j]]
                e = d.center_uv - truth[j]
                errors.append(float(np.linalg.norm(e)))
                nees.append(float(e @ np.linalg.solve(d.center_cov, e)))
    return FrontendScore(
        recall=n_found / n_inst if n_inst else float("nan"),
        precision=n_det_ok / n_det if n_det else float("nan"),
        median_center_error_px=float(np.median(errors)) if errors else float("nan"),
        mean_nees=float(np.mean(nees)) if nees else float("nan"),
        n_instances=n_inst,
        n_detections=n_det,
        n_views=n_views,
    )
