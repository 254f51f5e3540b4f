"""``posefuse run-active``: the estimator chooses where the camera looks next, in closed loop.

With ``--profile`` it renders synthetic bins and the candidates are the scene's own path and a
hemisphere over the bin (any of them rendered when chosen); with ``--dataset`` the candidates are
a BOP scene's recorded views. Each step prints the view taken, its score and the objects; with
ground truth, the share of the instances found (ADD-sym < 0.1 d).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from posefuse.cli.common import RUNS, add_command
from posefuse.estimator.core.errors import PosefuseError
from posefuse.service.resources import DEFAULT_CATALOG, DEFAULT_MODEL


def register(subparsers) -> None:
    p = add_command(
        subparsers,
        "run-active",
        "choose each next view by next-best-view and fuse it, in simulation",
        "Closes the loop: the policy picks a view among the candidates, the view is rendered "
        "(--profile) or read (--dataset), the learned front end detects, the estimator fuses; "
        "until --budget views or until every confirmed object is at least --confidence "
        "confident. Writes OUT/active.json (views taken, scores, estimates, accuracy).",
    )
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--profile", choices=("mixed", "robi"), help="render synthetic bins")
    src.add_argument("--dataset", help="BOP dataset folder: its recorded views are candidates")
    p.add_argument("--scenes", type=int, default=1, help="bins (--profile) or scenes to run")
    p.add_argument("--seed", type=int, default=0, help="scene seed (--profile)")
    p.add_argument(
        "--policy",
        choices=("nbv", "random", "sweep"),
        default="nbv",
        help="how the next view is chosen: next-best-view, a seeded random order, the path",
    )
    p.add_argument("--budget", type=int, default=8, help="views at most")
    p.add_argument("--confidence", type=float, default=None, help="stop at this confidence")
    p.add_argument("--model", default=DEFAULT_MODEL, help="front-end ONNX model")
    p.add_argument("--catalog", default=DEFAULT_CATALOG, help="BOP catalog folder (--profile)")
    p.add_argument("--out", default=f"{RUNS}/active", help="folder for active.json")
    p.set_defaults(func=_cmd_run_active)


def _cmd_run_active(args: argparse.Namespace) -> int:
    # lazy: the estimator and the simulation load trimesh, scipy and cv2 (~0.6 s)
    from posefuse.estimator.core.objects import load_catalog
    from posefuse.estimator.frontend.network import NetworkFrontend
    from posefuse.estimator.tracker import MultiViewEstimator
    from posefuse.sim.active import (
        ActiveConfig,
        RecordedScene,
        RenderedScene,
        run_policy,
        score_steps,
    )

    try:
        config = ActiveConfig(budget=args.budget, confidence=args.confidence)
    except ValueError as exc:
        raise PosefuseError(f"run-active: {exc}") from None
    if args.scenes < 1:
        raise PosefuseError("run-active: --scenes must be at least 1")
    if args.dataset:
        from posefuse.evaluation.dataset import load_dataset  # lazy: as above

        dataset = load_dataset(args.dataset)
        catalog = dataset.catalog
        scene_ids = list(dataset.scene_ids)[: args.scenes]
    else:
        catalog = load_catalog(args.catalog)
        scene_ids = list(range(args.scenes))
    network = NetworkFrontend(args.model, catalog)
    shared = MultiViewEstimator(catalog, show_progress=True)
    shared.warm_up()
    report = []
    for scene_id in scene_ids:

        def detect(image, k, _sid=scene_id):
            return network.detect(image)

        if args.dataset:
            source = RecordedScene(dataset.scene(scene_id), detect)
            where = f"{args.dataset} scene {scene_id}"
        else:  # lazy: as above
            from posefuse.sim.scenes import PROFILES, REALSENSE_1280x720, make_scene
            from posefuse.sim.synth import scene_seed

            spec = PROFILES[args.profile]
            seed = scene_seed(args.seed, scene_id)
            scene = make_scene(catalog, spec, seed, REALSENSE_1280x720)
            source = RenderedScene(catalog, scene, spec, detect, config, seed + 1)
            where = f"{args.profile} bin {scene_id} (seed {args.seed})"
        print(f"{where}: {len(source.candidates)} candidate views, policy {args.policy}")
        estimator = MultiViewEstimator(catalog, banks=shared.banks())
        truth = source.truth()

        counter = iter(range(1, config.budget + 1))

        def show(step, counter=counter):
            view = next(counter)
            confirmed = sum(e.status == "confirmed" for e in step.estimates)
            score = "" if step.score != step.score else f" score {step.score:6.2f} nats,"
            print(
                f"  view {view}: candidate {step.candidate:3d},{score} {len(step.estimates)} "
                f"estimates ({confirmed} confirmed), {step.objects_needing_views} need views"
            )

        run = run_policy(source, estimator, args.policy, config, seed=scene_id, on_step=show)
        found = score_steps(run, truth, catalog) if truth is not None else None
        if found:
            last = found[-1]
            print(
                f"  stopped ({run.stopped}) after {len(run.steps)} views: ADD-sym < 0.1 d "
                f"{last['add_sym']}/{last['n']}, MSSD < 0.1 d {last['mssd']}/{last['n']}"
            )
        else:
            print(f"  stopped ({run.stopped}) after {len(run.steps)} views")
        report.append(
            {
                "scene": scene_id,
                "policy": args.policy,
                "stopped": run.stopped,
                "views": [
                    {
                        "candidate": s.candidate,
                        "T_world_cam": source.candidates[s.candidate].T_world_cam.tolist(),
                        "score": None if s.score != s.score else s.score,
                        "objects": len(s.estimates),
                        "objects_needing_views": s.objects_needing_views,
                    }
                    for s in run.steps
                ],
                "accuracy": found,
            }
        )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "active.json").write_text(json.dumps(report, indent=1) + "\n")
    print(f"wrote {out / 'active.json'}")
    return 0
