"""The paper's Tables I and II on our synthetic bin scenes, from one command.

    posefuse bench --dataset DIR [--quick] [--out docs/benchmarks.md]

When DIR holds no dataset, it is rendered first (full: 50 scenes x 8 views at 1280x720,
seed 300; quick: 2 scenes x 8 views at 640x360, seed 301). Every method sees the same
detections (the oracle front end: the true centers with 2 px of noise and the visible masks,
seed 0) and scores the same LINE-2D features:

- ours: the two-step estimator (translation, then rotation from the scale-aware re-crop, then
  the rotation hypotheses verified in every view of the track, the winner refined over them);
- ours without verification and refinement: the ablation, each view's LINE-2D match judged
  alone;
- simultaneous: our translation, rotation from templates at 9 distances without re-crop;
- CosyPose-RGB and CosyPose-RGBD: per-view 6D poses fused across views (bench/baselines.py).

Scores (evaluation.scores): ADD-sym < 0.1 d (the headline), MSSD < 0.1 d, AR_MSSD and
precision, with the lenient ADI beside them, for the instances more than 75% visible in the 4th
and the 8th view of each scene, with the estimates made from the views up to it.
"""

from __future__ import annotations

import json
import shlex
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from posefuse.bench.baselines import (
    MATCH_THRESHOLD_RGB,
    MATCH_THRESHOLD_RGBD,
    Candidate,
    ClassGeometry,
    DepthAligner,
    MultiScaleMatcher,
    TimedMatcher,
    fuse_candidates,
    rgb_candidate,
    rgbd_candidate,
)
from posefuse.bench.machine import describe_machine
from posefuse.cli.run import tracker_config
from posefuse.estimator.core.errors import PosefuseError
from posefuse.estimator.rotation.matching import RotationMatcher
from posefuse.estimator.tracker import MultiViewEstimator
from posefuse.evaluation.oracle import OracleConfig, OracleFrontend
from posefuse.evaluation.run_dataset import run_dataset
from posefuse.evaluation.scores import PoseResult, evaluate

CHECKPOINTS = (4, 8)
FULL = {"scenes": 50, "views": 8, "seed": 300, "width": 1280, "height": 720}
# Scenes on which parameters may be tuned: seeds disjoint from every reported set (benchmarks 300
# and 301, /tmp/ds_big 200, real meshes 300, translation pages 100 and 1000-1029, the demo 900,
# the network's training scenes scene_seed(7000000, .)).
TUNING_SEED = 4242
FRONTEND_TEXT = {
    "oracle": "the oracle front end (true centers + 2 px Gaussian noise, visible masks, seed 0; "
    "an upper bound, not what a user gets)",
    "network": "the learned front end (`models/robi_like.onnx` and voting, what a user gets), "
    "as the paper's methods all used one localization network",
}
QUICK = {"scenes": 2, "views": 8, "seed": 301, "width": 640, "height": 360}
ORACLE = OracleConfig(center_sigma_px=2.0, seed=0)
METHODS = ("cosypose_rgb", "cosypose_rgbd", "ours_no_verification", "ours", "simultaneous")
LABELS = {
    "cosypose_rgb": "CosyPose-style RGB",
    "cosypose_rgbd": "CosyPose-style RGBD",
    "ours_no_verification": "ours without verification and refinement (ablation)",
    "ours": "ours (two-step)",
    "simultaneous": "simultaneous (multi-scale)",
}


@dataclass
class MethodRun:
    """results / targets per checkpoint; matching_s: seconds of each template-matching call
    per obj_id; seconds: wall time of the whole method."""

    results: dict[int, list[PoseResult]] = field(default_factory=dict)
    targets: dict[int, list[tuple[int, int]]] = field(default_factory=dict)
    matching_s: dict[int, list[float]] = field(default_factory=dict)
    seconds: float = 0.0


def ensure_dataset(root: Path, quick: bool, catalog_dir: str, profile: str = "mixed"):
    """The BOP dataset at root, rendered first (in the scene ``profile``) when root holds
    none."""
    import dataclasses

    from posefuse.estimator.core.objects import load_catalog
    from posefuse.evaluation.dataset import load_dataset
    from posefuse.sim.scenes import PROFILES, REALSENSE_1280x720
    from posefuse.sim.synth import SynthConfig, generate_dataset

    if not (root / "test").is_dir():
        spec = QUICK if quick else FULL
        config = SynthConfig(
            n_scenes=spec["scenes"],
            seed=spec["seed"],
            camera=REALSENSE_1280x720.resized(spec["width"], spec["height"]),
            scene=dataclasses.replace(PROFILES[profile], n_views=spec["views"]),
            profile=profile,
        )
        generate_dataset(load_catalog(catalog_dir), root, config)
    return load_dataset(root)


