"""Association and translation of the tracker on a front end's detections, without rotations.

python -m posefuse.bench.association --dataset DIR [--frontend network|oracle] [--model M.onnx]
                            [--cache FILE.pkl]

Runs the front end once over the dataset (its labelled detections, masks dropped, can be kept
in ``--cache`` and reused: the tracker's own figures then take seconds), then the translation
tracker of ``run-dataset`` (no rotation step), and prints the association recall and precision
and the NEES of the 3D translation after the last checkpoint. Used to tune the tracker on the
tuning seeds only (docs/frontend.md).
"""

from __future__ import annotations

import argparse
import pickle
from dataclasses import replace
from pathlib import Path

import numpy as np

from posefuse.estimator.tracker import TrackerConfig
from posefuse.evaluation.dataset import load_dataset
from posefuse.evaluation.oracle import OracleConfig, OracleFrontend
from posefuse.evaluation.run_dataset import LabelledNetworkFrontend, run_dataset, summary_markdown


class CachedFrontend:
    """Labelled detections of every view, computed once (masks dropped to keep it small)."""

    def __init__(self, dataset, frontend, cache: str | None = None):
        self.by_view: dict[tuple[int, int], list] = {}
        path = Path(cache) if cache else None
        if path is not None and path.is_file():
            self.by_view = pickle.loads(path.read_bytes())
            return
        for view in dataset.views():
            pairs = frontend.detect_with_truth(view)
            self.by_view[(view.scene_id, view.im_id)] = [
                (replace(d, mask=None), k) for d, k in pairs
            ]
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(pickle.dumps(self.by_view))

    def detect_with_truth(self, view):
        return self.by_view[(view.scene_id, view.im_id)]


def with_setting(config, path: list[str], value: float):
    """A copy of a (nested) frozen config with one field set; ints stay ints."""
    head = path[0]
    if not hasattr(config, head):
        raise SystemExit(f"--set: {type(config).__name__} has no field {head!r}")
    old = getattr(config, head)
    if len(path) > 1:
        return replace(config, **{head: with_setting(old, path[1:], value)})
    return replace(config, **{head: type(old)(value)})


def main(argv: list[str] | None = None) -> int:
    from posefuse.service.resources import DEFAULT_MODEL

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", required=True)
    parser.add_argument("--frontend", choices=("network", "oracle"), default="network")
    parser.add_argument("--model", default=DEFAULT_MODEL)
    parser.add_argument("--cache", help="pickle of the labelled detections (made if missing)")
    parser.add_argument("--sigma-px", type=float, default=2.0, help="oracle center noise")
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="a tracker setting, e.g. founding.hold_views=3 (repeatable)",
    )
    args = parser.parse_args(argv)
    config = TrackerConfig()
    for item in args.set:
        key, _, value = item.partition("=")
        config = with_setting(config, key.split("."), float(value))
    ds = load_dataset(args.dataset)
    if args.frontend == "network":
        from posefuse.estimator.frontend.network import NetworkFrontend

        inner = LabelledNetworkFrontend(ds, NetworkFrontend(args.model, ds.catalog))
    else:
        inner = OracleFrontend(ds, OracleConfig(center_sigma_px=args.sigma_px, with_masks=False))
    frontend = CachedFrontend(ds, inner, args.cache)
    run = run_dataset(ds, frontend, config, show_progress=False)
    print(summary_markdown(run, ds.catalog))
    last = max(r.n_views for r in run.rows) if run.rows else 0
    values = np.array([r.nees for r in run.rows if r.n_views == last])
    if len(values):
        print(
            f"NEES after {last} views: max {values.max():.1f}, "
            f"share above 30: {np.mean(values > 30):.3f}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
