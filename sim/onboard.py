"""From CAD meshes to a servable part set in one command (``posefuse onboard``).

Stages, each timed and written to ``DIR/parts.json``:

1. catalog: meshes read in their units (implausible sizes refused), symmetries detected as whole
   groups or taken from the person's ``--symmetry NAME=SPEC``, a BOP catalog in ``DIR/catalog``
   and a contact sheet per part in ``DIR/contact/NAME.png`` (flagged near-symmetries in red);
2. templates: the LINE-2D banks, built in parallel into the template cache;
3. front end: training scenes rendered and the network trained until the budget's deadline, or
   for a fixed number of steps on a fixed number of scenes with ``steps`` (the same network on
   any machine, however fast) (``DIR/model/parts.onnx`` and its card);
4. validation: held-out renders of both profiles (seeds never used for training), the front
   end's recall and precision, and ADD-sym after 4 and 8 views with the network's detections.

The budget covers the whole command: after the first two stages the rendering of training data
is sized from a pilot render so that it takes a third of what is left, and training ends early
enough to leave the validation its measured share.
"""

from __future__ import annotations

import json
import re
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from posefuse.estimator.core.errors import PosefuseError
from posefuse.estimator.core.objects import (
    Catalog,
    load_mesh,
    make_model,
    mesh_diameter,
    write_catalog,
)
from posefuse.estimator.core.symmetry import detect_symmetries, symmetry_from_spec
from posefuse.evaluation.eval_points import with_eval_points

MANIFEST = "parts.json"
MANIFEST_VERSION = 1
VALIDATION_SEED = 880_000  # held-out renders: disjoint from training (sim.train) and test seeds
# scored parts (visib > 0.75) a validation scene gives at its last view, a first guess of how
# many scenes the validation renders: the five meshes of ../shared/objects gave 7.9 (mixed) and
# 9.0 (robi) in onboarding's validation renders; a part set that gives fewer gets more scenes,
# in rounds sized from what the first gave, up to MAX_HELD_SCENES
INSTANCES_PER_SCENE = {"mixed": 7.5, "robi": 9.0}
MAX_HELD_SCENES = 40
# the network and the estimator on a validation view, besides its render
VALIDATION_S_PER_VIEW = 0.5
# the validation's measured time over its estimate from the single-process pilot: 449 s against
# 324 s for the five meshes of ../shared/objects (26 scenes; two render processes share the
# cores' memory and clock, and the pilot's scene is one draw of the profile)
VALIDATION_MARGIN = 1.4
# within the budget, the validation takes at most this share of what the catalog and templates
# leave (the rest trains), its target lowered to fit, down to MIN_HELD_INSTANCES parts a profile.
# The five meshes of ../shared/objects estimate 9.2 of 14.5 min for 100 parts (0.63): they keep
# them; LM-O's eight household meshes estimate 20 of 14 min and shrink
VALIDATION_SHARE_MAX = 0.65
MIN_HELD_INSTANCES = 30


@dataclass(frozen=True)
class OnboardConfig:
    units: str = "mm"
    minutes: float = 15.0  # the whole command's budget
    symmetry: dict[str, str] = field(default_factory=dict)  # part name -> spec
    views: int = 6  # per training scene
    val_scenes: int = 4  # calibration renders of the training run
    # the validation renders, per profile: scenes until at least ``held_instances`` parts are
    # scored (visib > 0.75) at the last view (8), or ``held_scenes`` scenes when given
    held_instances: int = 100
    held_scenes: int | None = None
    # the budget's validation may shrink: where the validation of ``held_instances`` parts would
    # take more than VALIDATION_SHARE_MAX of what the catalog and templates leave, its target is
    # lowered to fit (never below MIN_HELD_INSTANCES) and the run says so; False (a target the
    # person chose) keeps it and refuses a budget too small for it
    fit_validation: bool = True
    held_views: int = 8
    workers: int = 2
    seed: int = 0
    robi_fraction: float = 0.5
    # a fixed amount of training instead of the budget: ``steps`` optimiser steps on
    # ``train_scenes`` rendered scenes, whatever the machine's speed (``minutes`` is then unused)
    steps: int | None = None
    train_scenes: int = 24
    # the front end starts from this checkpoint's weights (the shipped model's by default: its
    # backbone and stage two are shared by every part; only the class heatmaps are new);
    # None trains from scratch
    init: str | None = "shipped"
    photometric: bool = False  # a real camera's effects drawn per training sample (sim.photometric)
    backgrounds: float = 0.0  # the share of training samples on clutter (sim.backgrounds)
    # the share of training scenes composed from parts rendered alone (sim.composite)
    composite: float = 0.0


