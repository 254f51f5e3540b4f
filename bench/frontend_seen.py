"""How much of the front end's accuracy is memory: recall and precision on views it trained on.

    python -m posefuse.bench.frontend_seen --training-set DIR [--model M.onnx] [--views 30]
        [--first-view N] [--by-object]

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
``--by-object`` adds both recalls per part type: a part set's large parts, say, can be lost
where its small ones are found.
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


def found_parts(
    detections, rows: np.ndarray, class_of: dict[int, int], any_class: bool = False
) -> tuple[np.ndarray, int]:
    """Which parts of one view the detections find, and how many detections are matched.

    Args:
        detections: the front end's detections.
        rows: (K, 11) the view's instance rows (``sim.train_data.INSTANCE_COLUMNS``).
        class_of: output class index (1..C) -> obj_id.
        any_class: a generalist's detections ("a part") match parts of any class.
    Returns:
        found: (K,) bool, matched one to one within 15 px and more than 75% visible;
        the number of detections matched to a part (visible or not).
    """
    obj_ids = [class_of[int(r[2])] for r in rows]
    matched = set(match_centers(detections, obj_ids, rows[:, 3:5], MAX_PX, any_class).values())
    found = np.zeros(len(rows), bool)
    found[list(matched)] = True
    return found & (rows[:, 9] > MIN_VISIB), len(matched)


def score_view(
    detections, rows: np.ndarray, class_of: dict[int, int], any_class: bool = False
) -> tuple[int, int, int]:
    """(parts found, parts more than 75% visible, detections matched) of one view; the
    arguments as :func:`found_parts`'s."""
    found, matched = found_parts(detections, rows, class_of, any_class)
    return int(found.sum()), int((rows[:, 9] > MIN_VISIB).sum()), matched


@dataclass(frozen=True)
class _BoxAsDetection:
    """A stage-one box in the shape ``match_centers`` reads."""

    obj_id: int
    center_uv: np.ndarray


def boxed_parts(boxes, rows: np.ndarray, class_of: dict[int, int], any_class: bool) -> np.ndarray:
    """(K,) bool: the parts more than 75% visible that stage one's ``boxes`` find, a box centred
    within MAX_PX of the part's visible box (``rows`` (K, 11) as in :func:`found_parts`), one to
    one.

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
    boxed = np.zeros(len(rows), bool)
    boxed[list(matched)] = True
    return boxed & (rows[:, 9] > MIN_VISIB)


def score_boxes(boxes, rows: np.ndarray, class_of: dict[int, int], any_class: bool) -> int:
    """The number of parts :func:`boxed_parts` finds."""
    return int(boxed_parts(boxes, rows, class_of, any_class).sum())


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
    parser.add_argument(
        "--by-object", action="store_true", help="also a row per part type and profile"
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
    # per (profile, obj_id or None for all): found, parts, found by stage one
    counts: dict[tuple[str, int | None], np.ndarray] = {}
    matched_dets = {p: np.zeros(2, int) for p in ("mixed", "robi")}  # matched, detections
    seen = dict.fromkeys(matched_dets, 0)
    for v in range(args.first_view - args.first_view % 2, ts.n_views, 2):
        profile = profile_of(v // spec["views"], spec["robi_fraction"])
        if seen[profile] >= args.views:
            continue
        seen[profile] += 1
        image = np.asarray(ts.full_rgb[v])
        rows = rows_of[v]
        detections = fe.detect(image)
        found, matched = found_parts(detections, rows, class_of, fe.card.agnostic)
        boxed = boxed_parts(fe.boxes(image), rows, class_of, fe.card.agnostic)
        visible = rows[:, 9] > MIN_VISIB
        matched_dets[profile] += (matched, len(detections))
        obj_of_row = np.array([class_of[int(r[2])] for r in rows], int)
        for key_obj in [None, *sorted(set(obj_of_row.tolist()))]:
            sel = visible if key_obj is None else visible & (obj_of_row == key_obj)
            counts.setdefault((profile, key_obj), np.zeros(3, int))
            counts[(profile, key_obj)] += (found[sel].sum(), sel.sum(), boxed[sel].sum())
    print(f"model {args.model}, training set {args.training_set}")
    print("| profile | part | views | parts | recall | precision | stage one alone: parts boxed |")
    print("|---|---|---|---|---|---|---|")
    for (profile, obj_id), (found, parts, boxed) in sorted(
        counts.items(), key=lambda kv: (kv[0][0], -1 if kv[0][1] is None else kv[0][1])
    ):
        if obj_id is not None and not args.by_object:
            continue
        if obj_id is None:
            name = "all"
            matched, dets = matched_dets[profile]
            precision = f"{matched / max(dets, 1):.3f}"
        else:
            name, precision = catalog[obj_id].name, ""
        print(
            f"| {profile} | {name} | {seen[profile]} | {parts} | {found / max(parts, 1):.3f} "
            f"| {precision} | {boxed / max(parts, 1):.3f} |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
