"""Data commands: object catalogs, rendered BOP datasets, their scoring and their pictures.

- ``posefuse catalog``: write a BOP object catalog
- ``posefuse synth``: render a BOP multi-view bin-picking dataset
- ``posefuse eval``: score a BOP results CSV
- ``posefuse overlay``: draw the ground truth of one view over its image
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

from posefuse.cli.common import _catalog_table, add_command
from posefuse.estimator.core.errors import PosefuseError
from posefuse.service.resources import DEFAULT_CATALOG


def _cmd_catalog(args: argparse.Namespace) -> int:
    # lazy: the catalog modules load trimesh and scipy (~0.5 s), too slow for --help
    from posefuse.estimator.core.objects import Catalog, load_mesh, make_model, write_catalog
    from posefuse.evaluation.eval_points import with_eval_points

    if args.family is not None:
        from posefuse.sim.family import family_models  # lazy: manifold3d, trimesh

        if args.mesh:
            raise PosefuseError("--family and --mesh: give one or the other")
        if args.family < 1:
            raise PosefuseError(f"--family: {args.family}: must be at least 1")
        if not 130.0 <= args.family_max_mm <= 400.0:
            raise PosefuseError(f"--family-max-mm: {args.family_max_mm}: must be in [130, 400]")
        catalog = Catalog(family_models(args.family, args.family_seed, max_mm=args.family_max_mm))
        write_catalog(Path(args.out), catalog)
        from posefuse.sim.contact_sheet import write_family_sheet

        sheet = write_family_sheet(catalog, Path(args.out) / "family.png")
        print(f"wrote {len(catalog)} shapes of family seed {args.family_seed} to {args.out}")
        print(f"their picture: {sheet}")
        return 0
    if args.mesh:
        models = []
        for k, path in enumerate(args.mesh):
            name = Path(path).stem
            models.append(make_model(k + 1, name, load_mesh(path, units=args.units)))
        catalog = Catalog(models)
    else:
        from posefuse.sim.catalog import robi_like_catalog  # lazy: trimesh, scipy (~0.5 s)

        catalog = robi_like_catalog()
    write_catalog(Path(args.out), with_eval_points(catalog))
    print(f"wrote {len(catalog)} objects to {args.out}")
    print(_catalog_table(catalog))
    return 0


def _cmd_synth(args: argparse.Namespace) -> int:
    # lazy: the renderer loads trimesh, scipy and cv2 (~0.6 s)
    from posefuse.estimator.core.objects import load_catalog
    from posefuse.sim.scenes import INTRINSICS, PROFILES
    from posefuse.sim.synth import SynthConfig, generate_dataset

    camera = INTRINSICS.get(args.intrinsics)
    if args.camera:
        from posefuse.sim.scenes import camera_of_size  # lazy: trimesh, scipy, cv2 (~0.5 s)

        try:
            w, h = (int(x) for x in args.camera.lower().split("x"))
            camera = camera_of_size(w, h)
        except ValueError as exc:
            raise PosefuseError(
                f"--camera: {args.camera!r}: expected WIDTHxHEIGHT ({exc})"
            ) from None
    elif args.intrinsics not in INTRINSICS:
        raise PosefuseError(
            f"--intrinsics: unknown {args.intrinsics!r}; use one of {sorted(INTRINSICS)}"
        )
    if args.scenes < 1 or args.views < 1:
        raise PosefuseError("--scenes and --views must be at least 1")
    if args.workers < 1:
        raise PosefuseError(f"--workers: {args.workers}: must be at least 1")
    profile = PROFILES[args.profile]
    lo, hi = args.instances or profile.n_instances
    if not 1 <= lo <= hi:
        raise PosefuseError("--instances needs MIN MAX with 1 <= MIN <= MAX")
    catalog = load_catalog(args.catalog)
    obj_ids = tuple(args.obj_ids) if args.obj_ids else None
    for obj_id in obj_ids or ():
        catalog[obj_id]  # raises a CatalogError naming the catalog
    config = SynthConfig(
        n_scenes=args.scenes,
        seed=args.seed,
        split=args.split,
        first_scene_id=args.first_scene,
        camera=camera,
        scene=dataclasses.replace(profile, n_instances=(lo, hi), n_views=args.views),
        profile=args.profile,
        obj_ids=obj_ids,
    )
    start = time.perf_counter()
    generate_dataset(catalog, args.out, config, show_progress=not args.quiet, workers=args.workers)
    elapsed = time.perf_counter() - start
    print(f"wrote {args.scenes} scenes x {args.views} views to {args.out} in {elapsed:.1f} s")
    return 0


def _cmd_eval(args: argparse.Namespace) -> int:
    # lazy: the dataset and scoring load trimesh, scipy and cv2 (~0.5 s)
    from posefuse.evaluation.dataset import load_dataset
    from posefuse.evaluation.scores import evaluate, read_results, read_targets

    dataset = load_dataset(args.dataset, split=args.split)
    results = read_results(args.results)
    targets = read_targets(args.targets) if args.targets else None
    report = evaluate(
        dataset,
        results,
        threshold=args.threshold,
        min_visib=args.min_visib,
        targets=targets,
    )
    print(report.to_markdown())
    if args.json:
        Path(args.json).write_text(json.dumps(report.to_json(), indent=2) + "\n")
        print(f"wrote {args.json}")
    return 0


def _cmd_overlay(args: argparse.Namespace) -> int:
    # lazy: the dataset loads trimesh, scipy and cv2 (~0.5 s)
    from posefuse.evaluation.dataset import load_dataset
    from posefuse.sim.overlay import write_gt_overlay

    dataset = load_dataset(args.dataset, split=args.split)
    write_gt_overlay(dataset, args.scene, args.im, args.out)
    print(f"wrote {args.out}")
    return 0


def register(subparsers) -> None:
    p = add_command(
        subparsers,
        "catalog",
        "write a BOP object catalog (procedural parts or your meshes)",
        "Without --mesh: the five procedural parts. With meshes: one object per file, named "
        "after it, with its symmetries detected.",
    )
    p.add_argument("--out", required=True, help="output folder (models/ of a BOP dataset)")
    p.add_argument(
        "--mesh",
        action="append",
        metavar="FILE",
        help="a mesh file (STL/PLY/OBJ); repeat for more (default: the procedural parts)",
    )
    p.add_argument("--units", default="mm", choices=["mm", "cm", "m"], help="units of --mesh files")
    p.add_argument(
        "--family",
        type=int,
        default=None,
        metavar="N",
        help="N shapes of the procedural part family instead (the five parts first, then drawn "
        "turned parts, fasteners, fittings, brackets, gears, castings, plates, flanges, rings), "
        "for training a generalist front end; symmetries are not detected",
    )
    p.add_argument(
        "--family-seed",
        type=int,
        default=1,
        help="seed of the drawn family shapes (tuning families take seeds of their own)",
    )
    p.add_argument(
        "--family-max-mm",
        type=float,
        default=130.0,
        help="the family's largest parts: above 130 mm, 30%% of the drawn shapes are scaled up "
        "to a longest side log-uniform between 130 mm and this (at most 400)",
    )
    p.set_defaults(func=_cmd_catalog)

    p = add_command(subparsers, "synth", "render a BOP multi-view bin-picking dataset")
    p.add_argument("--catalog", default=DEFAULT_CATALOG, help="BOP catalog folder")
    p.add_argument("--out", required=True, help="dataset folder to write")
    p.add_argument("--scenes", type=int, default=2, help="bin scenes to render")
    p.add_argument("--views", type=int, default=8, help="camera views per scene")
    p.add_argument("--seed", type=int, default=0, help="random seed of the scenes")
    p.add_argument("--split", default="test", help="BOP split folder to write")
    p.add_argument("--first-scene", type=int, default=0, help="id of the first scene")
    p.add_argument(
        "--profile",
        default="mixed",
        choices=["mixed", "robi"],
        help="mixed: 5-15 parts of 1-3 types, cameras around the bin; robi: 20-40 parts of one "
        "type piled densely, an eye-in-hand sweep over the bin",
    )
    p.add_argument(
        "--instances",
        type=int,
        nargs=2,
        metavar=("MIN", "MAX"),
        help="parts per bin (default: the profile's, 5 15 for mixed, 20 40 for robi)",
    )
    p.add_argument(
        "--intrinsics", default="realsense", help="camera: realsense, realsense-640 or ensenso"
    )
    p.add_argument(
        "--camera",
        default=None,
        metavar="WIDTHxHEIGHT",
        help="another sensor size, e.g. 640x480 or 1920x1080: the RealSense's horizontal field "
        "of view at that resolution (instead of --intrinsics)",
    )
    p.add_argument(
        "--obj-ids",
        type=int,
        nargs="+",
        metavar="ID",
        help="only these objects of the catalog (default: all of them)",
    )
    p.add_argument(
        "--workers",
        type=int,
        default=1,
        help="processes rendering scenes, one scene each (the files are the same)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_synth)

    p = add_command(
        subparsers,
        "eval",
        "score a BOP results CSV: ADD-sym, MSSD, AR_MSSD and precision per object",
    )
    p.add_argument("--dataset", required=True, help="the BOP dataset folder the results are of")
    p.add_argument("--results", required=True, help="CSV: scene_id,im_id,obj_id,score,R,t,time")
    p.add_argument("--split", default="test", help="BOP split folder of the dataset")
    p.add_argument(
        "--threshold", type=float, default=0.1, help="error threshold, fraction of the diameter"
    )
    p.add_argument(
        "--min-visib",
        type=float,
        default=0.75,
        help="score only instances with a larger visible fraction",
    )
    p.add_argument(
        "--targets",
        metavar="FILE",
        help="JSON list of {scene_id, im_id}: score only these views (default: every view)",
    )
    p.add_argument(
        "--json", metavar="FILE", help="also write the report as JSON here (default: do not)"
    )
    p.set_defaults(func=_cmd_eval)

    p = add_command(subparsers, "overlay", "draw the ground truth of one view over its image")
    p.add_argument("--dataset", required=True, help="BOP dataset folder")
    p.add_argument("--split", default="test", help="BOP split folder of the dataset")
    p.add_argument("--scene", type=int, default=0, help="scene id")
    p.add_argument("--im", type=int, default=0, help="image id in the scene")
    p.add_argument("--out", required=True, help="PNG file to write")
    p.set_defaults(func=_cmd_overlay)
