"""The closed loop of active perception: policies, stopping, scoring, and the command."""

import json
import subprocess
import sys

import numpy as np
import pytest
from conftest import SMALL_CAMERA

from posefuse.estimator.tracker import CONFIRMED, MultiViewEstimator
from posefuse.evaluation.dataset import load_dataset
from posefuse.evaluation.oracle import OracleConfig, OracleFrontend
from posefuse.sim.active import (
    ActiveConfig,
    RecordedScene,
    RenderedScene,
    run_policy,
    score_steps,
)


@pytest.fixture(scope="module")
def recorded(small_dataset_root):
    """Both scenes of the small dataset (3 recorded views each) with oracle detections."""
    dataset = load_dataset(small_dataset_root)
    oracle = OracleFrontend(dataset, OracleConfig(seed=3))
    sources = []
    for scene_id in dataset.scene_ids:
        scene = dataset.scene(scene_id)

        def detect(image, im_id, scene=scene):
            return [d for d, _ in oracle.detect_with_truth(scene.view(im_id))]

        sources.append(RecordedScene(scene, detect))
    return dataset, sources


@pytest.mark.parametrize("policy", ["nbv", "random", "sweep"])
def test_every_policy_starts_alike_and_never_repeats_a_view(recorded, policy, default_banks):
    dataset, sources = recorded
    n = found = 0
    for source in sources:
        estimator = MultiViewEstimator(dataset.catalog, banks=default_banks)
        run = run_policy(source, estimator, policy, ActiveConfig(budget=8), seed=1)
        taken = [s.candidate for s in run.steps]
        assert taken[0] == source.path[0]
        assert len(taken) == len(set(taken)) == len(source.candidates)  # 3 recorded views
        assert run.stopped == "no views left"
        if policy == "sweep":
            assert taken == source.path
        if policy == "nbv":
            assert all(np.isfinite(s.score) for s in run.steps[1:])
        else:
            assert all(np.isnan(s.score) for s in run.steps)
        scores = score_steps(run, source.truth(), dataset.catalog)
        assert len(scores) == 3 and scores[0]["add_sym"] == 0  # one view confirms nothing
        n += scores[-1]["n"]
        found += scores[-1]["add_sym"]
    # every policy ends with the same three views fused: a floor against the truth (7 or 8 of
    # the 13 scored parts are found, whatever the order; random rotations find none)
    assert n == 13 and found >= 0.4 * n, f"{policy}: {found} of {n} parts within 0.1 d"


def _min_confidence(step):
    confirmed = [e.confidence for e in step.estimates if e.status == CONFIRMED]
    return min(confirmed) if confirmed else None


def test_stops_once_every_confirmed_object_is_confident(recorded, default_banks):
    """The threshold is earned: it lies between the least confident confirmed object after the
    second view and after the third, so the run stops at the first of them where every
    confirmed object reaches it (an object above it is not enough: every confirmed one must
    be), and a threshold above both is never met."""
    dataset, sources = recorded
    source = sources[0]

    def run(confidence):
        estimator = MultiViewEstimator(dataset.catalog, banks=default_banks)
        config = ActiveConfig(budget=8, confidence=confidence)
        return run_policy(source, estimator, "sweep", config)

    reference = run(None)
    assert reference.stopped == "no views left" and len(reference.steps) == 3
    assert not any(e.status == CONFIRMED for e in reference.steps[0].estimates)
    c2, c3 = _min_confidence(reference.steps[1]), _min_confidence(reference.steps[2])
    # the third view changes the least confident object's confidence (verification across
    # views may lower it as well as raise it)
    assert 0.1 < min(c2, c3) and max(c2, c3) < 1 and abs(c2 - c3) > 0.01
    threshold = (c2 + c3) / 2
    first_met = 2 if c2 >= threshold else 3
    if first_met == 3:
        most_confident_after_two = max(e.confidence for e in reference.steps[1].estimates)
        assert most_confident_after_two > threshold  # one object is, the others are not yet

    stopped = run(threshold)
    assert stopped.stopped == "confident" and len(stopped.steps) == first_met
    last = stopped.steps[-1]
    assert all(e.confidence >= threshold for e in last.estimates if e.status == CONFIRMED)
    for a, b in zip(stopped.steps, reference.steps[:first_met], strict=True):  # the same views
        assert a.candidate == b.candidate
        assert [e.confidence for e in a.estimates] == [e.confidence for e in b.estimates]

    at_two = run(c2)  # met (>=) by every confirmed object after two views
    assert at_two.stopped == "confident" and len(at_two.steps) == 2
    never = run(min(1.0, max(c2, c3) + 1e-3))  # no object earns this within the recorded views
    assert never.stopped == "no views left" and len(never.steps) == 3


