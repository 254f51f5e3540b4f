"""Running the estimator offline: over BOP datasets, its template banks, the learned front end
(the quickstart that shows all of it on one small bin is ``cli/quickstart.py``).

- ``posefuse run-dataset``: the estimator over a BOP dataset, views one at a time, scored
- ``posefuse templates``: build (or load) the LINE-2D template banks of a catalog
- ``posefuse eval-frontend``: recall, precision and center accuracy of the learned front end
- ``posefuse frontend-overlay``: a picture of the learned front end's output on one view
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from posefuse.cli.common import add_command, add_parts_arg
from posefuse.estimator.core.errors import PosefuseError
from posefuse.evaluation.oracle import OracleConfig, OracleFrontend
from posefuse.service.resources import DEFAULT_CATALOG, DEFAULT_MODEL

# The oracle front end of run-dataset (and of the quickstart): true centers with this much
# Gaussian noise (px), this share of the instances missed and this many false positives per
# true detection.
ORACLE_CENTER_SIGMA = 2.0
ORACLE_DROP_RATE = 0.1
ORACLE_FALSE_POSITIVE_RATE = 0.05

DETECTION_LEGEND = (
    "Pose accuracy (instances with visib_fract > 0.75) in the view after which the "
    "estimates were taken: ADD-sym < 0.1 d (the headline; found instances in brackets), "
    "MSSD < 0.1 d, AR_MSSD (mean recall over MSSD thresholds 0.05-0.5 d), precision "
    "(found instances per estimate), and the lenient ADI < 0.1 d."
)

NOT_DETECTED_LEGEND = (
    "The instances not detected, by how many of the views so far detected them at all: never "
    "(the front end missed it in every view), in one view only (no second view to found a "
    "track with), or in two or more (held detections that founded no track)."
)

AMBIGUITY_LEGEND = (
    "The published poses of confirmed tracks whose instance shows more than 75%: those "
    "published unambiguous and the share right (ADD-sym < 0.1 d), those published ambiguous "
    "(a near-symmetric turn the views cannot rule out, published beside the pose), the share "
    "right, and the share whose truth is the pose or one of its published turns."
)


@dataclass
class DatasetReport:
    """What :func:`run_and_write` wrote, as text: the translation summary, and with the
    rotation step the scores per checkpoint (number of views), their table, the fates and the
    estimates kept above each confidence threshold."""

    summary: str
    reports: dict = field(default_factory=dict)
    table: str = ""
    fates: str = ""
    fates_legend: str = ""
    confidence: str = ""


def make_frontend(dataset, kind: str, oracle=None, model: str = DEFAULT_MODEL, seed: int = 0):
    """The detections of a run: ``oracle`` (noisy ground truth, ``oracle`` an OracleConfig) or
    ``network`` (the learned front end, labelled with the instance each lies on for scoring)."""
    if kind == "network":
        # lazy: cv2, and scipy/trimesh through run_dataset (~0.6 s), too slow for --help
        from posefuse.estimator.frontend.network import NetworkFrontend
        from posefuse.evaluation.run_dataset import LabelledNetworkFrontend

        return LabelledNetworkFrontend(dataset, NetworkFrontend(model, dataset.catalog, seed=seed))
    if kind == "oracle":
        return OracleFrontend(dataset, oracle)
    raise PosefuseError(f"--frontend: {kind!r} is not known; use oracle or network")


def run_and_write(
    dataset,
    frontend,
    out: Path,
    frontend_name: str,
    scene_ids: tuple[int, ...] | None = None,
    rotation: bool = True,
    quiet: bool = False,
    config=None,
    track_crops: bool = False,
) -> DatasetReport:
    """Run the estimator over ``dataset`` (views one at a time, one estimator per scene, the
    template banks built or loaded once) and write its tables into ``out``: translation errors,
    with ``rotation`` also BOP results and targets per checkpoint, their scores and the fate of
    every scored instance."""
    # lazy: the estimator and its scoring load scipy, trimesh and cv2 (~0.6 s)
    from posefuse.estimator.tracker import MultiViewEstimator
    from posefuse.evaluation.ambiguity import ambiguity_markdown, write_ambiguity
    from posefuse.evaluation.fates import fate_table, not_detected_table
    from posefuse.evaluation.run_dataset import (
        CHECKPOINTS,
        run_dataset,
        summary_markdown,
        write_fates,
        write_rows,
    )
    from posefuse.evaluation.scores import (
        checkpoint_markdown,
        evaluate,
        write_results,
        write_targets,
    )

    shared = MultiViewEstimator(dataset.catalog, config, show_progress=not quiet)
    if rotation:  # build (or load) every class's templates once, with a progress bar
        for obj_id in dataset.catalog:
            shared.matcher(obj_id)

    def factory():
        return MultiViewEstimator(dataset.catalog, config, banks=shared.banks())

    run = run_dataset(
        dataset,
        frontend,
        scene_ids=scene_ids,
        show_progress=not quiet,
        rotation=rotation,
        estimator_factory=factory,
        track_crops=track_crops,
    )
    write_rows(out / "translation_errors.csv", run.rows)
    summary = summary_markdown(run, dataset.catalog)
    (out / "translation_summary.md").write_text(
        "Median translation error (and relative to the camera distance) after 2, 4 and 8 "
        f"views.\n\n{summary}\n"
    )
    report = DatasetReport(summary)
    if not rotation:
        return report
    for n in CHECKPOINTS:
        if not run.targets[n]:
            continue
        write_results(out / f"results_{n}views.csv", run.results[n])
        write_targets(out / f"targets_{n}views.json", run.targets[n])
        report.reports[n] = evaluate(dataset, run.results[n], targets=run.targets[n])
    report.table = checkpoint_markdown(report.reports)
    (out / "detection_rate.md").write_text(f"{DETECTION_LEGEND}\n\n{report.table}\n")
    (out / "detection_rate.json").write_text(
        json.dumps({str(n): r.to_json() for n, r in report.reports.items()}, indent=1) + "\n"
    )
    write_fates(out / "fates.csv", run.fates)
    report.fates = fate_table(
        [f for f in run.fates if f.n_views >= 2], dataset.catalog, dataset.profile
    )
    report.fates_legend = (
        "Where each scored instance ended (estimator/fates.py gives the rules, first that "
        f"applies); profile {dataset.profile}, front end {frontend_name}."
    )
    missed = not_detected_table(
        [f for f in run.fates if f.n_views >= 2], dataset.catalog, dataset.profile
    )
    (out / "fates.md").write_text(
        f"{report.fates_legend}\n\n{report.fates}\n\n{NOT_DETECTED_LEGEND}\n\n{missed}\n"
    )
    from posefuse.evaluation.confidence import (
        CONFIDENCE_LEGEND,
        confidence_markdown,
        confidence_rows,
    )

    kept = confidence_rows(dataset, run.results, run.targets)
    report.confidence = f"{CONFIDENCE_LEGEND}\n\n{confidence_markdown(kept)}"
    (out / "confidence.md").write_text(f"{report.confidence}\n")
    rows = [r for n in CHECKPOINTS for r in run.ambiguity.get(n, [])]
    write_ambiguity(out / "ambiguity.csv", rows)
    (out / "ambiguity.md").write_text(
        f"{AMBIGUITY_LEGEND}\n\n{ambiguity_markdown(rows, dataset.catalog)}\n"
    )
    return report


def _switch(value: str) -> bool:
    """A bool setting's value: 1 / true / on or 0 / false / off."""
    word = value.strip().lower()
    if word in ("1", "true", "on"):
        return True
    if word in ("0", "false", "off"):
        return False
    raise ValueError(value)


