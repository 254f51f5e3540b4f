"""Time of the learned front end per frame, split by stage, against the parts in view.

python -m posefuse.bench.frontend_speed --dataset DIR [--dataset DIR ...]
    [--model models/robi_like.onnx] [--frames 30] [--threads 2] [--spin] [--repeat 1]
    [--refine-min-offset F]

For each frame: the whole front end as it runs (``NetworkFrontend.detect``), and stage one
alone (pre-processing, the box detector and its peaks); stage two is the rest (crops, the crop
network on all crops at once, the refinement pass, voting, masks, duplicate removal). Medians
are printed per dataset and per number of detections (1-10, 11-20, 21+). ``--spin`` times
the front end with onnxruntime's threads spinning after each run (its own default) instead of
sleeping (``NetworkFrontend``'s). ``--repeat N`` times each frame N times and keeps the
fastest of each part: on a shared machine whose neighbours take the cores now and then, the
least time is the front end's own (the medians of single runs moved by 10 to 40% between two
runs of the same code). ``--refine-min-offset`` times another ``refine_min_offset`` than the
card's.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

from posefuse.estimator.frontend.network import NetworkFrontend
from posefuse.evaluation.dataset import load_dataset


def time_frame(frontend: NetworkFrontend, image: np.ndarray) -> tuple[dict, int]:
    """Seconds of one frame through the front end's own ``detect`` (both stages, the
    refinement pass, voting, masks and duplicate removal), and of stage one alone
    (pre-processing, the box detector and its peaks); the number of detections."""
    t = {}
    if frontend.crop_session is not None:
        t0 = time.perf_counter()
        frontend.boxes(image)
        t["stage_one"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    dets = frontend.detect(image)
    t["total"] = time.perf_counter() - t0
    if "stage_one" in t:
        t["stage_two"] = max(t["total"] - t["stage_one"], 0.0)
    return t, len(dets)


def main(argv: list[str] | None = None) -> int:
    from posefuse.service.resources import DEFAULT_MODEL

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", action="append", required=True)
    parser.add_argument("--model", default=DEFAULT_MODEL)
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--spin", action="store_true", help="threads spin after a run")
    parser.add_argument(
        "--repeat", type=int, default=1, help="time each frame this often, keep the fastest"
    )
    parser.add_argument("--refine-min-offset", type=float, default=None)
    args = parser.parse_args(argv)
    if args.repeat < 1 or args.frames < 1:
        parser.error("--repeat and --frames must be at least 1")
    if args.refine_min_offset is not None and not args.refine_min_offset >= 0:
        parser.error("--refine-min-offset must be at least 0")
    buckets: dict[str, list[dict]] = {"1-10": [], "11-20": [], "21+": []}
    for root in args.dataset:
        ds = load_dataset(root)
        frontend = NetworkFrontend(args.model, ds.catalog, threads=args.threads, spin=args.spin)
        if args.refine_min_offset is not None:
            if frontend.crop_session is None:
                parser.error(f"--refine-min-offset: {args.model} is a one-stage model")
            frontend.two_stage = dataclasses.replace(
                frontend.two_stage, refine_min_offset=args.refine_min_offset
            )
        views = list(ds.views())[: args.frames]
        images = [ds.scene(v.scene_id).load_rgb(v.im_id) for v in views]
        frontend.detect(images[0])  # warm-up
        rows = []
        for image in images:
            runs = [time_frame(frontend, image) for _ in range(args.repeat)]
            t = {k: min(r[0][k] for r in runs) for k in runs[0][0]}
            n = runs[0][1]
            t["n"] = n
            rows.append(t)
            key = "1-10" if n <= 10 else "11-20" if n <= 20 else "21+"
            buckets[key].append(t)
        pools = "spinning" if args.spin else "sleeping"
        runs = f", fastest of {args.repeat}" if args.repeat > 1 else ""
        print(_summary(f"{root} ({len(rows)} frames, {args.threads} threads {pools}{runs})", rows))
    for key, rows in buckets.items():
        if rows:
            print(_summary(f"frames with {key} detections", rows))
    return 0


def _summary(title: str, rows: list[dict]) -> str:
    keys = [k for k in ("stage_one", "stage_two") if k in rows[0]]
    parts = ", ".join(f"{k} {np.median([r[k] for r in rows]) * 1000:.1f}" for k in keys)
    total = [r["total"] for r in rows]
    return (
        f"{title}: {np.median([r['n'] for r in rows]):.0f} detections (median); "
        f"whole front end median {np.median(total) * 1000:.1f} ms, p90 "
        f"{np.percentile(total, 90) * 1000:.1f} ms" + (f" ({parts} ms)" if parts else "")
    )


if __name__ == "__main__":
    raise SystemExit(main())