SMALL_HEMISPHERE = {"distances": (0.7,), "polar_deg": (0.0, 30.0), "n_azimuth": 6}


def _oracle_rendered(catalog, seed, spec):
    """A rendered bin (its 4-view path and 7 hemisphere candidates at 640x360) whose detections
    are the truth: the projected origin of every part at least 10% visible in the view, with
    2 px of noise seeded by the view, its visible box and mask."""
    from posefuse.estimator.frontend.detection import Detection
    from posefuse.sim.scenes import make_scene

    scene = make_scene(catalog, spec, seed, SMALL_CAMERA)
    config = ActiveConfig(budget=2, **SMALL_HEMISPHERE)
    source = None

    def detect(image, k):
        c = source.candidates[k]
        instance = source.renderer.render(c.camera, c.T_world_cam, scene.lighting).instance
        visib = source.visibility(k)
        rng = np.random.default_rng([seed, k])
        T_cam_world = np.linalg.inv(c.T_world_cam)
        out = []
        for i, inst in enumerate(scene.instances):
            noise = rng.normal(0.0, 2.0, 2)
            mask = instance == i
            t = (T_cam_world @ inst.T_world_obj)[:3, 3]
            if visib[i] < 0.1 or not mask.any() or t[2] <= 0:
                continue
            uv = c.camera.project(t)
            if not c.camera.contains(uv[None])[0]:
                continue
            ys, xs = np.nonzero(mask)
            box = np.array([xs.min(), ys.min(), xs.max() - xs.min() + 1, ys.max() - ys.min() + 1])
            out.append(Detection(inst.obj_id, box.astype(float), uv + noise, 4.0 * np.eye(2), mask))
        return out

    source = RenderedScene(catalog, scene, spec, detect, config, seed + 1)
    return source, config


def test_nbv_second_view_finds_more_parts_than_random_or_the_sweep(robi_catalog, default_banks):
    """Over six seeded bins, the view NBV picks second (across the first view's rays, where
    the parts are founded) gives more parts within ADD-sym 0.1 d than a random second view
    (mean of four seeds) or the planned path's. Measured: 21 of the 37 scored parts for NBV,
    15 or 16 (mean 15.25) at random, 14 for the sweep; an NBV that picks at random (random
    scores for the candidates) got 14."""
    from posefuse.sim.scenes import SceneSpec
    from posefuse.sim.synth import scene_seed

    spec = SceneSpec(n_instances=(5, 8), n_views=4)
    found = {"nbv": 0, "sweep": 0, "random": 0}
    n_random = 4
    n = 0
    for b in range(6):
        source, config = _oracle_rendered(robi_catalog, scene_seed(6600, b), spec)
        truth = source.truth()
        assert len(source.candidates) == 4 + 7
        runs = [("nbv", 0), ("sweep", 0)] + [("random", s) for s in range(n_random)]
        for policy, seed in runs:
            estimator = MultiViewEstimator(robi_catalog, banks=default_banks)
            run = run_policy(source, estimator, policy, config, seed=seed)
            assert run.stopped == "budget" and len(run.steps) == 2
            scores = score_steps(run, truth, robi_catalog)
            found[policy] += scores[1]["add_sym"]
        n += scores[1]["n"]
    random_mean = found["random"] / n_random
    assert n >= 30
    assert found["nbv"] >= 1.2 * random_mean, (found, n)
    assert found["nbv"] > found["sweep"], (found, n)


def test_run_active_command(tmp_path):
    out = tmp_path / "active"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "posefuse.cli",
            "run-active",
            "--profile",
            "robi",
            "--budget",
            "2",
            "--out",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    assert "view 2: candidate" in proc.stdout and "ADD-sym < 0.1 d" in proc.stdout
    (report,) = json.loads((out / "active.json").read_text())
    assert len(report["views"]) == 2 and report["views"][1]["score"] is not None
    assert report["views"][0]["candidate"] == 0
    bad = subprocess.run(
        [sys.executable, "-m", "posefuse.cli", "run-active", "--profile", "robi", "--budget", "0"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert bad.returncode != 0 and "budget" in bad.stderr
