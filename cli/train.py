"""Training the learned front end.

- ``posefuse train``: the center-voting front end on synthetic renders of a catalog
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from cli.common import add_command
from estimator.errors import PosefuseError
from service.resources import DEFAULT_CATALOG


def _cmd_train(args: argparse.Namespace) -> int:
    try:
        import torch  # noqa: F401
    except ImportError:
        raise PosefuseError(
            'training needs torch: pip install -e ".[train]" (a CPU build, torch==2.13.0)'
        ) from None
    from estimator.objects import load_catalog
    from sim.train import TrainConfig, train

    load_catalog(args.catalog)  # a CatalogError before any work
    if not args.out.endswith(".onnx"):
        raise PosefuseError(f"--out: {args.out!r} must end in .onnx")
    config = TrainConfig(
        n_scenes=args.scenes,
        views_per_scene=args.views,
        val_scenes=args.val_scenes,
        minutes=args.minutes,
        max_iterations=args.iterations,
        batch=args.batch,
        seed=args.seed,
        workers=args.workers,
        robi_fraction=args.robi_fraction,
    )
    card = train(args.catalog, args.out, config)
    print(json.dumps(card, indent=2))
    print(f"wrote {args.out} and {Path(args.out).with_suffix('.json')}")
    return 0


def register(subparsers) -> None:
    p = add_command(
        subparsers,
        "train",
        "train the center-voting front end on synthetic renders",
        "Needs the train extra (torch, CPU). The shipped model is models/robi_like.onnx; "
        "replacing it takes an explicit --out models/robi_like.onnx.",
    )
    p.add_argument("--catalog", default=DEFAULT_CATALOG, help="BOP catalog folder")
    p.add_argument(
        "--out", required=True, help="NAME.onnx to write (its model card NAME.json beside)"
    )
    p.add_argument("--scenes", type=int, default=400, help="training scenes to render")
    p.add_argument("--views", type=int, default=4, help="views per training scene")
    p.add_argument("--val-scenes", type=int, default=12, help="validation scenes to render")
    p.add_argument("--minutes", type=float, default=40.0, help="training time budget")
    p.add_argument("--iterations", type=int, default=100_000, help="at most this many steps")
    p.add_argument("--batch", type=int, default=8, help="images per training step")
    p.add_argument("--workers", type=int, default=2, help="rendering processes")
    p.add_argument(
        "--seed",
        type=int,
        default=0,
        help="seed of the initial weights, the batches and the augmentation",
    )
    p.add_argument(
        "--robi-fraction",
        type=float,
        default=0.5,
        help="share of training scenes in the robi profile, the rest mixed",
    )
    p.set_defaults(func=_cmd_train)
