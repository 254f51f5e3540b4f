"""Your own parts.

- ``posefuse onboard MESH... --out DIR``: CAD meshes to a servable part set (``DIR/parts.json``)
"""

from __future__ import annotations

import argparse
from pathlib import Path

from posefuse.cli.common import add_command
from posefuse.cli.train import add_real_camera_options
from posefuse.estimator.core.errors import PosefuseError


def _parse_symmetry(specs: list[str] | None) -> dict[str, str]:
    out: dict[str, str] = {}
    for spec in specs or ():
        name, sep, value = spec.partition("=")
        if not sep or not name or not value:
            raise PosefuseError(
                f"--symmetry {spec!r}: use NAME=SPEC, e.g. gear=continuous, gear=28:z, bolt=none"
            )
        out[name] = value
    return out


def _cmd_onboard(args: argparse.Namespace) -> int:
    try:  # lazy: torch is the optional [train] extra
        import torch  # noqa: F401
    except ImportError:
        raise PosefuseError(
            'onboard trains the front end and needs torch: pip install -e ".[train]" '
            "(a CPU build, torch==2.13.0)"
        ) from None
    from posefuse.sim.onboard import OnboardConfig, onboard, parts_table  # lazy: trimesh, scipy

    config = OnboardConfig(
        units=args.units,
        minutes=args.minutes,
        symmetry=_parse_symmetry(args.symmetry),
        views=args.views,
        held_scenes=args.held_scenes,
        held_instances=100 if args.held_instances is None else args.held_instances,
        fit_validation=args.held_instances is None,
        held_views=args.held_views,
        workers=args.workers,
        seed=args.seed,
        steps=args.steps,
        train_scenes=args.train_scenes,
        init=None if args.from_scratch else (args.init or "shipped"),
        photometric=args.photometric,
        backgrounds=args.backgrounds,
        composite=args.composite,
        frozen_backbones=args.frozen_backbones,
        scale_by_size=args.scale_by_size,
        class_balanced=args.class_balanced,
    )
    manifest = onboard(args.mesh, args.out, config)
    _write_demo(Path(args.out))
    print()
    print(parts_table(manifest))
    budget = (
        f"{manifest['training_steps']} training steps"
        if manifest["budget_minutes"] is None
        else f"a {manifest['budget_minutes']:g} min budget"
    )
    print(f"stages (s): {manifest['stage_seconds']}; {manifest['total_minutes']} min for {budget}")
    print(f"wrote {args.out}/parts.json; look at {args.out}/contact/*.png to confirm symmetries")
    print(f"next: posefuse demo --parts {args.out}   (its held-out mixed bins, scored)")
    print(f"      posefuse serve --parts {args.out}")
    return 0


DEMO_SCENES = 3  # of the held-out mixed bins, in DIR/demo.mcap


def _write_demo(out: Path) -> None:
    """DIR/demo.mcap: the first held-out mixed bins as a camera publishes them, for ``demo
    --parts``."""
    # lazy: the recorder and the dataset load mcap, scipy, trimesh and cv2 (~0.6 s)
    from posefuse.clients.demo import make_recording
    from posefuse.evaluation.dataset import load_dataset

    dataset = load_dataset(out / "validation" / "mixed")
    scenes = dataset.scene_ids[:DEMO_SCENES]
    make_recording(dataset, scenes, out / "demo.mcap", catalog=dataset.catalog)


def register(subparsers) -> None:
    p = add_command(
        subparsers,
        "onboard",
        "turn CAD meshes into a part set the daemon serves",
        "Reads the meshes, detects each part's symmetries (a contact sheet per part in "
        "DIR/contact/ shows the axes; near-symmetries are flagged for you to decide with "
        "--symmetry), builds the LINE-2D templates, renders training scenes and trains the "
        "front end until the budget's deadline, then measures the front end and ADD-sym on "
        "held-out renders of both scene profiles. `posefuse serve --parts DIR` (and demo, "
        "run-dataset, replay) take the result. Needs the train extra.",
    )
    p.add_argument(
        "mesh", nargs="+", help="mesh files (STL, PLY or OBJ); a part's name is its stem"
    )
    p.add_argument("--out", required=True, help="the part set folder to write")
    p.add_argument(
        "--units",
        default="mm",
        choices=["mm", "cm", "m"],
        help="units of the mesh files; a part outside 5 mm .. 2 m is refused as a unit mistake",
    )
    p.add_argument(
        "--minutes",
        type=float,
        default=15.0,
        help="budget of the whole command; training gets what the other stages leave",
    )
    p.add_argument(
        "--symmetry",
        action="append",
        metavar="NAME=SPEC",
        help="override a part's detected symmetry: none, continuous[:AXIS] or N[:AXIS] "
        "(AXIS x, y, z or main); repeat per part (default: detected)",
    )
    p.add_argument(
        "--steps",
        type=int,
        default=None,
        help="train a fixed number of steps on --train-scenes scenes instead of until the "
        "budget's deadline: the same front end on any machine (--minutes is then unused); "
        '0: no fine-tune at all, the initial model finds "a part" and the part set\'s '
        "templates name it (minutes instead of a quarter hour; fewer parts found and named)",
    )
    p.add_argument(
        "--train-scenes",
        type=int,
        default=24,
        help="training scenes rendered with --steps (default: 24)",
    )
    p.add_argument(
        "--init",
        default=None,
        help="fine-tune the front end from this checkpoint (default: the shipped model's, "
        "models/robi_like.ckpt: its backbone and stage two are kept, the class heatmaps new)",
    )
    p.add_argument(
        "--from-scratch", action="store_true", help="train the front end from random weights"
    )
    p.add_argument(
        "--frozen-backbones",
        action="store_true",
        help="fine-tune the necks and heads only: both stages' backbones keep the initial "
        "checkpoint's weights (cheaper steps, less to learn)",
    )
    p.add_argument(
        "--scale-by-size",
        action="store_true",
        help="find a part more than 1.4 times the largest the shipped model was trained on "
        "(88 mm) at half stage one's input scale, where it looks that size (an experiment: it "
        "found no more large parts in the evaluation; default: every part at the one scale)",
    )
    p.add_argument(
        "--class-balanced",
        action="store_true",
        help="draw each part type's training crops in inverse proportion to its share of the "
        "training renders' parts (an experiment; default: every part alike)",
    )
    add_real_camera_options(p)
    p.add_argument("--views", type=int, default=6, help="views per training scene")
    p.add_argument(
        "--held-instances",
        type=int,
        default=None,
        help="validation: render held-out scenes of each profile until this many parts are "
        "scored (more than 75%% visible) at 8 views (default: 100, fewer where the budget "
        "cannot hold them beside training, said in the output)",
    )
    p.add_argument(
        "--held-scenes",
        type=int,
        default=None,
        help="validation: this many held-out scenes per profile instead (default: as many as "
        "--held-instances needs)",
    )
    p.add_argument("--held-views", type=int, default=8, help="views per validation scene")
    p.add_argument("--workers", type=int, default=2, help="processes for rendering and templates")
    p.add_argument("--seed", type=int, default=0, help="seed of training and validation")
    p.set_defaults(func=_cmd_onboard)
