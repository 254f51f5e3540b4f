"""Where the two-stage front end loses the parts it misses, stage by stage.

    python -m posefuse.bench.frontend_misses --dataset DIR [--dataset DIR2] [--model M.onnx]
        [--by-object]

Per annotated part more than 75% visible, in every view, the first of these that applies:

- **found**: the front end's final detections have it (matched as ``eval-frontend`` matches:
  same class, one to one, center within 15 px);
- **a peak below the threshold**: stage one has no box of its class whose center lies within
  0.3 x the longer side of the part's visible box from that box's center, but it has a peak of
  the class there that scored at least ``LOW_PEAK`` (0.1) and less than the card's
  ``min_score``: stage one saw the part and was not sure enough;
- **no box**: not even such a peak;
- **stage two empty**: the nearest such box's crop gives no detection (too few object pixels);
- **stage two on a neighbour**: that crop's center lands within 15 px of another annotated part;
- **stage two off**: it lands more than 15 px from the part, and from any other;
- **lost after stage two**: it lands within 15 px, but the refinement pass, the spread filter or
  duplicate suppression lose it.

It also prints, over the missed parts that reached stage two, the median distance in pixels from
their box's stage-two center to their projected origin. The shares tell which stage to work on.
"""

from __future__ import annotations

import argparse
import dataclasses
from collections import Counter

import numpy as np

from posefuse.estimator.frontend.network import NetworkFrontend, image_seed, input_scale_for
from posefuse.estimator.frontend.two_stage import Box, decode_boxes
from posefuse.evaluation.dataset import load_dataset
from posefuse.evaluation.frontend_metrics import match_to_truth
from posefuse.service.resources import DEFAULT_MODEL

FATES = (
    "found",
    "a peak below the threshold",
    "no box",
    "stage two empty",
    "stage two on a neighbour",
    "stage two off",
    "lost after stage two",
)
MAX_PX = 15.0
BOX_NEAR = 0.3  # x the longer side of the part's visible box
MIN_VISIB = 0.75
LOW_PEAK = 0.1  # stage one's peaks down to this count as "seen, below the threshold"


def weak_peaks(fe: NetworkFrontend, image: np.ndarray) -> list[Box]:
    """Stage one's boxes whose peak scored in [LOW_PEAK, the card's min_score)."""
    config = dataclasses.replace(fe.two_stage, min_score=min(LOW_PEAK, fe.two_stage.min_score))
    low = decode_boxes(fe.infer(image), input_scale_for(image.shape[:2], fe.card), config)
    return [b for b in low if b.score < fe.two_stage.min_score]


def view_fates(fe: NetworkFrontend, image: np.ndarray, view):
    """(fates, stage-two errors in px, rows) of one view's parts (visib > 0.75); rows: one
    (obj_id, fate, stage-two error in px or None) per part, in the fates' order."""
    boxes = fe.boxes(image)
    weak_boxes = weak_peaks(fe, image)
    first_pass = fe.stage_two(image, boxes, np.random.default_rng([fe.seed, image_seed(image)]))
    final = fe.detect(image)
    agnostic = fe.card.agnostic  # a generalist's boxes and detections are of any class
    gts, truth, pairs = match_to_truth(final, view, MAX_PX, any_class=agnostic)
    found = set(pairs.values())
    obj_ids = [k for k, _ in fe.card.classes]

    def of_class(candidates: list[Box], obj_id: int) -> list[Box]:
        return [b for b in candidates if agnostic or obj_ids[b.class_index] == obj_id]

    rows = []
    for j, gt in enumerate(gts):
        if gt.visib_fract <= MIN_VISIB:
            continue
        if j in found:
            rows.append((gt.obj_id, "found", None))
            continue
        x, y, w, h = gt.bbox_visib
        visible_center = np.array([x + w / 2, y + h / 2])
        reach = BOX_NEAR * max(w, h)
        near = [
            (float(np.linalg.norm(b.center - visible_center)), i)
            for i, b in enumerate(boxes)
            if agnostic or obj_ids[b.class_index] == gt.obj_id
        ]
        if not near or min(near)[0] > reach:
            seen = any(
                np.linalg.norm(b.center - visible_center) <= reach
                for b in of_class(weak_boxes, gt.obj_id)
            )
            rows.append((gt.obj_id, "a peak below the threshold" if seen else "no box", None))
            continue
        det = first_pass[min(near)[1]]
        if det is None:
            rows.append((gt.obj_id, "stage two empty", None))
            continue
        error = float(np.linalg.norm(det.center_uv - truth[j]))
        others = np.delete(truth, j, axis=0)
        if error <= MAX_PX:
            fate = "lost after stage two"
        elif len(others) and np.min(np.linalg.norm(others - det.center_uv, axis=1)) <= MAX_PX:
            fate = "stage two on a neighbour"
        else:
            fate = "stage two off"
        rows.append((gt.obj_id, fate, error))
    fates = [f for _, f, _ in rows]
    errors = [e for _, _, e in rows if e is not None]
    return fates, errors, rows


def _table_row(label: str, rows: list) -> str:
    counts = Counter(f for _, f, _ in rows)
    n = len(rows)
    shares = " | ".join(f"{counts[f]} ({counts[f] / max(n, 1):.0%})" for f in FATES)
    errors = [e for _, _, e in rows if e is not None]
    median = f"{np.median(errors):.1f}" if errors else "-"
    return f"| {label} | {n} | {shares} | {median} |"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", action="append", required=True, help="BOP dataset folder")
    parser.add_argument("--model", default=str(DEFAULT_MODEL), help="a two-stage ONNX model")
    parser.add_argument(
        "--by-object", action="store_true", help="a row per part type too, under each dataset's"
    )
    args = parser.parse_args(argv)
    print(f"model {args.model}")
    print("| dataset | parts | " + " | ".join(FATES) + " | stage-two error, median px |")
    print("|---|---|" + "---|" * len(FATES) + "---|")
    for root in args.dataset:
        ds = load_dataset(root)
        fe = NetworkFrontend(args.model, ds.catalog)
        if fe.crop_session is None:
            raise SystemExit(f"{args.model}: not a two-stage model")
        rows: list = []
        for view in ds.views():
            image = ds.scene(view.scene_id).load_rgb(view.im_id)
            rows += view_fates(fe, image, view)[2]
        print(_table_row(root, rows))
        if args.by_object:
            for obj_id in sorted({o for o, _, _ in rows}):
                label = f"{root}: {ds.catalog[obj_id].name}"
                print(_table_row(label, [r for r in rows if r[0] == obj_id]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
