"""Where the two-stage front end loses the parts it misses, stage by stage.

    python -m posefuse.bench.frontend_misses --dataset DIR [--dataset DIR2] [--model M.onnx]
        [--by-object] [--picture SCENE:IM PNG]

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
``--by-object`` adds a row per part type; ``--picture`` draws one view of the first dataset with
every part boxed in its fate's colour (:func:`fate_picture`).

``--true-boxes`` asks stage two alone: each part's crop cut around its own visible box, of its
own class (:func:`true_box_errors`), and the share of those whose centre lands within 15 px.
Where that share is high and the parts are still lost, stage one is what loses them; where it
is low, stage two cannot place the part even when it is handed the right box. The same table
gives the median error as a share of the part's box side: a centre 15 px off is 5% of a part
300 px long and a quarter of one 60 px long.
"""

from __future__ import annotations

import argparse
import dataclasses
from collections import Counter
from dataclasses import dataclass

import cv2
import numpy as np

from posefuse.estimator.frontend.network import NetworkFrontend, image_seed
from posefuse.estimator.frontend.two_stage import Box
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


def stage_one(fe: NetworkFrontend, image: np.ndarray) -> tuple[list[Box], list[Box]]:
    """Stage one's boxes (as ``fe.boxes``) and its peaks that scored in [LOW_PEAK, the card's
    min_score), from one run of the detector."""
    config = fe.two_stage
    low = dataclasses.replace(config, min_score=min(LOW_PEAK, config.min_score))
    boxes, low_boxes = fe.stage_one(image, [config, low])
    return boxes, [b for b in low_boxes if b.score < config.min_score]


@dataclass(frozen=True)
class PartFate:
    """Where the front end left one part of one view: its class, its fate (one of FATES), the
    stage-two center's error in px where it reached stage two (else None), and its visible box
    (x, y, w, h) in pixels."""

    obj_id: int
    fate: str
    error: float | None
    bbox_visib: tuple[float, float, float, float]


def view_fates(fe: NetworkFrontend, image: np.ndarray, view):
    """(fates, stage-two errors in px, rows) of one view's parts (visib > 0.75); rows: one
    :class:`PartFate` per part, in the fates' order."""
    boxes, weak_boxes = stage_one(fe, image)
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
        x, y, w, h = (float(v) for v in gt.bbox_visib)
        box = (x, y, w, h)
        if j in found:
            rows.append(PartFate(gt.obj_id, "found", None, box))
            continue
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
            fate = "a peak below the threshold" if seen else "no box"
            rows.append(PartFate(gt.obj_id, fate, None, box))
            continue
        det = first_pass[min(near)[1]]
        if det is None:
            rows.append(PartFate(gt.obj_id, "stage two empty", None, box))
            continue
        error = float(np.linalg.norm(det.center_uv - truth[j]))
        others = np.delete(truth, j, axis=0)
        if error <= MAX_PX:
            fate = "lost after stage two"
        elif len(others) and np.min(np.linalg.norm(others - det.center_uv, axis=1)) <= MAX_PX:
            fate = "stage two on a neighbour"
        else:
            fate = "stage two off"
        rows.append(PartFate(gt.obj_id, fate, error, box))
    fates = [r.fate for r in rows]
    errors = [r.error for r in rows if r.error is not None]
    return fates, errors, rows


@dataclass(frozen=True)
class TrueBoxError:
    """Stage two on one part's own box: its class, its visible box's longer side in px, and
    the distance in px from the centre stage two voted to its projected origin (None: none)."""

    obj_id: int
    side_px: float
    error: float | None


