"""``posefuse bench``: the paper's Tables I and II (bench/paper_tables.py), a command the
project's own package adds through the ``posefuse.commands`` entry point ``bench``."""

from __future__ import annotations

import argparse

from posefuse.cli.common import add_command
from posefuse.service.resources import DEFAULT_CATALOG, DEFAULT_MODEL

# Relative to the current folder; the committed pages are regenerated with an explicit
# --out docs/benchmarks.md (or docs/benchmarks_network.md with --frontend network).
DEFAULT_BENCHMARKS = "runs/bench/benchmarks.md"


def _cmd_bench(args: argparse.Namespace) -> int:
    from posefuse.bench.paper_tables import main as bench_main

    return bench_main(args)


def register(subparsers) -> None:
    p = add_command(
        subparsers,
        "bench",
        "the paper's Tables I and II on rendered bins, every method on the same detections",
        "CosyPose-style RGB and RGBD fusion, the simultaneous ablation and ours. The committed "
        "pages are regenerated with an explicit --out docs/benchmarks.md (oracle) or "
        "--out docs/benchmarks_network.md (network).",
    )
    p.add_argument(
        "--dataset", required=True, help="a BOP dataset folder; rendered there if absent"
    )
    p.add_argument(
        "--quick", action="store_true", help="2 small scenes (640x360) instead of 50 (CI)"
    )
    p.add_argument(
        "--catalog", default=DEFAULT_CATALOG, help="BOP catalog of a dataset rendered here"
    )
    p.add_argument(
        "--out",
        default=DEFAULT_BENCHMARKS,
        help="the Markdown page to write (and its .json beside), relative to the current folder",
    )
    p.add_argument(
        "--profile",
        default="mixed",
        choices=["mixed", "robi"],
        help="scene profile of a dataset rendered by this command",
    )
    p.add_argument(
        "--frontend",
        default="oracle",
        choices=["oracle", "network"],
        help="the detections every method sees (oracle: the upper bound)",
    )
    p.add_argument(
        "--model", default=DEFAULT_MODEL, help="the network's ONNX model, with --frontend network"
    )
    p.set_defaults(func=_cmd_bench)