def _numeric_fields(cls) -> dict[str, object]:
    """The int, float and bool fields of a dataclass, each with its parser (the annotations
    are strings); ``enabled`` is left out: the ablation flags switch it."""
    parsers = {"int": int, "float": float, "float | None": float, "bool": _switch}
    return {
        f.name: parsers[f.type]
        for f in dataclasses.fields(cls)
        if f.type in parsers and f.name != "enabled"
    }


def verification_settings(pairs: list[str] | None) -> dict[str, float | None]:
    """``KEY=VALUE`` strings of ``--verification`` as numeric VerificationConfig fields,
    ``edges.KEY`` for the EdgeConfig it holds, ``turns.KEY`` for its TurnJudgeConfig (with
    ``turns.enabled``), or ``refinement.KEY`` for the RefineConfig (an
    optional one, such as ``settled_margin``, also takes ``none``); a PosefuseError names a
    malformed pair or an unknown field."""
    # lazy: the verification modules load scipy, trimesh and cv2 (~0.5 s)
    from posefuse.estimator.verification.edge_maps import EdgeConfig
    from posefuse.estimator.verification.refinement import RefineConfig
    from posefuse.estimator.verification.turns import TurnJudgeConfig
    from posefuse.estimator.verification.verify import VerificationConfig

    optional = {
        f.name for f in dataclasses.fields(VerificationConfig) if f.type == "float | None"
    } | {
        f"refinement.{f.name}" for f in dataclasses.fields(RefineConfig) if f.type == "float | None"
    }  # "none" switches it off
    numeric = _numeric_fields(VerificationConfig)
    numeric.update({f"edges.{k}": t for k, t in _numeric_fields(EdgeConfig).items()})
    numeric.update({f"refinement.{k}": t for k, t in _numeric_fields(RefineConfig).items()})
    numeric.update({f"turns.{k}": t for k, t in _numeric_fields(TurnJudgeConfig).items()})
    numeric["turns.enabled"] = _switch  # the judge has no ablation flag of its own
    numeric["translation_shared_frac"] = float  # the tracker's, given by a card as these are
    out: dict[str, float | None] = {}
    for pair in pairs or ():
        key, sep, value = pair.partition("=")
        if not sep or key not in numeric:
            raise PosefuseError(
                f"--verification {pair!r}: expected KEY=VALUE with KEY one of {sorted(numeric)}"
            )
        if key in optional and value.strip().lower() == "none":
            out[key] = None
            continue
        try:
            out[key] = numeric[key](value)
        except ValueError:
            kind = "0 or 1" if numeric[key] is _switch else "a number"
            raise PosefuseError(f"--verification {pair!r}: {value!r} is not {kind}") from None
    return out


