"""The rotation step alone, one view at a time, at the true translation: how often its best
template, and any of the hypotheses it hands the mixture, lies near the truth.

python -m posefuse.bench.view_matching --dataset DIR [--catalog-of DIR] [--masks box]
    [--min-visib 0.5] [--near-deg 15] [--per-view]

Every annotated instance of every view (visible fraction at least ``--min-visib``) is re-cropped
at its true translation (the scale is then exact) with the front end's mask of ``--masks`` (the
true silhouette, or its filled box) and scored by the whole template bank. Printed per object
and in all: the share of views whose best template is within ``--near-deg`` of the truth (the
closest symmetric equivalent), the share where one of the hypotheses the mixture gets (top-k
after suppression, ``RotationConfig``) is, and the median angle of the best. Unlike
``run-dataset``, nothing here depends on the translation, the association, the mixture or the
verification: it isolates what the image's edges say, so that a real photograph and its
rendered twin (``bench.real``) compare view by view, on more samples than instances.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass

import numpy as np

from posefuse.estimator.core.geometry import rotation_angle
from posefuse.estimator.rotation.matching import ray_correction, select_hypotheses
from posefuse.estimator.rotation.recrop import crop_roi
from posefuse.estimator.tracker import MultiViewEstimator
from posefuse.evaluation.dataset import load_dataset


@dataclass(frozen=True)
class ViewMatch:
    """One instance in one view: obj_id, scene_id, im_id, visib_fract, best_deg (the best
    template's angle to the truth), handed (a hypothesis within the limit), best_score."""

    obj_id: int
    scene_id: int
    im_id: int
    visib_fract: float
    best_deg: float
    handed: bool
    best_score: float


def _angles_to_truth(R_templates: np.ndarray, R_true: np.ndarray, symmetries: np.ndarray):
    """(N,) degrees from each of R_templates (N, 3, 3) to the closest of R_true @ S, S in
    symmetries (S, 3, 3)."""
    equivalents = np.einsum("ij,sjk->sik", R_true, symmetries)
    relative = np.einsum("sji,njk->nsik", equivalents, R_templates).reshape(-1, 3, 3)
    return np.degrees(rotation_angle(relative)).reshape(len(R_templates), -1).min(axis=1)


def view_matches(
    dataset, masks: str = "silhouette", min_visib: float = 0.5, near_deg: float = 15.0
) -> list[ViewMatch]:
    """:class:`ViewMatch` of every instance of ``dataset`` seen at least ``min_visib``."""
    if masks not in ("silhouette", "box"):
        raise ValueError(f"masks must be 'silhouette' or 'box', got {masks!r}")
    estimator = MultiViewEstimator(dataset.catalog, show_progress=False)
    out = []
    for view in dataset.views():
        scene = dataset.scene(view.scene_id)
        image = scene.load_rgb(view.im_id)
        for gt in view.gts:
            if gt.visib_fract < min_visib or gt.bbox_visib[2] <= 0:
                continue
            matcher = estimator.matcher(gt.obj_id)
            if masks == "box":
                mask = np.zeros(image.shape[:2], bool)
                x, y, w, h = gt.bbox_visib
                mask[y : y + h, x : x + w] = True
            else:
                mask = scene.load_mask_visib(view.im_id, gt.gt_idx)
            t = gt.T_cam_obj[:3, 3]
            roi, roi_mask = crop_roi(
                image, view.camera.K, t, matcher.bank, mask, matcher.config.mask_dilation_px
            )
            scores = matcher.scores(roi, roi_mask)
            R_ray = ray_correction(t)
            symmetries = dataset.catalog[gt.obj_id].symmetry_transforms()[:, :3, :3]
            degrees = _angles_to_truth(
                R_ray @ matcher.bank.R_cam_obj, gt.T_cam_obj[:3, :3], symmetries
            )
            best = int(np.argmax(scores))
            hypotheses = select_hypotheses(scores, matcher.bank.R_cam_obj, R_ray, matcher.config)
            out.append(
                ViewMatch(
                    gt.obj_id,
                    view.scene_id,
                    view.im_id,
                    float(gt.visib_fract),
                    float(degrees[best]),
                    any(degrees[h.template] < near_deg for h in hypotheses),
                    float(scores[best]),
                )
            )
    return out


def summary_rows(matches: list[ViewMatch], catalog, near_deg: float = 15.0) -> list[str]:
    """Markdown rows: per object, then all."""
    rows = [
        f"| object | views | best within {near_deg:g} deg | a hypothesis within "
        "| median best (deg) |",
        "|---|---|---|---|---|",
    ]
    groups = {o: [m for m in matches if m.obj_id == o] for o in sorted({m.obj_id for m in matches})}
    groups["all"] = matches
    for key, group in groups.items():
        if not group:
            continue
        best = np.array([m.best_deg for m in group])
        handed = np.array([m.handed for m in group])
        name = "**all**" if key == "all" else f"{key} {catalog[key].name}"
        rows.append(
            f"| {name} | {len(group)} | {100 * np.mean(best < near_deg):.1f}% | "
            f"{100 * handed.mean():.1f}% | {np.median(best):.1f} |"
        )
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", required=True, help="BOP dataset folder")
    parser.add_argument(
        "--catalog-of", help="read the catalog of this dataset (a rendered twin has the real one's)"
    )
    parser.add_argument("--masks", choices=("silhouette", "box"), default="silhouette")
    parser.add_argument("--min-visib", type=float, default=0.5)
    parser.add_argument("--near-deg", type=float, default=15.0)
    parser.add_argument("--per-view", action="store_true", help="a line per instance and view")
    args = parser.parse_args(argv)
    catalog = load_dataset(args.catalog_of).catalog if args.catalog_of else None
    dataset = load_dataset(args.dataset, catalog=catalog)
    matches = view_matches(dataset, args.masks, args.min_visib, args.near_deg)
    if args.per_view:
        for m in matches:
            print(
                f"scene {m.scene_id} im {m.im_id} obj {m.obj_id} visib {m.visib_fract:.2f}: "
                f"best {m.best_deg:.1f} deg (score {m.best_score:.3f}), handed {m.handed}"
            )
    print(f"{args.dataset}, {args.masks} masks, the true translation:\n")
    print("\n".join(summary_rows(matches, dataset.catalog, args.near_deg)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
