"""Choose the two-stage front end's detection threshold on tuning sets.

python -m posefuse.bench.frontend_thresholds --model models/robi_like.onnx --dataset DIR
    [--dataset DIR ...] [--scores 0.2 0.3 ...] [--duplicates 0.3 0.5 ...] [--refine 0 1]
    [--refine-offsets 0 0.03 ...] [--by-class]

Every (peak threshold, duplicate factor) pair runs the front end over every view and is
scored with ``score_frontend``'s matching (recall of parts more
than 75% visible, precision, median center error, NEES); ``--by-class`` adds a row per class
under each (its detections against its parts). ``--refine-offsets`` tries the refinement pass's
``refine_min_offset`` too (a vote this close to its crop's center, as a share of the crop's
side, is not cropped again). Run it on tuning seeds only.
"""

from __future__ import annotations

import argparse
import dataclasses

from posefuse.estimator.frontend.network import NetworkFrontend
from posefuse.evaluation.dataset import load_dataset
from posefuse.evaluation.frontend_metrics import score_frontend


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", required=True)
    parser.add_argument("--dataset", action="append", required=True)
    parser.add_argument("--scores", type=float, nargs="+", default=[0.15, 0.2, 0.3, 0.4, 0.5])
    parser.add_argument("--duplicates", type=float, nargs="+", default=[0.3, 0.5, 0.7])
    parser.add_argument("--refine", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--refine-offsets", type=float, nargs="+", default=None)
    parser.add_argument("--by-class", action="store_true", help="a row per class too")
    args = parser.parse_args(argv)
    for root in args.dataset:
        ds = load_dataset(root)
        fe = NetworkFrontend(args.model, ds.catalog)
        base = fe.two_stage
        views = list(ds.views())
        images = {(v.scene_id, v.im_id): ds.scene(v.scene_id).load_rgb(v.im_id) for v in views}
        print(f"{root}: {len(views)} views")
        offsets = args.refine_offsets or [base.refine_min_offset]
        print(
            "| min score | duplicates | refine | min offset | recall | precision | median px "
            "| NEES |"
        )
        print("|---|---|---|---|---|---|---|---|")
        combos = [
            (t, f, r, o)
            for t in args.scores
            for f in args.duplicates
            for r in args.refine
            for o in (offsets if r else [0.0])
        ]
        for t, f, r, o in combos:
            fe.two_stage = dataclasses.replace(
                base, min_score=t, duplicate_factor=f, refine_passes=r, refine_min_offset=o
            )

            found = {(v.scene_id, v.im_id): fe.detect(images[(v.scene_id, v.im_id)]) for v in views}

            def detect(view, found=found):
                return found[(view.scene_id, view.im_id)]

            rows = [("", score_frontend(ds, detect, views))]
            if args.by_class:
                classes = sorted({g.obj_id for v in views for g in v.gts})
                rows += [
                    (f" {ds.catalog[k].name}", score_frontend(ds, detect, views, obj_id=k))
                    for k in classes
                ]
            for label, s in rows:
                print(
                    f"| {t:.2f}{label} | {f:.2f} | {r} | {o:.3f} | {s.recall:.4f} | "
                    f"{s.precision:.4f} | "
                    f"{s.median_center_error_px:.2f} | {s.mean_nees:.2f} |"
                )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
