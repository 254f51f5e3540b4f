"""Where the two-stage front end loses the parts it misses, stage by stage.

    python -m posefuse.bench.frontend_misses --dataset DIR [--dataset DIR2] [--model M.onnx]

Per annotated part more than 75% visible, in every view, the first of these that applies:

- **found**: the front end's final detections have it (matched as ``eval-frontend`` matches:
  same class, one to one, center within 15 px);
- **no box**: stage one has no box of its class whose center lies within 0.3 x the longer side
  of the part's visible box from that box's center;
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
from collections import Counter

import numpy as np

from posefuse.estimator.frontend.network import NetworkFrontend, image_seed
from posefuse.evaluation.dataset import load_dataset
from posefuse.evaluation.frontend_metrics import match_to_truth
from posefuse.service.resources import DEFAULT_MODEL

FATES = (
    "found",
    "no box",
    "stage two empty",
    "stage two on a neighbour",
    "stage two off",
    "lost after stage two",
)
MAX_PX = 15.0
BOX_NEAR = 0.3  # x the longer side of the part's visible box
MIN_VISIB = 0.75


def view_fates(fe: NetworkFrontend, image: np.ndarray, view):
    """(fates, stage-two errors in px) of one view's parts (visib > 0.75)."""
    boxes = fe.boxes(image)
    first_pass = fe.stage_two(image, boxes, np.random.default_rng([fe.seed, image_seed(image)]))
    final = fe.detect(image)
    agnostic = fe.card.agnostic  # a generalist's boxes and detections are of any class
    gts, truth, pairs = match_to_truth(final, view, MAX_PX, any_class=agnostic)
    found = set(pairs.values())
    obj_ids = [k for k, _ in fe.card.classes]
    fates, errors = [], []
    for j, gt in enumerate(gts):
        if gt.visib_fract <= MIN_VISIB:
            continue
        if j in found:
            fates.append("found")
            continue
        x, y, w, h = gt.bbox_visib
        visible_center = np.array([x + w / 2, y + h / 2])
        near = [
            (float(np.linalg.norm(b.center - visible_center)), i)
            for i, b in enumerate(boxes)
            if agnostic or obj_ids[b.class_index] == gt.obj_id
        ]
        if not near or min(near)[0] > BOX_NEAR * max(w, h):
            fates.append("no box")
            continue
        det = first_pass[min(near)[1]]
        if det is None:
            fates.append("stage two empty")
            continue
        error = float(np.linalg.norm(det.center_uv - truth[j]))
        errors.append(error)
        others = np.delete(truth, j, axis=0)
        if error <= MAX_PX:
            fates.append("lost after stage two")
        elif len(others) and np.min(np.linalg.norm(others - det.center_uv, axis=1)) <= MAX_PX:
            fates.append("stage two on a neighbour")
        else:
            fates.append("stage two off")
    return fates, errors


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", action="append", required=True, help="BOP dataset folder")
    parser.add_argument("--model", default=str(DEFAULT_MODEL), help="a two-stage ONNX model")
    args = parser.parse_args(argv)
    print(f"model {args.model}")
    print("| dataset | parts | " + " | ".join(FATES) + " | stage-two error, median px |")
    print("|---|---|" + "---|" * len(FATES) + "---|")
    for root in args.dataset:
        ds = load_dataset(root)
        fe = NetworkFrontend(args.model, ds.catalog)
        if fe.crop_session is None:
            raise SystemExit(f"{args.model}: not a two-stage model")
        counts: Counter = Counter()
        errors: list[float] = []
        for view in ds.views():
            image = ds.scene(view.scene_id).load_rgb(view.im_id)
            fates, errs = view_fates(fe, image, view)
            counts.update(fates)
            errors.extend(errs)
        n = sum(counts.values())
        shares = " | ".join(f"{counts[f]} ({counts[f] / max(n, 1):.0%})" for f in FATES)
        median = f"{np.median(errors):.1f}" if errors else "-"
        print(f"| {root} | {n} | {shares} | {median} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