def card_settings(card_verification: dict | None, given: dict) -> dict:
    """The verification settings a model's card gives for its masks (``ModelCard.verification``)
    that ``--verification`` (``given``) does not replace."""
    return {k: v for k, v in (card_verification or {}).items() if k not in given}


def tracker_config(
    no_verify: bool = False, no_refine: bool = False, verification: dict | None = None
):
    """The estimator's settings, with the multi-view verification or the refinement off, and
    verification settings replaced (:func:`verification_settings`)."""
    from posefuse.estimator.tracker import TrackerConfig  # lazy: scipy, trimesh, cv2 (~0.6 s)

    config = TrackerConfig()
    if verification:
        try:
            config = config.with_verification_settings(verification)
        except ValueError as err:
            raise PosefuseError(f"--verification: {err}") from None
    if no_verify:
        config = dataclasses.replace(
            config, verification=dataclasses.replace(config.verification, enabled=False)
        )
    if no_verify or no_refine:
        config = dataclasses.replace(
            config, refinement=dataclasses.replace(config.refinement, enabled=False)
        )
    return config


def _cmd_run_dataset(args: argparse.Namespace) -> int:
    from posefuse.evaluation.dataset import load_dataset  # lazy: scipy, trimesh, cv2 (~0.5 s)

    if args.frontend not in ("oracle", "network"):
        raise PosefuseError(f"--frontend: {args.frontend!r} is not known; use oracle or network")
    if args.track_crops and args.frontend != "network":
        raise PosefuseError("--track-crops: only with --frontend network (stage two looks there)")
    if args.parts is not None:
        from posefuse.sim.onboard import load_part_set  # lazy: loads trimesh and scipy (~0.5 s)

        if args.model is not None:
            raise PosefuseError("--parts names the model: drop --model")
        args.model = str(load_part_set(args.parts).model)
    args.model = args.model or DEFAULT_MODEL
    dataset = load_dataset(args.dataset, split=args.split)
    rotation = not args.translation_only
    try:
        oracle = OracleConfig(
            center_sigma_px=args.center_sigma,
            drop_rate=args.drop_rate,
            false_positive_rate=args.false_positive_rate,
            with_masks=rotation,
            masks=args.oracle_masks,
            seed=args.seed,
        )
    except ValueError as exc:
        raise PosefuseError(f"oracle settings: {exc}") from None
    scene_ids = tuple(args.scenes) if args.scenes else None
    for scene_id in scene_ids or ():
        dataset.scene(scene_id)  # a DatasetError naming the missing scene
    frontend = make_frontend(dataset, args.frontend, oracle, args.model, args.seed)
    if not rotation and args.frontend == "network" and len(dataset.catalog) > 1:
        if frontend.network.card.agnostic:
            raise PosefuseError(
                f'--translation-only: {args.model} finds "a part" and the estimator names '
                "each from its images, which a translation-only run does not pass it; drop "
                "--translation-only"
            )
    verification = verification_settings(args.verification)
    config = tracker_config(args.no_verify, args.no_refine, verification)
    if args.frontend == "network":
        config = config.with_card(card_settings(frontend.network.card.verification, verification))
    region = dataset.bin if args.bin == "dataset" else None
    config = dataclasses.replace(config, bin=region)
    if not args.quiet:
        print(f"bin: {'from the dataset' if region is not None else 'not used'}")
    out = Path(args.out)
    report = run_and_write(
        dataset,
        frontend,
        out,
        args.frontend,
        scene_ids,
        rotation=rotation,
        quiet=args.quiet,
        config=config,
        track_crops=args.track_crops,
    )
    print(report.summary)
    print(f"wrote {out / 'translation_errors.csv'} and {out / 'translation_summary.md'}")
    if rotation:
        print(f"\n{DETECTION_LEGEND}")
        print(report.table)
        print(f"\n{report.fates_legend}")
        print(report.fates)
        print(f"\n{report.confidence}")
        print(
            "wrote results_*views.csv, targets_*views.json, detection_rate.md, "
            f"detection_rate.json, fates.csv, fates.md and confidence.md to {out}"
        )
    return 0