def true_box_errors(
    fe: NetworkFrontend, image: np.ndarray, view, offset: float = 0.0, size_factor: float = 1.0
) -> list[TrueBoxError]:
    """Stage two, one pass, on a box per part more than 75% visible: its visible box, of its
    class (any class for a generalist), scored as a confident box. One row per such part, in
    the order of ``view_fates``'s rows; ``error`` None where the crop gave no centre.

    ``offset`` moves each box's centre by that share of its longer side, in a direction drawn
    per part (seeded by the image), and ``size_factor`` scales its width and height: stage
    one's box as it errs (for the large parts of a part set about 0.13 of the side off and 0.9
    of the size: docs/lab/2026-12-06-large-parts-half-scale.md)."""
    gts, truth, _ = match_to_truth([], view, MAX_PX)
    obj_ids = [k for k, _ in fe.card.classes]
    directions = np.random.default_rng([image_seed(image), 3]).uniform(0, 2 * np.pi, len(gts))
    parts, boxes = [], []
    for j, gt in enumerate(gts):
        if gt.visib_fract <= MIN_VISIB:
            continue
        x, y, w, h = (float(v) for v in gt.bbox_visib)
        index = 0 if fe.card.agnostic else obj_ids.index(gt.obj_id)
        step = offset * max(w, h) * np.array([np.cos(directions[j]), np.sin(directions[j])])
        center = np.array([x + w / 2 - 0.5, y + h / 2 - 0.5]) + step
        boxes.append(Box(index, center, np.array([w, h]) * size_factor, 1.0))
        parts.append((j, gt.obj_id, max(w, h)))
    rng = np.random.default_rng([fe.seed, image_seed(image), 2])
    votes = fe.stage_two_votes(image, boxes, rng) if boxes else []
    return [
        TrueBoxError(
            obj_id, side, None if v is None else float(np.linalg.norm(v.center - truth[j]))
        )
        for (j, obj_id, side), v in zip(parts, votes, strict=True)
    ]


def _true_box_row(label: str, rows: list[TrueBoxError]) -> str:
    errors = np.array([np.inf if r.error is None else r.error for r in rows])
    sides = np.array([r.side_px for r in rows])
    n = len(rows)
    within = int((errors <= MAX_PX).sum())
    placed = np.isfinite(errors)
    median = f"{np.median(errors[placed]):.1f}" if placed.any() else "-"
    relative = f"{np.median(errors[placed] / sides[placed]):.3f}" if placed.any() else "-"
    side = f"{np.median(sides):.0f}" if n else "-"
    share = f"{within} ({within / max(n, 1):.0%})"
    return f"| {label} | {n} | {side} | {share} | {median} | {relative} |"


# the picture's colours (RGB), by fate
FATE_COLOURS = {
    "found": (40, 200, 40),
    "a peak below the threshold": (255, 150, 0),
    "no box": (220, 30, 30),
    "stage two empty": (160, 60, 220),
    "stage two on a neighbour": (230, 230, 40),
    "stage two off": (250, 110, 200),
    "lost after stage two": (40, 200, 230),
}


LEGEND_WIDTH = 250  # px, left of the view
WEAK_PEAK_COLOUR = (255, 210, 90)  # the rings of stage one's peaks below the threshold


def fate_picture(fe: NetworkFrontend, image: np.ndarray, view) -> np.ndarray:
    """(h, w, 3) uint8 RGB: the view with each part's visible box in its fate's colour
    (FATE_COLOURS), stage one's boxes at the card's threshold as filled dots and its peaks
    below it as rings, and a legend; cut to the parts' region."""
    out = image.copy()
    rows = view_fates(fe, image, view)[2]
    for r in rows:
        x, y, w, h = (int(round(v)) for v in r.bbox_visib)
        cv2.rectangle(out, (x, y), (x + w, y + h), FATE_COLOURS[r.fate], 2)
    boxes, weak = stage_one(fe, image)
    for b in boxes:
        cv2.circle(out, tuple(int(round(v)) for v in b.center), 5, (0, 0, 255), -1)
    for b in weak:
        cv2.circle(out, tuple(int(round(v)) for v in b.center), 5, WEAK_PEAK_COLOUR, 2)
    if rows:  # the parts' region, with a margin
        boxes = np.array([r.bbox_visib for r in rows])
        x0 = max(int(boxes[:, 0].min()) - 40, 0)
        y0 = max(int(boxes[:, 1].min()) - 40, 0)
        x1 = min(int((boxes[:, 0] + boxes[:, 2]).max()) + 40, out.shape[1])
        y1 = min(int((boxes[:, 1] + boxes[:, 3]).max()) + 40, out.shape[0])
        out = out[y0:y1, x0:x1]
    legend = np.full((max(out.shape[0], 220), LEGEND_WIDTH, 3), 255, np.uint8)

    def label(text: str, y: int) -> None:
        cv2.putText(legend, text, (36, y), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)

    for k, (fate, colour) in enumerate(FATE_COLOURS.items()):
        y = 20 + 24 * k
        cv2.rectangle(legend, (10, y - 12), (28, y + 4), colour, -1)
        label(fate, y)
    y = 20 + 24 * len(FATE_COLOURS)
    cv2.circle(legend, (19, y - 4), 5, (0, 0, 255), -1)
    label("stage one's box", y)
    cv2.circle(legend, (19, y + 20), 5, WEAK_PEAK_COLOUR, 2)
    label("a peak below the threshold", y + 24)
    canvas = np.full((legend.shape[0], out.shape[1], 3), 255, np.uint8)
    canvas[: out.shape[0]] = out
    return np.hstack([legend, canvas])


