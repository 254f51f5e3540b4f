"""Time of the learned front end per 1280x720 frame: pre-processing, network, voting.

python -m bench.frontend_speed --dataset DIR [--model models/robi_like.onnx] [--frames 30]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from estimator.dataset import load_dataset
from estimator.frontend.network import NetworkFrontend, preprocess


def main(argv: list[str] | None = None) -> int:
    from service.resources import DEFAULT_MODEL

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", required=True)
    parser.add_argument("--model", default=DEFAULT_MODEL)
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args(argv)
    ds = load_dataset(args.dataset)
    frontend = NetworkFrontend(args.model, ds.catalog, threads=args.threads)
    views = list(ds.views())[: args.frames]
    images = [ds.scene(v.scene_id).load_rgb(v.im_id) for v in views]
    frontend.detect(images[0])  # warm-up
    total, net = [], []
    for k, image in enumerate(images):
        start = time.perf_counter()
        frontend.session.run(None, {frontend.input_name: preprocess(image, frontend.card)})
        net.append(time.perf_counter() - start)
        start = time.perf_counter()
        frontend.detect(image, stamp_seed=k)
        total.append(time.perf_counter() - start)
    total_ms, net_ms = np.median(total) * 1000, np.median(net) * 1000
    print(f"{len(images)} frames of {args.dataset}, {args.threads} onnxruntime threads")
    print(f"pre-processing + network: median {net_ms:.1f} ms")
    print(
        f"pre-processing + network + voting (whole front end): median {total_ms:.1f} ms, "
        f"p90 {np.percentile(total, 90) * 1000:.1f} ms"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
