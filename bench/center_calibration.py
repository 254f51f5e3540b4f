"""How honest the front end's centre covariances are, by detection score, and their calibration.

python -m posefuse.bench.center_calibration --dataset DIR [--dataset DIR ...] [--model ONNX]
    [--edges 0.4,0.6,0.8,0.9] [--write]

Runs the learned front end over every view of the calibration datasets (renders with seeds
disjoint from every reported and tuning set; the shipped calibration: ``posefuse synth --profile
robi --out /tmp/cal_robi --scenes 4 --views 8 --seed 5353`` and ``--profile mixed --out
/tmp/cal_mixed --scenes 4 --views 8 --seed 5454``), matches each detection to the true centre
it lies on (within 15 px, the front end's own scoring), and prints per score bin the number of
matches and the 2D NEES ``e^T Sigma^-1 e`` (2 expected): mean, median, and the trimmed mean of
the 95% smallest. The factor of a bin is what its covariances must be multiplied by for the
trimmed mean NEES to be its expected value under a Gaussian trimmed the same way (a few
centres on the wrong part are the association gates' to refuse, not the covariance's to cover);
never below 1. With ``--write`` the factors go into the model card (``center_cov_by_score``),
where :class:`~posefuse.estimator.frontend.network.NetworkFrontend` applies them; the table is
then measured again with them.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

from posefuse.evaluation.center_calibration import nees_table
from posefuse.evaluation.dataset import load_dataset
from posefuse.evaluation.frontend_metrics import match_to_truth
from posefuse.service.resources import DEFAULT_MODEL


def collect(datasets, model: str) -> list[tuple[float, float]]:
    """(score, NEES) of every detection matched to a true centre in the datasets' views."""
    from posefuse.estimator.frontend.network import NetworkFrontend

    pairs = []
    for dataset in datasets:
        frontend = NetworkFrontend(model, dataset.catalog)
        views = list(dataset.views())
        for view in tqdm(views, desc=dataset.root.name, unit="view"):
            image = dataset.scene(view.scene_id).load_rgb(view.im_id)
            dets = frontend.detect(image)
            _, truth, matched = match_to_truth(dets, view)
            for i, j in matched.items():
                e = dets[i].center_uv - truth[j]
                pairs.append((dets[i].score, float(e @ np.linalg.solve(dets[i].center_cov, e))))
    return pairs


def table(pairs, edges: list[float]) -> list[dict]:
    """One row per score bin [lo, hi): n, mean, median, trimmed mean NEES and the factor."""
    return nees_table([s for s, _ in pairs], [n for _, n in pairs], edges)


def _print(rows, title: str) -> None:
    print(f"\n{title}\n")
    print("| score | matches | mean NEES | median | trimmed mean (95%) | factor |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        if not r["n"]:
            print(f"| [{r['lo']:.2f}, {r['hi']:.2f}) | 0 | - | - | - | - |")
            continue
        print(
            f"| [{r['lo']:.2f}, {r['hi']:.2f}) | {r['n']} | {r['mean']:.1f} | "
            f"{r['median']:.2f} | {r['trimmed_mean']:.2f} | {r['factor']:.2f} |"
        )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", action="append", required=True, help="calibration set")
    parser.add_argument("--model", default=str(DEFAULT_MODEL), help="ONNX model")
    parser.add_argument("--edges", default="0.4,0.6,0.8,0.9", help="score bin edges")
    parser.add_argument("--write", action="store_true", help="the factors into the model card")
    args = parser.parse_args(argv)
    edges = [float(x) for x in args.edges.split(",") if x]
    if edges != sorted(edges) or not all(0 < e < 1 for e in edges):
        parser.error(f"--edges must increase within (0, 1), got {args.edges}")
    datasets = [load_dataset(d) for d in args.dataset]
    rows = table(collect(datasets, args.model), edges)
    _print(rows, f"2D centre NEES by detection score ({args.model}; 2 expected)")
    if args.write:
        card_path = Path(args.model).with_suffix(".json")
        card = json.loads(card_path.read_text())
        card["center_cov_by_score"] = [[r["hi"], round(r.get("factor", 1.0), 3)] for r in rows]
        card_path.write_text(json.dumps(card, indent=2) + "\n")
        print(f"\nwrote center_cov_by_score to {card_path}")
        _print(table(collect(datasets, args.model), edges), "measured again with the factors")
    return 0


if __name__ == "__main__":
    sys.exit(main())
