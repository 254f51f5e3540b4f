"""``posefuse quickstart``: render a small bin, run the estimator over it and score it."""

from __future__ import annotations

import argparse
import dataclasses
import shlex
from pathlib import Path

from posefuse.cli.common import RUNS, add_command
from posefuse.cli.run import (
    DETECTION_LEGEND,
    ORACLE_CENTER_SIGMA,
    ORACLE_DROP_RATE,
    ORACLE_FALSE_POSITIVE_RATE,
    make_frontend,
    run_and_write,
    tracker_config,
)
from posefuse.evaluation.oracle import OracleConfig
from posefuse.service.resources import DEFAULT_CATALOG


def _cmd_quickstart(args: argparse.Namespace) -> int:
    # lazy: the catalog, renderer and scoring load trimesh, scipy and cv2 (~0.6 s)
    from posefuse.estimator.core.objects import load_catalog
    from posefuse.evaluation.dataset import load_dataset
    from posefuse.evaluation.scores import checkpoint_markdown
    from posefuse.sim.overlay import write_gt_overlay
    from posefuse.sim.scenes import SceneSpec
    from posefuse.sim.synth import SynthConfig, generate_dataset

    out = Path(args.out)
    catalog = load_catalog(args.catalog)
    print(f"1/4 rendering 1 bin scene x 8 views of {len(catalog)} parts into {out}")
    generate_dataset(
        catalog, out, SynthConfig(n_scenes=1, seed=args.seed, scene=SceneSpec(n_views=8))
    )
    dataset = load_dataset(out)
    overlay = out / "overlay_000000_000000.png"
    write_gt_overlay(dataset, 0, 0, overlay)
    print(f"2/4 ground-truth overlay of the first view: {overlay}")
    run_dir = out / "run"
    oracle = OracleConfig(
        center_sigma_px=ORACLE_CENTER_SIGMA,
        drop_rate=ORACLE_DROP_RATE,
        false_positive_rate=ORACLE_FALSE_POSITIVE_RATE,
        seed=args.seed,
    )
    print(
        f"3/4 running the estimator over the views one at a time into {run_dir}, on the oracle "
        f"front end (true centers + {ORACLE_CENTER_SIGMA:g} px noise, "
        f"{ORACLE_DROP_RATE:.0%} missed, {ORACLE_FALSE_POSITIVE_RATE:.0%} false positives)"
    )
    # the bin synth recorded, as run-dataset gives it by default
    config = dataclasses.replace(tracker_config(), bin=dataset.bin)
    report = run_and_write(
        dataset, make_frontend(dataset, "oracle", oracle), run_dir, "oracle", config=config
    )
    shown = {n: r for n, r in report.reports.items() if n in (4, 8)}
    print(f"4/4 the estimates after 4 and 8 views against the ground truth.\n\n{DETECTION_LEGEND}")
    print(checkpoint_markdown(shown))
    print(f"(all tables, 2 views too and the fate of every part, in {run_dir})\n")
    where = shlex.quote(str(out))
    print(
        f"next: posefuse run-dataset --dataset {where} --frontend network "
        f"--out {shlex.quote(str(out / 'run_net'))}  (the learned front end)"
    )
    print("      posefuse demo  (the daemon on Zenoh, replaying the demo recording)")
    return 0


def register(subparsers) -> None:
    p = add_command(
        subparsers,
        "quickstart",
        "render a small bin, run the estimator on it and score it",
        "Renders 1 bin scene x 8 views, draws the ground truth of the first view, runs the "
        "estimator over the views (oracle detections, as run-dataset) into OUT/run and prints "
        "its ADD-sym and MSSD after 4 and 8 views.",
    )
    p.add_argument("--catalog", default=DEFAULT_CATALOG, help="BOP catalog folder")
    p.add_argument(
        "--out",
        default=f"{RUNS}/quickstart",
        help="folder for the dataset and the run, relative to the current folder",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the scene and of the detections")
    p.set_defaults(func=_cmd_quickstart)
