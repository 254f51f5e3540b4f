"""Cost of one rotation measurement per object per view, two-step versus multi-scale.

python -m posefuse.bench.rotation_measure --dataset DIR [--rois 200]

On the views of a BOP dataset, for every instance with visib_fract > 0.75 (up to --rois), with
the true translation and the visible mask (what the translation step and the front end give):

- two-step (ours): scale-aware re-crop to l_r = 128 px, LINE-2D responses, the bank scored at
  the known center;
- multi-scale ("simultaneous" ablation of the paper): no re-crop; the RoI is cut at the image's
  own scale, large enough for the nearest part, and the templates at 9 distances
  (bench.baselines.MultiScaleMatcher) are scored at the known center;
- for reference, ``cv2.linemod.Detector.match`` of the single-scale bank on the re-cropped RoI
  (it searches every position).

Prints the median milliseconds per object and view, and the ratio.
"""

from __future__ import annotations

import argparse
import time
from collections import defaultdict

import numpy as np

from posefuse.bench.baselines import MultiScaleMatcher
from posefuse.estimator.rotation.matching import RotationMatcher
from posefuse.estimator.rotation.recrop import crop_roi
from posefuse.estimator.rotation.templates import build_template_bank, make_detector
from posefuse.evaluation.dataset import load_dataset


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", required=True)
    parser.add_argument("--rois", type=int, default=200)
    parser.add_argument("--linemod-rois", type=int, default=20)
    args = parser.parse_args(argv)
    ds = load_dataset(args.dataset)
    matchers = {k: RotationMatcher(build_template_bank(m)) for k, m in ds.catalog.items()}
    multi: dict[int, MultiScaleMatcher] = {}
    times = defaultdict(list)
    per_object: dict[int, dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
    n = 0
    for view in ds.views():
        scene = ds.scene(view.scene_id)
        image = scene.load_rgb(view.im_id)
        K = view.camera.K
        for gt in view.gts:
            if gt.visib_fract <= 0.75 or n >= args.rois:
                continue
            n += 1
            mask = scene.load_mask_visib(view.im_id, gt.gt_idx)
            t_cam = gt.T_cam_obj[:3, 3]
            matcher = matchers[gt.obj_id]
            start = time.perf_counter()
            roi, roi_mask = crop_roi(image, K, t_cam, matcher.bank, mask)
            int(np.argmax(matcher.scores(roi, roi_mask)))
            times["two-step"].append(time.perf_counter() - start)
            per_object[gt.obj_id]["two-step"].append(times["two-step"][-1])

            if gt.obj_id not in multi:
                multi[gt.obj_id] = MultiScaleMatcher(matcher)
            start = time.perf_counter()
            uv = K[:2, :2] @ (t_cam[:2] / t_cam[2]) + K[:2, 2]
            int(np.argmax(multi[gt.obj_id].scores(image, K, uv, mask)))
            times["multi-scale"].append(time.perf_counter() - start)
            per_object[gt.obj_id]["multi-scale"].append(times["multi-scale"][-1])

            if len(times["linemod"]) < args.linemod_rois:
                # cv2.linemod's own matcher searches every position; its cost per template does
                # not depend on which templates it holds, so time it with 300 templates taken
                # from this RoI (the same 63 features each)
                det = make_detector(matcher.bank.config)
                added = sum(det.addTemplate([roi], "t", roi_mask)[0] >= 0 for _ in range(300))
                if added:
                    start = time.perf_counter()
                    det.match([roi], 80.0, ["t"], [roi_mask])
                    times["linemod"].append((time.perf_counter() - start, added))
        if n >= args.rois:
            break
    two = np.median(times["two-step"]) * 1000
    many = np.median(times["multi-scale"]) * 1000
    print(
        f"{n} RoIs of {args.dataset}; bank sizes "
        + ", ".join(f"{ds.catalog[k].name} {len(m.bank)}" for k, m in matchers.items())
    )
    print(
        f"two-step (re-crop + 1 scale), per object per view: median {two:.2f} ms, "
        f"p90 {np.percentile(times['two-step'], 90) * 1000:.2f} ms"
    )
    print(
        f"multi-scale (9 distances, no re-crop), same RoIs: median {many:.2f} ms, "
        f"p90 {np.percentile(times['multi-scale'], 90) * 1000:.2f} ms"
    )
    print(f"ratio multi-scale / two-step: {many / two:.1f}x")
    print("| object | templates | RoIs | two-step ms | multi-scale ms | ratio |")
    print("|---|---|---|---|---|---|")
    for obj_id, t in sorted(per_object.items()):
        a, b = np.median(t["two-step"]) * 1000, np.median(t["multi-scale"]) * 1000
        print(
            f"| {ds.catalog[obj_id].name} | {len(matchers[obj_id].bank)} | "
            f"{len(t['two-step'])} | {a:.2f} | {b:.2f} | {b / a:.1f}x |"
        )
    if times["linemod"]:
        per_tpl = np.median([t / k for t, k in times["linemod"]]) * 1e6
        print(
            f"cv2.linemod.Detector.match, every position of a 128 px RoI: "
            f"{per_tpl:.1f} us per template"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
