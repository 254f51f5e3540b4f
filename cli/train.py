"""Training the learned front end.

- ``posefuse train``: the two-stage front end on synthetic renders of a catalog, resumable
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from posefuse.cli.common import add_command
from posefuse.estimator.core.errors import PosefuseError
from posefuse.service.resources import DEFAULT_CATALOG


def bf16_choice(args: argparse.Namespace) -> bool | None:
    """``TrainConfig.bf16`` from the flags: ``--fp32`` False, ``--bf16`` True, neither None
    (bfloat16 autocast where the CPU has bfloat16 instructions: ``sim.train.native_bf16``)."""
    return False if args.fp32 else (True if args.bf16 else None)


def _cmd_train(args: argparse.Namespace) -> int:
    try:  # lazy: torch is the optional [train] extra
        import torch  # noqa: F401
    except ImportError:
        raise PosefuseError(
            'training needs torch: pip install -e ".[train]" (a CPU build, torch==2.13.0)'
        ) from None
    # lazy: the catalog and the training modules load trimesh, scipy and cv2 (~0.6 s)
    from posefuse.estimator.core.objects import load_catalog
    from posefuse.sim.train import TrainConfig, train

    load_catalog(args.catalog)  # a CatalogError before any work
    if not args.out.endswith(".onnx"):
        raise PosefuseError(f"--out: {args.out!r} must end in .onnx")
    if args.extend and not args.resume:
        raise PosefuseError("--extend: needs --resume (it lengthens a checkpoint's schedule)")
    if args.resume and not Path(args.resume).is_file():
        raise PosefuseError(f"--resume: {args.resume}: no such checkpoint")
    for root in args.tune:
        if not (Path(root) / "models").is_dir() and not any(Path(root).glob("*/0*")):
            raise PosefuseError(f"--tune: {root}: not a BOP dataset (posefuse synth writes one)")
    if args.input_scale is not None and not 0.1 <= args.input_scale <= 1.0:
        raise PosefuseError(f"--input-scale: {args.input_scale}: must be in [0.1, 1]")
    if args.width < 1:
        raise PosefuseError(f"--width: {args.width}: must be at least 1")
    for name in ("backgrounds", "composite"):
        if not 0.0 <= getattr(args, name) <= 1.0:
            raise PosefuseError(f"--{name}: {getattr(args, name)}: must be in [0, 1]")
    if args.crop_width is not None and args.crop_width < 1:
        raise PosefuseError(f"--crop-width: {args.crop_width}: must be at least 1")
    if args.vote_loss is not None and args.vote_loss < 0:
        raise PosefuseError(f"--vote-loss: {args.vote_loss}: must be at least 0")
    if args.threads is not None and args.threads < 1:
        raise PosefuseError(f"--threads: {args.threads}: must be at least 1")
    config = TrainConfig(
        n_scenes=args.scenes,
        views_per_scene=args.views,
        val_scenes=args.val_scenes,
        minutes=args.minutes,
        max_iterations=args.iterations,
        batch=args.batch,
        crop_batch=args.crop_batch,
        lr=args.lr,
        width=args.width,
        input_scale=args.input_scale,
        crop_width=args.crop_width,
        crop_box_channel=args.box_channel,
        dihedral=args.dihedral,
        photometric=args.photometric,
        backgrounds=args.backgrounds,
        composite=args.composite,
        seed=args.seed,
        workers=args.workers,
        threads=args.threads,
        robi_fraction=args.robi_fraction,
        data_dir=args.data_dir,
        checkpoint=args.checkpoint,
        checkpoint_minutes=args.checkpoint_minutes,
        tune=tuple(args.tune),
        bf16=bf16_choice(args),
        resume=args.resume,
        init=args.init,
        run_steps=args.run_steps,
        extend=(args.extend, args.extend_lr) if args.extend else None,
        vote_loss=args.vote_loss,
        agnostic=args.agnostic,
        materials=args.materials,
    )
    card = train(args.catalog, args.out, config)
    print(json.dumps(card, indent=2))
    print(f"wrote {args.out} and {Path(args.out).with_suffix('.json')}")
    return 0


def register(subparsers) -> None:
    p = add_command(
        subparsers,
        "train",
        "train the two-stage front end (boxes, then a center per crop) on synthetic renders",
        "Needs the train extra (torch, CPU). The shipped model is models/robi_like.onnx with "
        "its crop model models/robi_like_crop.onnx and checkpoint models/robi_like.ckpt; "
        "replacing it takes an explicit --out models/robi_like.onnx. A run ends at its step "
        "count or its time budget; --resume CKPT goes on with the checkpoint's data, seeds "
        "and schedule (see docs/training.md).",
    )
    p.add_argument("--catalog", default=DEFAULT_CATALOG, help="BOP catalog folder")
    p.add_argument(
        "--out", required=True, help="NAME.onnx to write (its model card NAME.json beside)"
    )
    p.add_argument("--scenes", type=int, default=200, help="training scenes to render")
    p.add_argument("--views", type=int, default=4, help="views per training scene")
    p.add_argument(
        "--val-scenes", type=int, default=8, help="calibration scenes to render (held out)"
    )
    p.add_argument("--minutes", type=float, default=40.0, help="this run's wall-clock budget")
    p.add_argument(
        "--iterations",
        type=int,
        default=40_000,
        help="the schedule's length in steps, over every resumed run (a resume keeps the "
        "checkpoint's)",
    )
    p.add_argument("--batch", type=int, default=16, help="detector crops per step")
    p.add_argument(
        "--lr", type=float, default=2e-3, help="peak learning rate of the schedule (AdamW)"
    )
    p.add_argument(
        "--width",
        type=int,
        default=16,
        help="stage one's width (the detector's backbone; stage two's too unless --crop-width); "
        "a resume or an --init keeps its checkpoint's",
    )
    p.add_argument(
        "--input-scale",
        type=float,
        default=None,
        help="stage one's input: the 1280x720 view resized by this (default 0.5); a training set "
        "rendered for another scale is resized from its full views, not rendered again; a "
        "resume keeps its checkpoint's, an --init its checkpoint's unless this is given (the "
        "same convolutions, fine-tuned at the new scale)",
    )
    p.add_argument(
        "--crop-width",
        type=int,
        default=None,
        help="stage two's width (default: the detector's, 16); with --init from a narrower "
        "checkpoint, a multiple of its width: the network is widened so that it starts "
        "computing what the narrower one did",
    )
    p.add_argument(
        "--box-channel",
        action="store_true",
        help="give stage two the box as a fourth input channel (with --init from a checkpoint "
        "without it, its first layer is widened with zero weights)",
    )
    p.add_argument(
        "--dihedral",
        action="store_true",
        help="augment with upside-down flips (both stages) and transposes (stage two) besides "
        "mirrors; kept in the checkpoint",
    )
    add_real_camera_options(p)
    p.add_argument(
        "--vote-loss",
        type=float,
        default=None,
        help="weight of the proxy voting loss on stage two's votes (0: off, the default; a "
        "resume keeps the checkpoint's unless given)",
    )
    p.add_argument("--crop-batch", type=int, default=48, help="stage-two crops per step")
    p.add_argument(
        "--data-dir",
        default=None,
        help="where rendered training sets are kept and reused (default: ~/.cache/posefuse/train)",
    )
    p.add_argument(
        "--checkpoint",
        default=None,
        help="the resumable checkpoint to write (default: NAME.ckpt beside --out)",
    )
    p.add_argument(
        "--checkpoint-minutes",
        type=float,
        default=30.0,
        help="minutes between checkpoints (each also scores --tune: the learning curve)",
    )
    p.add_argument(
        "--resume", default=None, help="a checkpoint to go on from (its data and schedule)"
    )
    p.add_argument(
        "--run-steps",
        type=int,
        default=None,
        help="stop this run after this many steps (the schedule is --iterations; resume later)",
    )
    p.add_argument(
        "--extend",
        type=int,
        default=None,
        help="with --resume: lengthen the schedule by a warm restart of this many steps after "
        "its end (linear warm-up, then a cosine from --extend-lr); kept in the checkpoint",
    )
    p.add_argument(
        "--extend-lr", type=float, default=1e-3, help="peak learning rate of --extend's restart"
    )
    p.add_argument(
        "--init",
        default=None,
        help="fine-tune from this checkpoint (another catalog's: its class heatmaps are "
        "replaced, the shared backbone and stage two kept)",
    )
    p.add_argument(
        "--tune",
        action="append",
        default=[],
        help="a BOP dataset scored at every checkpoint (repeat for several; tuning seeds only)",
    )
    precision = p.add_mutually_exclusive_group()
    precision.add_argument(
        "--fp32",
        action="store_true",
        help="train in float32 (default: bfloat16 autocast where the CPU has bfloat16 "
        "instructions, float32 elsewhere)",
    )
    precision.add_argument(
        "--bf16", action="store_true", help="train in bfloat16 autocast even without them"
    )
    p.add_argument("--workers", type=int, default=2, help="rendering processes")
    p.add_argument(
        "--threads",
        type=int,
        default=None,
        help="torch threads of the training loop (default: the cores other processes leave "
        "free, looked at every few steps)",
    )
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
    p.add_argument(
        "--agnostic",
        action="store_true",
        help="one class, 'a part', for every object: the generalist of a shape family "
        "(posefuse catalog --family), which onboarding fine-tunes from",
    )
    p.add_argument(
        "--materials",
        default="catalog",
        choices=["catalog", "random"],
        help="catalog: each part as it will be seen; random: a factory material drawn per part "
        "type and scene (metal, chrome, oxide, paint, plastic)",
    )
    p.set_defaults(func=_cmd_train)


def add_real_camera_options(p: argparse.ArgumentParser) -> None:
    """The training data's options for real photographs, shared by train and onboard."""
    p.add_argument(
        "--photometric",
        action="store_true",
        help="draw a real camera's exposure, white balance, tone curve, blur, noise and JPEG "
        "per training sample (sim.photometric); kept in the checkpoint",
    )
    p.add_argument(
        "--backgrounds",
        type=float,
        default=0.0,
        metavar="P",
        help="the share of training samples (both stages) whose background, all that is no "
        "part, is replaced by procedural clutter (sim.backgrounds: for photographs of parts "
        "among other things); kept in the checkpoint (default: 0, the bins as rendered)",
    )
    p.add_argument(
        "--composite",
        type=float,
        default=0.0,
        metavar="P",
        help="the share of training scenes composed from the parts rendered alone, in any "
        "orientation, onto clutter (sim.composite: many times faster than a rendered scene, "
        "without a bin's contact and shadows); kept in the checkpoint (default: 0, all "
        "rendered)",
    )