def make_frontend(dataset, kind: str, model: str | None = None):
    """The detections every method sees: ``oracle`` (true centers + 2 px noise, true visible
    masks) or ``network`` (the learned front end, as a user gets it), labelled with the
    instance each lies on for scoring only."""
    if kind == "oracle":
        return OracleFrontend(dataset, ORACLE)
    if kind == "network":
        from posefuse.estimator.frontend.network import NetworkFrontend
        from posefuse.evaluation.run_dataset import LabelledNetworkFrontend
        from posefuse.service.resources import DEFAULT_MODEL

        return LabelledNetworkFrontend(
            dataset, NetworkFrontend(model or DEFAULT_MODEL, dataset.catalog)
        )
    raise ValueError(f"front end: expected 'oracle' or 'network', got {kind!r}")


def _run_tracker(
    dataset, banks, simultaneous: bool, progress: bool, frontend, config=None
) -> MethodRun:
    run = MethodRun(matching_s={k: [] for k in dataset.catalog})
    start = time.perf_counter()

    def factory():
        matchers = {}
        for k, bank in banks.items():
            inner = RotationMatcher(bank)
            if simultaneous:
                inner = MultiScaleMatcher(inner)
            matchers[k] = TimedMatcher(inner, run.matching_s[k])
        return MultiViewEstimator(dataset.catalog, config, banks=banks, matchers=matchers)

    out = run_dataset(
        dataset,
        frontend,
        checkpoints=CHECKPOINTS,
        show_progress=progress,
        rotation=True,
        estimator_factory=factory,
    )
    run.results, run.targets = out.results, out.targets
    run.seconds = time.perf_counter() - start
    return run


def _run_cosypose(dataset, banks, use_depth: bool, progress: bool, frontend) -> MethodRun:
    run = MethodRun(matching_s={k: [] for k in dataset.catalog})
    run.results = {n: [] for n in CHECKPOINTS}
    run.targets = {n: [] for n in CHECKPOINTS}
    start = time.perf_counter()
    matchers = {k: RotationMatcher(b) for k, b in banks.items()}
    multi = {k: MultiScaleMatcher(m) for k, m in matchers.items()}
    aligners = {k: DepthAligner(dataset.catalog[k]) for k in banks}
    geometries = {k: ClassGeometry(dataset.catalog[k]) for k in banks}
    n_views = sum(len(dataset.scene(s).im_ids) for s in dataset.scene_ids)
    label = "cosypose-rgbd" if use_depth else "cosypose-rgb"
    bar = tqdm(total=n_views, desc=label, unit="view", disable=not progress)
    for scene_id in dataset.scene_ids:
        scene = dataset.scene(scene_id)
        candidates: list[Candidate] = []
        for count, im_id in enumerate(scene.im_ids, start=1):
            view = scene.view(im_id)
            image = scene.load_rgb(im_id)
            depth = scene.load_depth(im_id) if use_depth else None
            for det, _ in frontend.detect_with_truth(view):
                t0 = time.perf_counter()
                if use_depth:
                    T, score = rgbd_candidate(
                        matchers[det.obj_id],
                        aligners[det.obj_id],
                        image,
                        depth,
                        view.camera,
                        det,
                        multi[det.obj_id],
                    )
                else:
                    T, score = rgb_candidate(multi[det.obj_id], image, view.camera, det)
                run.matching_s[det.obj_id].append(time.perf_counter() - t0)
                if score > 0:
                    candidates.append(
                        Candidate(count, det.obj_id, score, T, view.T_world_cam, view.camera.K)
                    )
            bar.update(1)
            if count not in CHECKPOINTS:
                continue
            run.targets[count].append((scene_id, im_id))
            threshold = MATCH_THRESHOLD_RGBD if use_depth else MATCH_THRESHOLD_RGB
            for obj in fuse_candidates(candidates, geometries, threshold):
                T_cam_obj = view.T_cam_world @ obj.T_world_obj
                run.results[count].append(
                    PoseResult(scene_id, im_id, obj.obj_id, obj.score, T_cam_obj)
                )
    bar.close()
    run.seconds = time.perf_counter() - start
    return run