def _cmd_templates(args: argparse.Namespace) -> int:
    # lazy: the catalog and templates load trimesh, scipy and cv2 (~0.6 s)
    from posefuse.estimator.core.objects import load_catalog
    from posefuse.estimator.rotation.templates import build_template_bank

    catalog = load_catalog(args.catalog)
    rows = [
        "| obj_id | name | templates | size (KiB) | build (s) |",
        "|---|---|---|---|---|",
    ]
    for obj_id, model in catalog.items():
        bank = build_template_bank(model, cache_dir=args.cache, show_progress=not args.quiet)
        rows.append(
            f"| {obj_id} | {model.name} | {len(bank)} | {bank.nbytes / 1024:.0f} | "
            f"{bank.build_seconds:.1f} |"
        )
    print("\n".join(rows))
    return 0


def _cmd_eval_frontend(args: argparse.Namespace) -> int:
    # lazy: cv2, and the dataset and scoring load scipy and trimesh (~0.5 s)
    from posefuse.estimator.frontend.network import NetworkFrontend
    from posefuse.evaluation.dataset import load_dataset
    from posefuse.evaluation.frontend_metrics import score_frontend

    dataset = load_dataset(args.dataset, split=args.split)
    frontend = NetworkFrontend(args.model, dataset.catalog, threads=args.threads)
    views = [v for v in dataset.views()][: args.max_views or None]

    def detect(view):
        image = dataset.scene(view.scene_id).load_rgb(view.im_id)
        return frontend.detect(image)

    agnostic = frontend.card.agnostic  # a generalist's "a part" matches a part of any class
    score = score_frontend(dataset, detect, views, min_visib=args.min_visib, any_class=agnostic)
    kind = " (a generalist: classes not scored)" if agnostic else ""
    print(f"Front end {args.model}{kind} on {args.dataset} (profile {dataset.profile}):\n")
    print(score.to_markdown())
    return 0


def _cmd_frontend_overlay(args: argparse.Namespace) -> int:
    # lazy: cv2 (~30 ms), and the dataset loads scipy and trimesh (~0.5 s)
    import cv2

    from posefuse.estimator.frontend.network import NetworkFrontend
    from posefuse.evaluation.dataset import load_dataset
    from posefuse.sim.overlay import frontend_overlay

    dataset = load_dataset(args.dataset, split=args.split)
    frontend = NetworkFrontend(args.model, dataset.catalog)
    scene = dataset.scene(args.scene)
    view = scene.view(args.im)
    image = scene.load_rgb(args.im)
    raw = frontend.infer(image)
    dets = frontend.detect(image)
    truth = [view.camera.project(g.T_cam_obj[:3, 3]) for g in view.gts if g.visib_fract > 0.1]
    picture = frontend_overlay(image, raw, dets, frontend.card, np.array(truth).reshape(-1, 2))
    if args.crop:
        x, y, w, h = args.crop
        picture = picture[y : y + h, x : x + w]
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(args.out, picture)
    print(f"wrote {args.out}: {len(dets)} detections")
    return 0


