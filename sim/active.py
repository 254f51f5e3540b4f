"""Active perception in simulation: the estimator chooses where the camera looks next.

A :class:`ViewSource` is a scene whose candidate views can be taken in any order: a synthetic
bin rendered on demand (:class:`RenderedScene`, each candidate rendered once with the sensor's
noise, seeded by its index, so every policy sees the same image from the same pose), or the
recorded views of a BOP scene (:class:`RecordedScene`). :func:`run_policy` closes the loop: it
takes the first view, then asks the policy for the next one among the views not taken yet,
runs the front end on it and fuses it, until the view budget is spent or every confirmed object
is at least as confident as the threshold.

Policies: ``nbv`` (:mod:`estimator.nbv` on the estimator's tracks and held detections),
``random`` (a seeded random order) and ``sweep`` (the scene's own planned path, in order).
All start from the same first view (the path's first).

Scoring (:func:`score_steps`): the poses reported after each view against the instances more
than 75% visible in that shared first view, with BOP's greedy matching: ADD-sym < 0.1 d and
MSSD < 0.1 d. The same instances are scored for every policy and every number of views.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from posefuse.estimator.nbv import (
    BinRegion,
    CandidateView,
    NbvConfig,
    appearance_index,
    default_candidates,
    score_candidates,
    tracks_for_nbv,
)
from posefuse.estimator.tracker import CONFIRMED, Frame, MultiViewEstimator, ObjectEstimate
from posefuse.evaluation.scores import error_matrix, match_estimates

POLICIES = ("nbv", "random", "sweep")
MIN_VISIB = 0.75


@dataclass(frozen=True)
class ActiveConfig:
    budget: int = 8  # views at most
    confidence: float | None = None  # stop once every confirmed object is this confident
    nbv: NbvConfig = field(default_factory=NbvConfig)
    # the default candidates: the scene's path plus a hemisphere over the bin
    distances: tuple[float, ...] = (0.6, 0.8)
    polar_deg: tuple[float, ...] = (0.0, 17.5, 35.0)
    n_azimuth: int = 8

    def __post_init__(self) -> None:
        if self.budget < 1:
            raise ValueError(f"view budget must be at least 1, got {self.budget}")
        if self.confidence is not None and not 0 < self.confidence <= 1:
            raise ValueError(f"confidence threshold must be in (0, 1], got {self.confidence}")


@dataclass(frozen=True, eq=False)
class Truth:
    """The instances of a scene: obj_id (G,), T_world_obj (G, 4, 4), and which are scored."""

    obj_ids: np.ndarray
    T_world_obj: np.ndarray
    scored: np.ndarray  # (G,) bool: more than MIN_VISIB visible in the first view


class ViewSource:
    """Candidate views of one scene, any of which can be taken (see the module docstring)."""

    candidates: list[CandidateView]
    path: list[int]  # the planned path (the sweep), indices into candidates
    bin_region: BinRegion | None = None

    def image(self, k: int) -> np.ndarray:
        raise NotImplementedError

    def detections(self, k: int) -> list:
        raise NotImplementedError

    def truth(self) -> Truth | None:
        return None


class RenderedScene(ViewSource):
    """A synthetic bin (:func:`sim.scenes.make_scene`): the scene's own views (its path) and a
    hemisphere over the bin, rendered when first asked for."""

    def __init__(self, catalog, scene, spec, detect: Callable, config: ActiveConfig, seed: int):
        from posefuse.estimator.rotation.render import Renderer
        from posefuse.sim.synth import BIN_ID, _part_material

        self.catalog = catalog
        self.scene = scene
        self._detect = detect
        self._seed = seed
        self.bin_region = BinRegion(spec.bin.size, spec.bin.wall_height)
        path = [CandidateView(T, scene.camera) for T in scene.T_world_cams]
        hemisphere = default_candidates(
            scene.camera, self.bin_region, config.distances, config.polar_deg, config.n_azimuth
        )
        self.candidates = path + hemisphere
        self.path = list(range(len(path)))
        materials = [_part_material(catalog, i.obj_id) for i in scene.instances]
        meshes = [catalog[i.obj_id].mesh for i in scene.instances] + [scene.bin_mesh]
        poses = [i.T_world_obj for i in scene.instances] + [np.eye(4)]
        ids = list(range(len(scene.instances))) + [BIN_ID]
        self.renderer = Renderer(meshes, poses, ids, materials + [scene.bin_material])
        self._images: dict[int, np.ndarray] = {}
        self._detections: dict[int, list] = {}
        self._visib: dict[int, np.ndarray] = {}

    def _render(self, k: int) -> None:
        from posefuse.sim.sensor import SensorModel, apply_rgb

        c = self.candidates[k]
        res = self.renderer.render(c.camera, c.T_world_cam, self.scene.lighting)
        rng = np.random.default_rng([self._seed, k])
        self._images[k] = apply_rgb(res.image, SensorModel(), rng)
        visib = []
        for i in range(len(self.scene.instances)):
            full = self.renderer.render_mask(c.camera, c.T_world_cam, i).sum()
            visib.append((res.instance == i).sum() / full if full else 0.0)
        self._visib[k] = np.array(visib)

    def image(self, k: int) -> np.ndarray:
        if k not in self._images:
            self._render(k)
        return self._images[k]

    def visibility(self, k: int) -> np.ndarray:
        """(G,) visible share of every instance in view k."""
        self.image(k)
        return self._visib[k]

    def detections(self, k: int) -> list:
        if k not in self._detections:
            self._detections[k] = self._detect(self.image(k), k)
        return self._detections[k]

    def truth(self) -> Truth:
        inst = self.scene.instances
        return Truth(
            np.array([i.obj_id for i in inst]),
            np.stack([i.T_world_obj for i in inst]),
            self.visibility(self.path[0]) > MIN_VISIB,
        )


class RecordedScene(ViewSource):
    """The recorded views of a BOP scene as the candidates (the path: their im_id order)."""

    def __init__(self, scene, detect: Callable):
        self.scene = scene
        self._detect = detect
        self._views = [scene.view(i) for i in scene.im_ids]
        self.candidates = [CandidateView(v.T_world_cam, v.camera) for v in self._views]
        self.path = list(range(len(self._views)))
        self._detections: dict[int, list] = {}

    def image(self, k: int) -> np.ndarray:
        return self.scene.load_rgb(self._views[k].im_id)

    def detections(self, k: int) -> list:
        if k not in self._detections:
            self._detections[k] = self._detect(self.image(k), self._views[k].im_id)
        return self._detections[k]

    def truth(self) -> Truth | None:
        first = self._views[0]
        if not first.gts:
            return None
        return Truth(
            np.array([g.obj_id for g in first.gts]),
            np.stack([first.T_world_cam @ g.T_cam_obj for g in first.gts]),
            np.array([g.visib_fract > MIN_VISIB for g in first.gts]),
        )


@dataclass(frozen=True, eq=False)
class ActiveStep:
    """One view taken: its candidate index, the NBV score it had (NaN for the baselines), the
    estimates reported after it (confirmed, with a rotation; all of them after one view)."""

    candidate: int
    score: float
    estimates: tuple[ObjectEstimate, ...]
    objects_needing_views: int = 0


@dataclass(frozen=True, eq=False)
class ActiveRun:
    policy: str
    steps: tuple[ActiveStep, ...]
    stopped: str  # "budget", "confident" or "no views left"


def run_policy(
    source: ViewSource,
    estimator: MultiViewEstimator,
    policy: str,
    config: ActiveConfig | None = None,
    seed: int = 0,
    on_step: Callable[[ActiveStep], None] | None = None,
) -> ActiveRun:
    """Take views of ``source`` as ``policy`` chooses and fuse them (module docstring)."""
    from posefuse.estimator.nbv import needs_view

    cfg = config or ActiveConfig()
    if policy not in POLICIES:
        raise ValueError(f"policy must be one of {', '.join(POLICIES)}, got {policy!r}")
    rng = np.random.default_rng(seed)
    taken: list[int] = []
    steps: list[ActiveStep] = []
    stopped = "budget"
    indices: dict = {}
    for count in range(1, cfg.budget + 1):
        left = [k for k in range(len(source.candidates)) if k not in taken]
        if not left:
            stopped = "no views left"
            break
        score = float("nan")
        if count == 1:
            k = source.path[0]
        elif policy == "sweep":
            rest = [k for k in source.path if k not in taken]
            if not rest:
                stopped = "no views left"
                break
            k = rest[0]
        elif policy == "random":
            k = int(rng.choice(left))
        else:
            tracks = tracks_for_nbv(estimator, cfg.nbv.max_components)
            for t in tracks:
                if t.obj_id not in indices and len(t.weights) > 1:
                    model = estimator.catalog[t.obj_id]
                    indices[t.obj_id] = appearance_index(estimator.matcher(t.obj_id).bank, model)
            scores = score_candidates(
                tracks, [source.candidates[j] for j in left], indices, cfg.nbv, source.bin_region
            )
            k = left[scores.best]
            score = float(scores.score[scores.best])
        taken.append(k)
        c = source.candidates[k]
        frame = Frame(count * 100_000_000, c.camera, c.T_world_cam, source.image(k))
        estimator.update(frame, source.detections(k))
        reported = tuple(
            e
            for e in estimator.estimates(include_tentative=True)
            if e.hypotheses and (count == 1 or e.status == CONFIRMED)
        )
        needing = sum(needs_view(t, cfg.nbv) for t in tracks_for_nbv(estimator))
        step = ActiveStep(k, score, reported, needing)
        steps.append(step)
        if on_step is not None:
            on_step(step)
        confirmed = [e for e in reported if e.status == CONFIRMED]
        if (
            cfg.confidence is not None
            and confirmed
            and all(e.confidence >= cfg.confidence for e in confirmed)
        ):
            stopped = "confident"
            break
    return ActiveRun(policy, tuple(steps), stopped)


def score_steps(run: ActiveRun, truth: Truth, catalog) -> list[dict[str, int]]:
    """Per view taken: scored instances and how many are found by ADD-sym and MSSD < 0.1 d."""
    out = []
    for step in run.steps:
        found = {"add_sym": 0, "mssd": 0}
        for obj_id in sorted(set(truth.obj_ids.tolist())):
            gts = np.nonzero(truth.obj_ids == obj_id)[0]
            est = sorted(
                (e for e in step.estimates if e.class_id == obj_id), key=lambda e: -e.confidence
            )
            if not est:
                continue
            model = catalog[obj_id]
            T_est = np.stack([e.T_world_obj for e in est])
            for metric in found:
                errors = error_matrix(model, T_est, truth.T_world_obj[gts], metric, model.diameter)
                for _, g in match_estimates(errors, 0.1 * model.diameter):
                    found[metric] += int(truth.scored[gts[g]])
        out.append({"n": int(truth.scored.sum()), **found})
    return out
