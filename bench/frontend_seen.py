"""How much of the front end's accuracy is memory: recall and precision on views it trained on.

    python -m posefuse.bench.frontend_seen --training-set DIR [--model M.onnx] [--views 30]
        [--first-view N]

``DIR`` is a rendered training set (``posefuse train --data-dir``: the folder that holds
``meta.json``). Its first ``--views`` views of each profile (one in two, so that two views of a
scene do not both count) go through the front end, and are scored as ``eval-frontend`` scores a
BOP dataset (``evaluation.frontend_metrics``): detections matched one to one to the annotated
parts of their class within 15 px; recall over the parts more than 75% visible, precision over
every detection. Far better numbers here than on the tuning sets mean the network has learned
these views rather than the task: more scenes, or more augmentation, is then what it needs.

Beside them, stage one alone: the share of those parts that one of its boxes is centred on
(the box's centre within 15 px of the part's visible box's, matched one to one). What stage one
finds and the front end then loses is stage two's (its centre off, or merged as a duplicate).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass

import numpy as np

from posefuse.estimator.core.objects import load_catalog
from posefuse.estimator.frontend.network import NetworkFrontend
from posefuse.evaluation.frontend_metrics import match_centers
from posefuse.service.resources import DEFAULT_MODEL

MAX_PX = 15.0
MIN_VISIB = 0.75


def score_view(
    detections, rows: np.ndarray, class_of: dict[int, int], any_class: bool = False
) -> tuple[int, int, int]:
    """(parts found, parts more than 75% visible, detections matched) of one view.

    Args:
        detections: the front end's detections.
        rows: (K, 11) the view's instance rows (``sim.train_data.INSTANCE_COLUMNS``).
        class_of: output class index (1..C) -> obj_id.
        any_class: a generalist's detections ("a part") match parts of any class.
    """
    obj_ids = [class_of[int(r[2])] for r in rows]
    matched = set(match_centers(detections, obj_ids, rows[:, 3:5], MAX_PX, any_class).values())
    visible = rows[:, 9] > MIN_VISIB
    found = sum(1 for j in matched if visible[j])
    return found, int(visible.sum()), len(matched)


@dataclass(frozen=True)
class _BoxAsDetection:
    """A stage-one box in the shape ``match_centers`` reads."""

    obj_id: int
    center_uv: np.ndarray


def score_boxes(boxes, rows: np.ndarray, class_of: dict[int, int], any_class: bool) -> int:
    """Parts more than 75% visible that stage one's ``boxes`` find: a box centred within MAX_PX
    of the part's visible box (``rows`` (K, 11) as in :func:`score_view`), one to one.

    Args:
        boxes: ``estimator.frontend.two_stage.Box`` of one view (class index in output order,
            0-based: output class ``k + 1``).
    """
    as_dets = [
        _BoxAsDetection(0 if any_class else class_of[b.class_index + 1], b.center) for b in boxes
    ]
    obj_ids = [0 if any_class else class_of[int(r[2])] for r in rows]
    box_centers = np.stack([(rows[:, 5] + rows[:, 7]) / 2, (rows[:, 6] + rows[:, 8]) / 2], 1)
    matched = set(match_centers(as_dets, obj_ids, box_centers, MAX_PX, any_class).values())
    return sum(1 for j in matched if rows[j, 9] > MIN_VISIB)


def main(argv: list[str] | None = None) -> int:
    from posefuse.sim.train_data import class_index, open_training_set, profile_of

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--training-set", required=True, help="a rendered training set folder")
    parser.add_argument("--model", default=str(DEFAULT_MODEL), help="a two-stage ONNX model")
    parser.add_argument("--views", type=int, default=30, help="views scored per profile")
    parser.add_argument(
        "--first-view",
        type=int,
        default=0,
        help="start at this view (a set rendered larger than the model's: its scenes the model "
        "never saw, from the same generator)",
    )
    args = parser.parse_args(argv)
    try:
        ts = open_training_set(args.training_set)
    except FileNotFoundError as e:
        raise SystemExit(f"--training-set: {e}") from None
    spec = ts.meta["spec"]
    catalog = load_catalog(ts.meta["catalog"])
    class_of = {k: obj_id for obj_id, k in class_index(catalog).items()}
    fe = NetworkFrontend(args.model, catalog)
    rows_of = ts.view_instances()
    # found, parts, matched, detections, found by stage one
    totals = {p: np.zeros(5, int) for p in ("mixed", "robi")}
    seen = dict.fromkeys(totals, 0)
    for v in range(args.first_view - args.first_view % 2, ts.n_views, 2):
        profile = profile_of(v // spec["views"], spec["robi_fraction"])
        if seen[profile] >= args.views:
            continue
        seen[profile] += 1
        image = np.asarray(ts.full_rgb[v])
        detections = fe.detect(image)
        found, parts, matched = score_view(detections, rows_of[v], class_of, fe.card.agnostic)
        boxed = score_boxes(fe.boxes(image), rows_of[v], class_of, fe.card.agnostic)
        totals[profile] += (found, parts, matched, len(detections), boxed)
    print(f"model {args.model}, training set {args.training_set}")
    print("| profile | views | parts | recall | precision | stage one alone: parts boxed |")
    print("|---|---|---|---|---|---|")
    for profile, (found, parts, matched, dets, boxed) in totals.items():
        print(
            f"| {profile} | {seen[profile]} | {parts} | {found / max(parts, 1):.3f} "
            f"| {matched / max(dets, 1):.3f} | {boxed / max(parts, 1):.3f} |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