def run_all(dataset, banks, progress: bool = True, frontend=None) -> dict[str, MethodRun]:
    """Every method on the same detections (default: the oracle front end)."""
    frontend = frontend or make_frontend(dataset, "oracle")
    return {
        "cosypose_rgb": _run_cosypose(dataset, banks, False, progress, frontend),
        "cosypose_rgbd": _run_cosypose(dataset, banks, True, progress, frontend),
        "ours_no_verification": _run_tracker(
            dataset, banks, False, progress, frontend, tracker_config(no_verify=True)
        ),
        "ours": _run_tracker(dataset, banks, False, progress, frontend),
        "simultaneous": _run_tracker(dataset, banks, True, progress, frontend),
    }


def score_runs(dataset, runs: dict[str, MethodRun]) -> dict:
    """{method: {"rates": {n: {str(obj_id) | "all": ADD-sym rate}}, "reports": {n: the
    EvaluationReport's JSON (every metric, precision)}, "ms": {str(obj_id) | "all": ms}}}
    (rates are fractions; ms is the median of one template-matching call)."""
    out = {}
    for name, run in runs.items():
        rates, reports = {}, {}
        for n in CHECKPOINTS:
            report = evaluate(dataset, run.results[n], targets=run.targets[n])
            reports[n] = report.to_json()
            rates[n] = {str(k): o.rate() for k, o in report.objects.items()}
            rates[n]["all"] = report.rate
            rates[n]["instances"] = report.n_instances
        ms = {
            str(k): float(np.median(v)) * 1000 if v else float("nan")
            for k, v in run.matching_s.items()
        }
        every = [t for v in run.matching_s.values() for t in v]
        ms["all"] = float(np.median(every)) * 1000 if every else float("nan")
        closest = {n: closest_errors(dataset, run, n) for n in CHECKPOINTS}
        out[name] = {
            "rates": rates,
            "reports": reports,
            "ms": ms,
            "calls": len(every),
            "seconds": run.seconds,
            "closest": closest,
        }
    return out


def closest_errors(dataset, run: MethodRun, n: int) -> dict[str, int]:
    """Each scored instance by the ADD-sym of the closest estimate of its class in its view:
    below 0.1 d, 0.1-0.5 d (estimated, inaccurate), none within 0.5 d (not estimated)."""
    from posefuse.evaluation.scores import pose_error

    by_view: dict[tuple[int, int, int], list[PoseResult]] = {}
    for r in run.results[n]:
        by_view.setdefault((r.scene_id, r.im_id, r.obj_id), []).append(r)
    counts = {"within_0.1d": 0, "0.1d_to_0.5d": 0, "none_within_0.5d": 0}
    for scene_id, im_id in run.targets[n]:
        view = dataset.scene(scene_id).view(im_id)
        for gt in view.gts:
            if gt.visib_fract <= 0.75:
                continue
            model = dataset.catalog[gt.obj_id]
            errors = [
                pose_error(model, r.T_cam_obj, gt.T_cam_obj, "add_sym")
                for r in by_view.get((scene_id, im_id, gt.obj_id), [])
            ]
            best = min(errors, default=np.inf) / model.diameter
            key = (
                "within_0.1d"
                if best < 0.1
                else "0.1d_to_0.5d"
                if best < 0.5
                else "none_within_0.5d"
            )
            counts[key] += 1
    return counts


def _pct(x: float) -> str:
    return "-" if x is None or np.isnan(x) else f"{100 * x:.1f}"


def _ms(x: float) -> str:
    return "-" if np.isnan(x) else f"{x:.2f}"


def _verdict(ours: float, rgb: float, rgbd: float) -> str:
    if any(np.isnan(x) for x in (ours, rgb, rgbd)):
        return "no instance"
    parts = []
    parts.append("beats RGB" if ours > rgb else ("ties RGB" if ours == rgb else "**loses to RGB**"))
    if ours >= rgbd:
        parts.append("beats RGBD" if ours > rgbd else "ties RGBD")
    else:
        parts.append(f"**below RGBD by {100 * (rgbd - ours):.1f}**")
    return ", ".join(parts)