class Stages:
    """Prints one line per stage with the elapsed time and the budget's end."""

    def __init__(self, budget_s: float | None, echo=print):
        self.start = time.time()
        self.budget_s = budget_s
        self.seconds: dict[str, float] = {}
        self.echo = echo
        self._t = self.start

    def begin(self, k: int, name: str, detail: str = "") -> None:
        self._t = time.time()
        elapsed = self._t - self.start
        left = (
            f", {(self.budget_s - elapsed) / 60:.1f} min of the budget left"
            if self.budget_s is not None
            else ""
        )
        head = f"[{k}/4] {name}{': ' + detail if detail else ''}"
        self.echo(f"{head}  (elapsed {elapsed / 60:.1f} min{left})")

    def end(self, name: str) -> float:
        self.seconds[name] = round(time.time() - self._t, 1)
        return self.seconds[name]

    @property
    def deadline(self) -> float | None:
        return None if self.budget_s is None else self.start + self.budget_s


BOP_MODEL_NAME = re.compile(r"^obj_(\d{6})$")


def part_ids_and_names(paths: list[str]) -> tuple[list[int], list[str]]:
    """The obj_id and name of each mesh.

    Meshes named as a BOP dataset names them (``obj_000005.ply``, every one of them) keep their
    ids, so the part set's model scores on the dataset they came from; each takes its name from
    the ``models_info.json`` beside it where that gives one (LM-O's "can"), else its file name.
    Any other set of meshes is numbered 1..N in the order given, named by file.
    """
    stems = [Path(p).stem for p in paths]
    matches = [BOP_MODEL_NAME.match(s) for s in stems]
    if not paths or not all(matches):
        return list(range(1, len(paths) + 1)), stems
    ids = [int(m.group(1)) for m in matches]
    if min(ids) < 1:
        raise PosefuseError(f"onboard: a BOP model's obj_id must be positive, got {stems}")
    names = []
    for path, obj_id, stem in zip(paths, ids, stems, strict=True):
        info_path = Path(path).parent / "models_info.json"
        name = stem
        if info_path.is_file():
            try:
                entry = json.loads(info_path.read_text()).get(str(obj_id), {})
            except (json.JSONDecodeError, UnicodeDecodeError, AttributeError) as exc:
                raise PosefuseError(
                    f"onboard: {info_path} is not a BOP models_info: {exc}"
                ) from None
            if isinstance(entry, dict) and str(entry.get("name", "")).strip():
                name = str(entry["name"]).strip()
        names.append(name)
    return ids, names


