"""The closed loop of active perception: policies, stopping, scoring, and the command."""

import json
import subprocess
import sys

import numpy as np
import pytest

from posefuse.estimator.dataset import load_dataset
from posefuse.estimator.frontend.oracle import OracleConfig, OracleFrontend
from posefuse.estimator.tracker import MultiViewEstimator
from posefuse.sim.active import ActiveConfig, RecordedScene, run_policy, score_steps


@pytest.fixture(scope="module")
def recorded(small_dataset_root):
    dataset = load_dataset(small_dataset_root)
    scene = dataset.scene(dataset.scene_ids[0])
    oracle = OracleFrontend(dataset, OracleConfig(seed=3))

    def detect(image, im_id):
        return [d for d, _ in oracle.detect_with_truth(scene.view(im_id))]

    return dataset, RecordedScene(scene, detect)


@pytest.mark.parametrize("policy", ["nbv", "random", "sweep"])
def test_every_policy_starts_alike_and_never_repeats_a_view(recorded, policy, default_banks):
    dataset, source = recorded
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
    found = score_steps(run, source.truth(), dataset.catalog)
    assert len(found) == 3 and all(0 <= f["add_sym"] <= f["n"] for f in found)


def test_stops_once_every_confirmed_object_is_confident(recorded, default_banks):
    dataset, source = recorded
    estimator = MultiViewEstimator(dataset.catalog, banks=default_banks)
    run = run_policy(source, estimator, "sweep", ActiveConfig(budget=8, confidence=1e-6))
    last = run.steps[-1]
    assert run.stopped == "confident" and len(run.steps) < 3
    assert last.estimates and all(e.confidence >= 1e-6 for e in last.estimates)


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