def summary_table(scores: dict, methods: tuple[str, ...]) -> list[str]:
    """Every metric of every method, all objects pooled, at 4 and 8 views."""
    lines = [
        "| method | views | ADD-sym-0.1d | MSSD-0.1d | AR_MSSD | precision | estimates "
        "| ADI-0.1d (lenient) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for m in methods:
        for n in CHECKPOINTS:
            a = scores[m]["reports"][n]["all"]
            lines.append(
                f"| {LABELS[m]} | {n} | **{_pct(a['add_sym'])}** | {_pct(a['mssd'])} | "
                f"{_pct(a['ar_mssd'])} | {_pct(a['precision'])} | {a['estimates']} | "
                f"{_pct(a['adi'])} |"
            )
    return lines


def _compare(ours: float, other: float, name: str) -> str:
    d = 100 * (ours - other)
    if abs(d) < 0.05:
        return f"ties {name}"
    return f"{'leads' if d > 0 else 'trails'} {name} by {abs(d):.1f} points"


def table_sentences(scores: dict, table: str) -> list[str]:
    """Where ours wins and loses, read off the numbers of this run."""
    others = (
        ("cosypose_rgb", "cosypose_rgbd", "ours_no_verification")
        if table == "I"
        else ("simultaneous",)
    )
    out = []
    for n in CHECKPOINTS:
        ours = scores["ours"]["reports"][n]["all"]
        parts = []
        for key, label in (("add_sym", "ADD-sym"), ("mssd", "MSSD"), ("ar_mssd", "AR_MSSD")):
            cmp = ", ".join(
                _compare(ours[key], scores[o]["reports"][n]["all"][key], LABELS[o]) for o in others
            )
            parts.append(f"by {label} ours {cmp}")
        prec = ", ".join(
            _compare(ours["precision"], scores[o]["reports"][n]["all"]["precision"], LABELS[o])
            for o in others
        )
        parts.append(f"in precision ours {prec}")
        out.append(f"- At {n} views: " + "; ".join(parts) + ".")
    return out


def markdown(dataset, scores: dict, meta: dict) -> str:
    catalog = dataset.catalog
    rows = [(str(k), catalog[k].name) for k in catalog] + [("all", "all")]
    lines = [
        "# Benchmarks: the paper's Tables I and II on synthetic bin scenes",
        "",
        f"Made by `{meta['command']}` in {meta['minutes']:.1f} min on {meta['machine']}.",
        f"Dataset `{meta['dataset']}` (profile {meta.get('profile', 'unknown')}): "
        f"{meta['scenes']} scenes x {meta['views']} views "
        f"({meta['resolution']}), rendered by this command with seed {meta['dataset_seed']} "
        f"when absent. Detections: {FRONTEND_TEXT[meta.get('frontend', 'oracle')]}, the same "
        "for every method. Every number on this page comes from that run; the raw numbers are "
        "in the `.json` file beside it.",
        "",
        "Scores, in % of the instances more than 75% visible in the 4th / 8th view of each "
        "scene, estimated from the views up to it: **ADD-sym < 0.1 d** (the headline: ADD, the "
        "paper's metric, against the symmetric equivalent of the truth closest to the estimate), "
        "MSSD < 0.1 d, AR_MSSD (BOP's mean recall over MSSD thresholds 0.05-0.5 d), precision "
        "(found instances per estimate; estimates of barely visible parts left out) and ADI "
        "< 0.1 d, which is lenient (a random rotation with the true center passes it for 15-64% "
        "of the instances, depending on the part, on the 12 scenes of docs/performance.md) "
        "and shown only to compare with earlier pages. Errors equal "
        "bop_toolkit's on each part's evaluation points; matching as BOP's.",
        "",
        "Until the metric changed, this page's headline was ADD(-S), which is ADI for every "
        "one of our parts (all five are symmetric): the ADI column is that figure, now taken "
        "from the true points as bop_toolkit does. Claims made with it do not all hold under "
        "ADD-sym and MSSD: the sentences under each table say where ours wins and loses now.",
        "",
        "## Table I: multi-view fusion of per-view poses versus ours",
        "",
        *summary_table(scores, ("cosypose_rgb", "cosypose_rgbd", "ours_no_verification", "ours")),
        "",
        *table_sentences(scores, "I"),
        "",
        "ADD-sym < 0.1 d per object:",
        "",
        "| object | CosyPose-RGB 4 | CosyPose-RGB 8 | CosyPose-RGBD 4 | CosyPose-RGBD 8 "
        "| ours 4 | ours 8 | ours at 8 views |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for key, name in rows:
        r = {m: scores[m]["rates"] for m in METHODS}
        cells = []
        for m in ("cosypose_rgb", "cosypose_rgbd", "ours"):
            cells += [_pct(r[m][4][key]), _pct(r[m][8][key])]
        verdict = _verdict(r["ours"][8][key], r["cosypose_rgb"][8][key], r["cosypose_rgbd"][8][key])
        label = f"**{name}**" if key == "all" else name
        lines.append(f"| {label} | " + " | ".join(cells) + f" | {verdict} |")
    n4 = scores["ours"]["rates"][4]["instances"]
    n8 = scores["ours"]["rates"][8]["instances"]
    lines += [
        "",
        f"Instances scored: {n4} at 4 views, {n8} at 8 views.",
        "",
        "## Table II: simultaneous (multi-scale templates) versus two-step",
        "",
        *summary_table(scores, ("simultaneous", "ours")),
        "",
        *table_sentences(scores, "II"),
        "",
        "ADD-sym < 0.1 d per object, and the time of one rotation measurement:",
        "",
        "| object | simultaneous 4 | simultaneous 8 | two-step 4 | two-step 8 "
        "| simultaneous ms | two-step ms | ratio |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for key, name in rows:
        s, t = scores["simultaneous"], scores["ours"]
        ratio = s["ms"][key] / t["ms"][key] if t["ms"][key] > 0 else float("nan")
        ratio_text = "-" if np.isnan(ratio) else f"{ratio:.1f}x"
        label = f"**{name}**" if key == "all" else name
        lines.append(
            f"| {label} | {_pct(s['rates'][4][key])} | {_pct(s['rates'][8][key])} | "
            f"{_pct(t['rates'][4][key])} | {_pct(t['rates'][8][key])} | "
            f"{_ms(s['ms'][key])} | {_ms(t['ms'][key])} | {ratio_text} |"
        )
    lines += [
        "",
        "Template matching: median milliseconds of one rotation measurement of one object in "
        "one view (re-crop or multi-scale RoI, LINE-2D responses, scoring), "
        f"{scores['ours']['calls']} and {scores['simultaneous']['calls']} measurements.",
        "",
        "## Time per method",
        "",
        "| method | wall time s | template-matching calls | median ms per call |",
        "|---|---|---|---|",
    ]
    for m in METHODS:
        lines.append(
            f"| {LABELS[m]} | {scores[m]['seconds']:.0f} | {scores[m]['calls']} | "
            f"{_ms(scores[m]['ms']['all'])} |"
        )
    lines += [
        "",
        "## Where the misses come from",
        "",
        "Each scored instance by the ADD-sym error of the closest estimate of its class in its "
        "view: an accurate estimate (< 0.1 d), an inaccurate one (0.1-0.5 d), or none within "
        "0.5 d (the part was not estimated, or not fused into one object).",
        "",
        "| method | views | < 0.1 d | 0.1-0.5 d | none within 0.5 d |",
        "|---|---|---|---|---|",
    ]
    for m in METHODS:
        for n in CHECKPOINTS:
            k = scores[m]["closest"][n]
            lines.append(
                f"| {LABELS[m]} | {n} | {k['within_0.1d']} | {k['0.1d_to_0.5d']} | "
                f"{k['none_within_0.5d']} |"
            )
    lines += [
        "",
        "## How the baselines are set up",
        "",
        "- All methods use the same LINE-2D features (162 viewpoints x 36 in-plane rotations, "
        "63 features, the fundamental region of each part's symmetries) and the same masks.",
        "- Templates at 9 distances (0.45-0.95 m, geometric spacing) are the canonical bank's "
        "features scaled about the center, as rendering at another distance gives under weak "
        "perspective.",
        "- CosyPose-style fusion with the cameras known: candidates of a class in different "
        "views are matched by symmetric pose distance (threshold "
        f"{MATCH_THRESHOLD_RGB:g} x diameter for RGB, {MATCH_THRESHOLD_RGBD:g} x diameter for "
        "RGBD: for each, the best of 0.1, 0.2, 0.4, 0.8, 1.2, 1.6, 2.4 tried on the first 20 "
        "scenes of the full dataset, i.e. tuned in the baseline's favour), one candidate per "
        "view joins the highest-scoring seed, and objects seen in two views or more are "
        "refined by minimising the symmetric reprojection error of 50 model points over their "
        "views.",
        "- RGBD: the median sensor depth in the mask (the sensor has holes on shiny metal) "
        "places the part, the rotation is matched at that scale, and the part is moved along "
        "its ray until its rendered depth fits the measured one (twice).",
        "- Ours and the simultaneous ablation share the tracker; they differ only in the "
        "rotation measurement. Ours measures rotations once the translation's depth is known "
        "to 5%, so at 4 views some parts have fewer rotation measurements than the per-view "
        "baselines, which have a 6D pose from the first view.",
        "",
        "## Tuning and held-out scenes",
        "",
        "- Two choices were made on this page's own test scenes (seed 300), so the numbers above "
        "are optimistic for them: three rotation hypotheses per view for ours and the "
        "simultaneous ablation (`RotationConfig.top_k = 3`, picked from 1, 2, 3 by this "
        "benchmark's earlier ADD(-S) figures), and the CosyPose baselines' matching thresholds "
        "(picked in their favour on the first 20 scenes).",
        "- From now on parameters are tuned only on scenes rendered with "
        f"`posefuse synth --seed {TUNING_SEED}`, a seed disjoint from every reported set "
        "(300 and 301 here, 200 for docs/performance.md and docs/frontend.md, 100 and "
        "1000-1029 for the translation pages, 900 for the demo, and the network's training "
        "scenes `scene_seed(7000000, 0..299)`).",
        "",
        *meta.get("notes", []),
    ]
    return "\n".join(lines).rstrip() + "\n"


def dataset_seed(root: Path, default: int) -> int:
    """The seed the dataset was rendered with (its synth.json), else the spec's."""
    try:
        return int(json.loads((root / "synth.json").read_text())["seed"])
    except (OSError, KeyError, ValueError, TypeError):
        return default


def main(args) -> int:
    from posefuse.estimator.rotation.templates import build_template_bank

    start = time.perf_counter()
    root = Path(args.dataset)
    dataset = ensure_dataset(root, args.quick, args.catalog, args.profile)
    frontend = make_frontend(dataset, args.frontend, args.model)
    first = dataset.scene(dataset.scene_ids[0])
    camera = first.view(first.im_ids[0]).camera
    if args.frontend == "network":
        w, h = frontend.network.card.image_size
        if (camera.width, camera.height) != (w, h):
            raise PosefuseError(
                f"--frontend network: the model expects {w}x{h} images, {root} has "
                f"{camera.width}x{camera.height} (--quick renders small ones)"
            )
    banks = {k: build_template_bank(m, show_progress=True) for k, m in dataset.catalog.items()}
    runs = run_all(dataset, banks, progress=True, frontend=frontend)
    scores = score_runs(dataset, runs)
    spec = QUICK if args.quick else FULL
    meta = {
        "command": "posefuse bench " + " ".join(shlex.quote(a) for a in args.argv),
        "minutes": (time.perf_counter() - start) / 60,
        "machine": describe_machine(),
        "dataset": str(root),
        "scenes": len(dataset.scene_ids),
        "views": len(first.im_ids),
        "resolution": f"{camera.width}x{camera.height}",
        "dataset_seed": dataset_seed(root, spec["seed"]),
        "profile": dataset.profile,
        "frontend": args.frontend,
    }
    text = markdown(dataset, scores, meta)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if out.exists():  # the next-best-view section of python -m posefuse.bench.active stays
        from posefuse.bench.active import MARK_BEGIN

        previous = out.read_text()
        if MARK_BEGIN in previous:
            text = text.rstrip("\n") + "\n\n" + MARK_BEGIN + previous.split(MARK_BEGIN, 1)[1]
    out.write_text(text)
    doc = {"meta": meta, "scores": scores}
    out.with_suffix(".json").write_text(
        json.dumps(doc, indent=1, sort_keys=True, default=str) + "\n"
    )
    print(text)
    print(f"wrote {out} and {out.with_suffix('.json')} in {meta['minutes']:.1f} min")
    return 0
