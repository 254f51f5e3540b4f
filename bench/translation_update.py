"""Cost of one translation update of one object with 8 views of history.

python -m posefuse.bench.translation_update [--repeats 2000]

An update appends the new view's center to the track and re-runs the robust Gauss-Newton from
the previous estimate, exactly as :class:`estimator.tracker.MultiViewEstimator` does. Prints the
median and the 90th percentile in milliseconds.
"""

from __future__ import annotations

import argparse
import platform
import time

import numpy as np

from posefuse.estimator.translation.gaussian import (
    CenterObservations,
    estimate_translation,
    prior_from_first_view,
)
from posefuse.sim.scenes import REALSENSE_1280x720, SceneSpec, sample_views


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=2000)
    parser.add_argument("--views", type=int, default=8)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    rng = np.random.default_rng(args.seed)
    cam = REALSENSE_1280x720
    T_world_cams = sample_views(SceneSpec(n_views=args.views + 1), rng)
    t_true = np.array([0.03, -0.02, 0.03])
    cov = np.eye(2) * 4.0
    obs = CenterObservations.empty()
    first = None
    for k, T_wc in enumerate(T_world_cams):
        T_cw = np.linalg.inv(T_wc)
        uv = cam.project(T_cw[:3, :3] @ t_true + T_cw[:3, 3]) + rng.normal(0, 2.0, 2)
        if first is None:
            first = prior_from_first_view(T_wc, cam.K, uv, 120.0, 0.08)
        if k == args.views:
            new_view = (T_cw, uv)
            break
        obs = obs.append(T_cw, cam.K, uv, cov, k)
    prior_mean, prior_cov = first
    previous = estimate_translation(obs, prior_mean, prior_cov)
    times = []
    for _ in range(args.repeats):
        start = time.perf_counter()
        grown = obs.append(new_view[0], cam.K, new_view[1], cov, args.views)
        estimate_translation(grown, prior_mean, prior_cov, start=previous.t_world_obj)
        times.append(time.perf_counter() - start)
    ms = np.array(times) * 1000
    print(
        f"machine: {platform.processor() or platform.machine()}, python {platform.python_version()}"
    )
    print(
        f"translation update, {args.views} views of history + 1 new, {args.repeats} runs: "
        f"median {np.median(ms):.3f} ms, p90 {np.percentile(ms, 90):.3f} ms"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