def register(subparsers) -> None:
    p = add_command(
        subparsers,
        "run-dataset",
        "run the estimator over a BOP dataset, views one at a time, and score it",
    )
    p.add_argument("--dataset", required=True, help="BOP dataset folder")
    p.add_argument("--split", default="test", help="BOP split folder of the dataset")
    p.add_argument("--out", required=True, help="folder for the error tables")
    p.add_argument(
        "--frontend",
        default="oracle",
        help="oracle (noisy detections from the ground truth) or network (the learned model)",
    )
    p.add_argument(
        "--model",
        help="ONNX model for --frontend network (default: the part set's with --parts, else "
        "the shipped models/robi_like.onnx)",
    )
    add_parts_arg(p)
    p.add_argument(
        "--scenes",
        type=int,
        nargs="+",
        metavar="ID",
        help="only these scene ids (default: every scene)",
    )
    p.add_argument(
        "--center-sigma",
        type=float,
        default=ORACLE_CENTER_SIGMA,
        help="oracle center noise, px",
    )
    p.add_argument(
        "--drop-rate",
        type=float,
        default=ORACLE_DROP_RATE,
        help="oracle: share of the instances missed",
    )
    p.add_argument(
        "--false-positive-rate",
        type=float,
        default=ORACLE_FALSE_POSITIVE_RATE,
        help="oracle: false detections per true one",
    )
    p.add_argument(
        "--oracle-masks",
        choices=("silhouette", "box"),
        default="silhouette",
        help="oracle: the true silhouettes as masks, or the filled visible boxes (the rotation "
        "step then reads the part's outline from the image's own edges)",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the front end's noise")
    p.add_argument("--translation-only", action="store_true", help="skip the rotation step")
    p.add_argument(
        "--no-verify",
        action="store_true",
        help="without the multi-view verification and refinement (the ablation)",
    )
    p.add_argument(
        "--track-crops",
        action="store_true",
        help="with --frontend network: stage two also where the tracks expect parts that stage "
        "one missed",
    )
    p.add_argument(
        "--no-refine",
        action="store_true",
        help="verify across views, but do not refine",
    )
    p.add_argument(
        "--verification",
        action="append",
        metavar="KEY=VALUE",
        help="replace a verification setting, e.g. mask_weight=2.0, settled_margin=none to "
        "verify at every new view, edges.KEY=V, turns.KEY=V (turns.enabled=0: the near-symmetric "
        "turns not judged) or refinement.KEY=V (repeatable; for tuning)",
    )
    p.add_argument(
        "--bin",
        choices=("dataset", "none"),
        default="dataset",
        help="the bin the parts lie in, as a cell that knows it gives it to the estimator: the "
        "one the dataset records (synth.json; none recorded: not used), or none",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_run_dataset)

    p = add_command(
        subparsers,
        "templates",
        "build (or load from the cache) the LINE-2D templates of a catalog",
    )
    p.add_argument("--catalog", default=DEFAULT_CATALOG, help="BOP catalog folder")
    p.add_argument(
        "--cache",
        metavar="DIR",
        help="cache folder (default: $POSEFUSE_CACHE, else ~/.cache/posefuse)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_templates)

    p = add_command(subparsers, "eval-frontend", "recall, precision and center accuracy of a model")
    p.add_argument("--dataset", required=True, help="BOP dataset folder")
    p.add_argument("--split", default="test", help="BOP split folder of the dataset")
    p.add_argument("--model", default=DEFAULT_MODEL, help="ONNX model of the front end")
    p.add_argument("--threads", type=int, default=2, help="onnxruntime threads")
    p.add_argument(
        "--min-visib",
        type=float,
        default=0.75,
        help="score only instances with a larger visible fraction",
    )
    p.add_argument("--max-views", type=int, default=0, help="score only the first N views (0: all)")
    p.set_defaults(func=_cmd_eval_frontend)

    p = add_command(subparsers, "frontend-overlay", "draw the learned front end's output on a view")
    p.add_argument("--dataset", required=True, help="BOP dataset folder")
    p.add_argument("--split", default="test", help="BOP split folder of the dataset")
    p.add_argument("--model", default=DEFAULT_MODEL, help="ONNX model of the front end")
    p.add_argument("--scene", type=int, default=0, help="scene id")
    p.add_argument("--im", type=int, default=0, help="image id in the scene")
    p.add_argument(
        "--crop",
        type=int,
        nargs=4,
        metavar=("X", "Y", "W", "H"),
        help="keep only this rectangle of the picture, px (default: the whole view)",
    )
    p.add_argument("--out", required=True, help="image file to write (PNG)")
    p.set_defaults(func=_cmd_frontend_overlay)