def _table_row(label: str, rows: list[PartFate]) -> str:
    counts = Counter(r.fate for r in rows)
    n = len(rows)
    shares = " | ".join(f"{counts[f]} ({counts[f] / max(n, 1):.0%})" for f in FATES)
    errors = [r.error for r in rows if r.error is not None]
    median = f"{np.median(errors):.1f}" if errors else "-"
    return f"| {label} | {n} | {shares} | {median} |"


def write_picture(root: str, model: str, view_key: str, png: str) -> None:
    """fate_picture of view ``SCENE:IM`` of the dataset at ``root``, written to ``png``."""
    try:
        scene_id, im_id = (int(v) for v in view_key.split(":"))
    except ValueError:
        raise SystemExit(f"--picture: expected SCENE:IM such as 0:0, got {view_key!r}") from None
    ds = load_dataset(root)
    views = [v for v in ds.views() if (v.scene_id, v.im_id) == (scene_id, im_id)]
    if not views:
        raise SystemExit(f"--picture: {root} has no view {view_key}")
    fe = NetworkFrontend(model, ds.catalog)
    image = ds.scene(scene_id).load_rgb(im_id)
    picture = fate_picture(fe, image, views[0])
    cv2.imwrite(png, cv2.cvtColor(picture, cv2.COLOR_RGB2BGR))
    print(f"wrote {png}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", action="append", required=True, help="BOP dataset folder")
    parser.add_argument("--model", default=str(DEFAULT_MODEL), help="a two-stage ONNX model")
    parser.add_argument(
        "--by-object", action="store_true", help="a row per part type too, under each dataset's"
    )
    parser.add_argument(
        "--picture",
        nargs=2,
        metavar=("SCENE:IM", "PNG"),
        help="also draw that view of the first dataset, each part in its fate's colour",
    )
    parser.add_argument(
        "--true-boxes",
        action="store_true",
        help="also stage two alone, on crops cut around each part's own visible box",
    )
    parser.add_argument(
        "--box-offset",
        type=float,
        default=0.0,
        help="with --true-boxes: each box's centre moved by this share of its longer side",
    )
    parser.add_argument(
        "--box-size",
        type=float,
        default=1.0,
        help="with --true-boxes: each box's width and height times this",
    )
    args = parser.parse_args(argv)
    if (args.box_offset, args.box_size) != (0.0, 1.0) and not args.true_boxes:
        parser.error("--box-offset and --box-size move the boxes of --true-boxes: add it")
    if args.picture:
        write_picture(args.dataset[0], args.model, *args.picture)
    print(f"model {args.model}")
    print("| dataset | parts | " + " | ".join(FATES) + " | stage-two error, median px |")
    print("|---|---|" + "---|" * len(FATES) + "---|")
    true_tables = []
    for root in args.dataset:
        ds = load_dataset(root)
        fe = NetworkFrontend(args.model, ds.catalog)
        if fe.crop_session is None:
            raise SystemExit(f"{args.model}: not a two-stage model")
        rows: list[PartFate] = []
        true_rows: list[TrueBoxError] = []
        for view in ds.views():
            image = ds.scene(view.scene_id).load_rgb(view.im_id)
            rows += view_fates(fe, image, view)[2]
            if args.true_boxes:
                true_rows += true_box_errors(fe, image, view, args.box_offset, args.box_size)
        print(_table_row(root, rows))
        if args.by_object:
            for obj_id in sorted({r.obj_id for r in rows}):
                label = f"{root}: {ds.catalog[obj_id].name}"
                print(_table_row(label, [r for r in rows if r.obj_id == obj_id]))
        true_tables.append((root, ds.catalog, true_rows))
    for root, catalog, true_rows in true_tables if args.true_boxes else []:
        moved = (
            f" (moved {args.box_offset:g} of its side, x{args.box_size:g} in size)"
            if (args.box_offset, args.box_size) != (0.0, 1.0)
            else ""
        )
        print(f"\nstage two on each part's own box{moved}, {root}:")
        print(
            "| part | parts | box side, median px | centre within 15 px | error, median px "
            "| error / box side, median |"
        )
        print("|---|---|---|---|---|---|")
        print(_true_box_row("all", true_rows))
        for obj_id in sorted({r.obj_id for r in true_rows}) if args.by_object else []:
            label = catalog[obj_id].name
            print(_true_box_row(label, [r for r in true_rows if r.obj_id == obj_id]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