def read_parts(paths: list[str], config: OnboardConfig, echo=print) -> tuple[Catalog, dict]:
    """The catalog of the meshes (ids and names by :func:`part_ids_and_names`) and, per part,
    its symmetry report as JSON."""
    ids, names = part_ids_and_names(paths)
    if len(set(names)) != len(names):
        raise PosefuseError(f"onboard: two meshes share a name: {sorted(names)}")
    if len(set(ids)) != len(ids):
        raise PosefuseError(f"onboard: two meshes share an obj_id: {sorted(ids)}")
    unknown = sorted(set(config.symmetry) - set(names))
    if unknown:
        raise PosefuseError(f"--symmetry: no mesh named {unknown}; the parts are {names}")
    models, reports = [], {}
    for obj_id, path, name in zip(ids, paths, names, strict=True):
        mesh = load_mesh(path, units=config.units)
        if not mesh.is_watertight:
            # CAD exports often are: rendering, symmetry detection and the pose errors work on
            # the surface alone, so the mesh is used as it is
            echo(
                f"  note: {path} is not watertight ({len(mesh.faces)} triangles with open "
                "edges); accepted, as only its surface is used"
            )
        diameter = mesh_diameter(mesh)
        report = detect_symmetries(mesh, diameter)
        if name in config.symmetry:
            try:
                disc, cont = symmetry_from_spec(config.symmetry[name], mesh, diameter, report)
            except ValueError as exc:
                raise PosefuseError(f"--symmetry {name}: {exc}") from None
            decided = f"set by --symmetry {name}={config.symmetry[name]}"
        else:
            disc, cont = report.discrete, report.continuous
            decided = "detected"
        models.append(
            make_model(obj_id, name, mesh, disc, cont, near_symmetries=report.alternatives)
        )
        reports[name] = {
            "report": report,
            "decided": decided,
            "json": {
                "detected": report.describe(),
                "decided": decided,
                "axes": [
                    {
                        "axis": list(a.axis),
                        "order": a.order,
                        "residual": a.residual,
                        "margin": report.margin(a),
                    }
                    for a in report.axes
                ],
                "alternatives": [
                    {"axis": list(a.axis), "order": a.order, "residual": a.residual}
                    for a in report.alternatives
                ],
                "flags": list(report.flags),
            },
        }
    return Catalog(models), reports


def onboard(paths: list[str], out: str | Path, config: OnboardConfig, echo=print) -> dict:
    """Run every stage; returns the manifest written to ``out/parts.json``."""
    from posefuse.estimator.rotation.templates import build_template_banks
    from posefuse.sim.contact_sheet import write_contact_sheet

    if not paths:
        raise PosefuseError("onboard: give at least one mesh file")
    if config.steps is not None:
        if config.steps <= 0 or config.train_scenes < 2:
            raise PosefuseError(
                f"--steps must be positive and --train-scenes at least 2, got {config.steps} "
                f"and {config.train_scenes}"
            )
    for name, share in (("backgrounds", config.backgrounds), ("composite", config.composite)):
        if not 0.0 <= share <= 1.0:
            raise PosefuseError(f"--{name} must be in [0, 1], got {share}")
    if config.steps is None and config.minutes <= 0:
        raise PosefuseError(f"--minutes must be positive, got {config.minutes}")
    if config.held_instances < 1 or (config.held_scenes is not None and config.held_scenes < 1):
        raise PosefuseError(
            f"--held-instances and --held-scenes must be at least 1, got {config.held_instances} "
            f"and {config.held_scenes}"
        )
    out = Path(out)
    stages = Stages(None if config.steps is not None else config.minutes * 60, echo)

    stages.begin(1, "catalog", f"{len(paths)} mesh(es) in {config.units}")
    catalog, reports = read_parts(paths, config, echo)
    write_catalog(out / "catalog", with_eval_points(catalog))
    for model in catalog.values():
        info = reports[model.name]
        sheet = write_contact_sheet(model, info["report"], out / "contact" / f"{model.name}.png")
        echo(
            f"  {model.name}: {model.diameter * 1000:.1f} mm, {model.describe_symmetries()} "
            f"({info['decided']}); contact sheet {sheet}"
        )
        for flag in info["report"].flags:
            echo(f"    check: {flag}")
    stages.end("catalog")

    stages.begin(2, "templates", "LINE-2D banks, one process per part")
    build_template_banks([catalog[k] for k in catalog], workers=config.workers)
    stages.end("templates")

    stages.begin(
        3,
        "front end",
        "render training scenes, train until the deadline"
        if config.steps is None
        else f"render {config.train_scenes} training scenes, train {config.steps} steps",
    )
    model_path = out / "model" / "parts.onnx"
    card, config = _train(out / "catalog", model_path, catalog, config, stages)
    stages.end("front end")

    stages.begin(4, "validation", "held-out renders of both profiles, network front end")
    validation = validate(out, catalog, model_path, config, echo)
    stages.end("validation")

    manifest = {
        "version": MANIFEST_VERSION,
        "catalog": "catalog",
        "model": "model/parts.onnx",
        "units_read": config.units,
        "parts": [
            {
                "obj_id": k,
                "name": m.name,
                "diameter_mm": round(m.diameter * 1000, 2),
                "symmetry": m.describe_symmetries(),
                "symmetry_detection": reports[m.name]["json"],
                "contact_sheet": f"contact/{m.name}.png",
            }
            for k, m in catalog.items()
        ],
        "training": card.get("training", {}),
        "validation": validation,
        "validation_target_parts": (
            None if config.held_scenes is not None else config.held_instances
        ),
        "stage_seconds": stages.seconds,
        "budget_minutes": None if config.steps is not None else config.minutes,
        "training_steps": config.steps,
        "total_minutes": round((time.time() - stages.start) / 60, 2),
    }
    (out / MANIFEST).write_text(json.dumps(manifest, indent=2) + "\n")
    return manifest


def initial_checkpoint(config) -> str | None:
    """The checkpoint onboarding fine-tunes from: ``config.init``, where "shipped" means the
    shipped generalist's (``models/generalist.ckpt``: it has seen hundreds of part shapes, so
    its backbone and stage two know what a part is) when it is there, else the shipped catalog
    model's (``models/robi_like.ckpt``)."""
    if config.init is None:
        return None
    if config.init != "shipped":
        if not Path(config.init).is_file():
            raise PosefuseError(f"--init: {config.init}: no such checkpoint")
        return config.init
    from posefuse.service.resources import DEFAULT_MODEL, GENERALIST_MODEL

    for model in (GENERALIST_MODEL, DEFAULT_MODEL):
        shipped = Path(model).with_suffix(".ckpt")
        if shipped.is_file():
            return str(shipped)
    return None


def _train(catalog_dir: Path, model_path: Path, catalog: Catalog, config, stages: Stages) -> dict:
    from posefuse.sim.train import TrainConfig, train

    init = initial_checkpoint(config)

    if config.steps is not None:  # a fixed amount of work: no clock decides anything
        return train(
            catalog_dir,
            model_path,
            TrainConfig(
                n_scenes=config.train_scenes,
                views_per_scene=config.views,
                val_scenes=config.val_scenes,
                minutes=1e6,  # never the limit: max_iterations is
                max_iterations=config.steps,
                warmup=max(config.steps // 10, 1),
                workers=config.workers,
                seed=config.seed,
                robi_fraction=config.robi_fraction,
                deadline=None,
                init=init,
                photometric=config.photometric,
                backgrounds=config.backgrounds,
                composite=config.composite,
                tune_min_score=True,
            ),
        ), config
    setup, per_view = pilot_render(catalog_dir)
    workers = max(config.workers, 1)
    left = stages.deadline - time.time()
    config = fitted_validation(config, left, setup, per_view, stages.echo)
    reserve = validation_seconds(config, setup, per_view)
    usable = left - reserve
    if usable < 30:
        raise PosefuseError(
            f"--minutes {config.minutes}: {left / 60:.1f} min remain after the catalog and "
            f"templates, not enough to train and validate (about {reserve / 60:.1f} min of "
            "validation alone); raise --minutes"
        )
    # the training scenes' renders take about a third of what is left
    per_scene = (setup + config.views * per_view) / workers
    if config.composite > 0:
        composed = pilot_compose(catalog_dir, config.views) / workers
        per_scene = (1 - config.composite) * per_scene + config.composite * composed
    n_views = max(int(usable / 3 / per_scene) * config.views, 2 * config.views)
    n_scenes = max(n_views // config.views, 2)
    train_config = TrainConfig(
        n_scenes=n_scenes,
        views_per_scene=config.views,
        val_scenes=config.val_scenes,
        minutes=usable / 60,
        workers=config.workers,
        seed=config.seed,
        robi_fraction=config.robi_fraction,
        deadline=stages.deadline - reserve,
        clock_schedule=True,  # however many steps the minutes hold, the run ends annealed
        tune_min_score=True,
        init=init,
        photometric=config.photometric,
        backgrounds=config.backgrounds,
        composite=config.composite,
    )
    return train(catalog_dir, model_path, train_config), config


def fitted_validation(config, left_s: float, setup: float, per_view: float, echo=print):
    """``config`` with the validation's target lowered so that the validation takes at most
    VALIDATION_SHARE_MAX of the ``left_s`` seconds the budget has after the catalog and
    templates (its time estimated by :func:`validation_seconds`), never below
    MIN_HELD_INSTANCES; unchanged where it fits, where the person fixed the validation
    (``fit_validation`` False, or ``held_scenes``), or where the target is already that low."""
    import dataclasses

    reserve = validation_seconds(config, setup, per_view)
    allowed = VALIDATION_SHARE_MAX * left_s
    if (
        not config.fit_validation
        or config.held_scenes is not None
        or reserve <= allowed
        or config.held_instances <= MIN_HELD_INSTANCES
    ):
        return config
    target = config.held_instances
    while target > MIN_HELD_INSTANCES:  # the scene counts are whole, so step down to fit
        target = max(MIN_HELD_INSTANCES, int(target * 0.9))
        fitted = dataclasses.replace(config, held_instances=target)
        if validation_seconds(fitted, setup, per_view) <= allowed:
            break
    needed = config.minutes + (reserve / VALIDATION_SHARE_MAX - left_s) / 60
    echo(
        f"  note: a validation of {config.held_instances} parts a profile would take about "
        f"{reserve / 60:.1f} of the {left_s / 60:.1f} min left; it scores {target} parts a "
        f"profile instead (--minutes {np.ceil(needed):.0f} for {config.held_instances})"
    )
    return fitted


def validate(out: Path, catalog: Catalog, model_path: Path, config, echo=print) -> dict:
    """Front-end recall/precision and ADD-sym at 4 and 8 views on held-out renders."""
    from posefuse.estimator.frontend.network import NetworkFrontend
    from posefuse.estimator.tracker import MultiViewEstimator
    from posefuse.evaluation.dataset import load_dataset
    from posefuse.evaluation.frontend_metrics import score_frontend
    from posefuse.evaluation.run_dataset import LabelledNetworkFrontend, run_dataset
    from posefuse.evaluation.scores import evaluate

    figures = {}
    for k, profile in enumerate(("mixed", "robi")):
        root = out / "validation" / profile
        seed = VALIDATION_SEED + config.seed * 10 + k
        n_scenes, scored = render_validation(catalog, root, profile, seed, config)
        dataset = load_dataset(root)
        network = NetworkFrontend(model_path, dataset.catalog, seed=config.seed)

        def detect(view, network=network, dataset=dataset):
            image = dataset.scene(view.scene_id).load_rgb(view.im_id)
            return network.detect(image, stamp_seed=view.scene_id * 100_000 + view.im_id)

        score = score_frontend(dataset, detect, list(dataset.views()))
        shared = MultiViewEstimator(dataset.catalog)
        shared.prepare_templates(workers=config.workers)
        run = run_dataset(
            dataset,
            LabelledNetworkFrontend(dataset, network),
            show_progress=False,
            rotation=True,
            estimator_factory=lambda d=dataset, s=shared: MultiViewEstimator(
                d.catalog, banks=s.banks()
            ),
        )
        accuracy = {}
        for n in (4, 8):
            if run.targets.get(n):
                report = evaluate(dataset, run.results[n], targets=run.targets[n])
                total = report.total
                accuracy[str(n)] = {
                    "add_sym": total.rate(),
                    "mssd": total.rate("mssd"),
                    "ar_mssd": total.ar_mssd,
                    "precision": total.precision(),
                    "instances": total.n_instances,
                }
        figures[profile] = {
            "dataset": f"validation/{profile}",
            "seed": seed,
            "scenes": n_scenes,
            "views": config.held_views,
            "scored_instances": scored,
            "frontend": {
                "recall": score.recall,
                "precision": score.precision,
                "median_center_error_px": score.median_center_error_px,
                "instances": score.n_instances,
            },
            "views_accuracy": accuracy,
        }
        acc = "  ".join(f"{n} views ADD-sym {100 * a['add_sym']:.1f}%" for n, a in accuracy.items())
        echo(
            f"  {profile} ({n_scenes} scenes, {scored[str(config.held_views)]} parts scored at "
            f"{config.held_views} views): front end recall {score.recall:.3f}, precision "
            f"{score.precision:.3f}; {acc}"
        )
    return figures


def pilot_render(catalog_dir: Path) -> tuple[float, float]:
    """(seconds to lay out and prepare a scene, seconds to render one of its views) here, in one
    process: a robi scene (the slower profile: its parts are dropped one by one onto the pile)
    prepared, then two of its views rendered."""
    from posefuse.sim.train import TRAIN_SEED_BASE
    from posefuse.sim.train_data import _cached_catalog, _scene_renderer, render_views

    _cached_catalog(str(catalog_dir))  # loaded once, as each worker has it
    t0 = time.perf_counter()
    prepared = _scene_renderer(str(catalog_dir), 0, 2, TRAIN_SEED_BASE + 7, "robi")
    t1 = time.perf_counter()
    render_views(*prepared, 0.5)
    t2 = time.perf_counter()
    return t1 - t0, (t2 - t1) / 2


def pilot_compose(catalog_dir: Path, views: int) -> float:
    """Seconds to compose one training scene of ``views`` views here (``sim.composite``), in
    one process: a mixed one, whose cut-outs are of every part."""
    from posefuse.sim.train import TRAIN_SEED_BASE
    from posefuse.sim.train_data import compose_scene

    t0 = time.perf_counter()
    compose_scene(str(catalog_dir), 0, views, TRAIN_SEED_BASE + 7, "mixed", 0.5)
    return time.perf_counter() - t0


def validation_scenes(config) -> int:
    """How many scenes the validation is expected to render, both profiles together."""
    if config.held_scenes is not None:
        return 2 * config.held_scenes
    return sum(
        min(int(np.ceil(config.held_instances / guess)), MAX_HELD_SCENES)
        for guess in INSTANCES_PER_SCENE.values()
    )


def validation_seconds(config, setup: float, per_view: float) -> float:
    """The validation's expected wall time: its scenes rendered in ``config.workers`` processes
    (``setup`` and ``per_view`` from :func:`pilot_render`), and the network and the tracker on
    every view."""
    scenes = validation_scenes(config)
    views = scenes * config.held_views
    render = (scenes * setup + views * per_view) / max(config.workers, 1)
    return VALIDATION_MARGIN * (render + views * VALIDATION_S_PER_VIEW)


def scored_instances(root: Path, scene_ids, checkpoints: tuple[int, ...]) -> dict[int, int]:
    """Parts scored (visib > 0.75, as ``evaluation.scores``) in the ``count``-th view of the
    scenes ``scene_ids`` of a rendered dataset, per count of ``checkpoints``."""
    counts = dict.fromkeys(checkpoints, 0)
    for scene_id in scene_ids:
        info = json.loads((root / "test" / f"{scene_id:06d}" / "scene_gt_info.json").read_text())
        im_ids = sorted(info, key=int)
        for n in checkpoints:
            counts[n] += sum(g["visib_fract"] > 0.75 for g in info[im_ids[n - 1]])
    return counts


def render_validation(
    catalog: Catalog, root: Path, profile: str, seed: int, config
) -> tuple[int, dict[str, int]]:
    """Render a profile's validation scenes into ``root``: ``config.held_scenes`` of them, or
    rounds of scenes until ``held_instances`` parts are scored at the last view (each round
    sized from the scenes so far), at most MAX_HELD_SCENES. Returns the scenes and the scored
    parts per count of views reported (4, 8 and the last)."""
    from posefuse.sim.scenes import PROFILES
    from posefuse.sim.synth import SynthConfig, generate_dataset, write_synth_json

    spec = _with_views(PROFILES[profile], config.held_views)
    last = config.held_views
    checkpoints = tuple(sorted({n for n in (4, 8) if n <= last} | {last}))
    done, counts = 0, dict.fromkeys(checkpoints, 0)
    target = config.held_instances
    while True:
        if config.held_scenes is not None:
            n = config.held_scenes - done
        else:
            per_scene = counts[last] / done if done else INSTANCES_PER_SCENE.get(profile, 6.0)
            missing = target - counts[last]
            n = int(np.ceil(missing / max(per_scene, 0.5)))
        n = min(n, MAX_HELD_SCENES - done)
        if n <= 0:
            break
        part = SynthConfig(n_scenes=n, seed=seed, first_scene_id=done, scene=spec, profile=profile)
        generate_dataset(catalog, root, part, show_progress=False, workers=config.workers)
        for c, m in scored_instances(root, range(done, done + n), checkpoints).items():
            counts[c] += m
        done += n
        if config.held_scenes is not None or counts[last] >= target:
            break
    write_synth_json(root, SynthConfig(n_scenes=done, seed=seed, scene=spec, profile=profile))
    return done, {str(c): m for c, m in counts.items()}


def _with_views(spec, n_views: int):
    import dataclasses

    return dataclasses.replace(spec, n_views=n_views)


@dataclass(frozen=True)
class PartSet:
    """A servable part set: the folder ``posefuse onboard`` wrote."""

    root: Path
    catalog: Path
    model: Path
    manifest: dict


def load_part_set(root: str | Path) -> PartSet:
    """Read ``root/parts.json``; raises PosefuseError naming what is missing."""
    root = Path(root)
    path = root / MANIFEST
    if not path.is_file():
        raise PosefuseError(f"{path}: missing; a part set is the folder `posefuse onboard` wrote")
    try:
        manifest = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise PosefuseError(f"{path}: not valid JSON: {exc}") from None
    if not isinstance(manifest, dict) or manifest.get("version") != MANIFEST_VERSION:
        raise PosefuseError(f"{path}: not a version-{MANIFEST_VERSION} part set manifest")
    catalog, model = root / str(manifest.get("catalog")), root / str(manifest.get("model"))
    for what, p in (("catalog", catalog), ("model", model)):
        if not p.exists():
            raise PosefuseError(f"{path}: its {what} {p} is missing")
    return PartSet(root, catalog, model, manifest)


def parts_table(manifest: dict) -> str:
    """The manifest's parts and validation figures as Markdown."""
    rows = ["| obj_id | name | diameter (mm) | symmetry | flags |", "|---|---|---|---|---|"]
    for p in manifest["parts"]:
        flags = len(p["symmetry_detection"]["flags"])
        rows.append(
            f"| {p['obj_id']} | {p['name']} | {p['diameter_mm']:.1f} | {p['symmetry']} | "
            f"{flags or '-'} |"
        )
    rows += [
        "",
        "| profile | recall | precision | ADD-sym 4 views | ADD-sym 8 views |",
        "|---|---|---|---|---|",
    ]
    for profile, v in manifest["validation"].items():
        acc = v["views_accuracy"]
        cells = [f"{100 * acc[n]['add_sym']:.1f}%" if n in acc else "-" for n in ("4", "8")]
        rows.append(
            f"| {profile} | {v['frontend']['recall']:.3f} | {v['frontend']['precision']:.3f} | "
            f"{cells[0]} | {cells[1]} |"
        )
    return "\n".join(rows) + "\n" + _nan_note(manifest)


def _nan_note(manifest: dict) -> str:
    vals = [v["frontend"]["recall"] for v in manifest["validation"].values()]
    return "" if all(np.isfinite(vals)) else "(nan: no visible instance to score)\n"
