"""The challenge of a poorly fitting winner (VerificationConfig.challenge_cost, the pose stage's
_challenge): with the track's translation a tenth of the diameter off, a winner in the wrong
basin refines to a pose that still costs much; the best hypothesis of another basin, refined
too, leads where it costs plainly less, and a winner that fits is never displaced."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
from test_verification import _tube

from posefuse.estimator.core.geometry import rotation_angle, so3_exp
from posefuse.estimator.tracker.config import TrackerConfig
from posefuse.estimator.tracker.pose_stage import PoseStage
from posefuse.estimator.verification.refinement import (
    EdgeScoring,
    PoseGuess,
    PosePrior,
    refine_pose,
)
from posefuse.estimator.verification.verify import Verdict, reweight, score_hypotheses

_SCENE: dict = {}


def _scene(robi_catalog):
    """The tube in three views, its stage's edges and refinement settings, the truth, a flip
    that is not a symmetry, and a translation 0.12 d off (made once per process)."""
    if not _SCENE:
        model, T_world_obj, views = _tube(robi_catalog)
        obj_id = next(k for k, m in robi_catalog.items() if m is model)
        stage = PoseStage(robi_catalog, TrackerConfig())
        edges, _ = stage.model_edges(obj_id)
        R_true = T_world_obj[:3, :3]
        # half a turn about an axis across the tube's: plainly another basin
        R_flip = R_true @ so3_exp(np.pi * np.array([0.0, 0.6, 0.8]))
        t_off = T_world_obj[:3, 3] + 0.12 * model.diameter * np.array([0.0, 0.6, -0.8])
        _SCENE.update(
            model=model,
            obj_id=obj_id,
            views=views,
            edges=edges,
            rcfg=stage.refinement_config(obj_id),
            truth=T_world_obj,
            hyps=np.array([R_flip, so3_exp(np.deg2rad(8.0) * np.array([1.0, 0, 0])) @ R_true]),
            t_off=t_off,
        )
    return _SCENE


def _track(scene, best: int, config: TrackerConfig):
    """A track whose verification chose hypothesis ``best`` at the biased translation, and
    whose winner was refined as the pose stage refines it."""
    d = scene["model"].diameter
    cov_t = np.eye(3) * (0.02 * d) ** 2  # sure of its biased centre: the move is 6 sigma
    cov_R = np.eye(3) * np.deg2rad(20.0) ** 2
    cost = np.array([0.9, 1.0]) if best == 0 else np.array([1.0, 0.9])
    component = np.array([0, 1])
    weights = np.array([0.5, 0.5])
    verdict = Verdict(
        scene["hyps"],
        component,
        np.zeros(2, int),
        cost,
        np.repeat(cost[:, None], len(scene["views"]), axis=1),
        reweight(cost, component, weights, len(scene["views"]), 0.05),
        best,
    )
    refined = refine_pose(
        scene["edges"],
        scene["views"],
        PoseGuess(scene["hyps"][best], scene["t_off"]),
        PosePrior(scene["t_off"], cov_t, cov_R),
        EdgeScoring.of(config.verification),
        scene["rcfg"],
    )
    return SimpleNamespace(
        obj_id=scene["obj_id"],
        verdict=verdict,
        refined=refined,
        edge_views=scene["views"],
        estimate=SimpleNamespace(t_world_obj=scene["t_off"], cov=cov_t),
        mixture=SimpleNamespace(
            components=[SimpleNamespace(cov=cov_R), SimpleNamespace(cov=cov_R)], weights=weights
        ),
    )


def _challenged(robi_catalog, best: int, challenge_cost: float | None):
    scene = _scene(robi_catalog)
    base = TrackerConfig()
    config = dataclasses.replace(
        base,
        verification=dataclasses.replace(base.verification, challenge_cost=challenge_cost),
        # the cost's fall takes the move past the sure prior, as the tracker's default does
        refinement=dataclasses.replace(base.refinement, accept_cost_drop=0.35),
    )
    stage = PoseStage(robi_catalog, config)
    stage.model_edges(scene["obj_id"])
    scene = dict(scene, rcfg=stage.refinement_config(scene["obj_id"]))
    track = _track(scene, best, config)
    before = (track.verdict, track.refined)
    stage._challenge(track, scene["edges"], scene["rcfg"])
    return scene, track, before


def test_a_winner_in_the_wrong_basin_is_displaced_by_the_refined_challenger(robi_catalog):
    scene, track, (verdict0, refined0) = _challenged(robi_catalog, best=0, challenge_cost=0.6)
    truth = scene["truth"]
    assert track.verdict.best == 1
    assert track.refined is not refined0 and track.refined.accepted
    angle = np.rad2deg(rotation_angle(track.refined.R_world_obj @ truth[:3, :3].T))
    assert angle < 3.0
    moved_to = np.linalg.norm(track.refined.t_world_obj - truth[:3, 3])
    assert moved_to < 0.03 * scene["model"].diameter  # from 0.12 d
    # the two refined costs replace the verification's, and the weights follow them
    costs = score_hypotheses(
        scene["edges"],
        scene["views"],
        track.refined.R_world_obj[None],
        track.refined.t_world_obj,
        TrackerConfig().verification,
    )
    assert track.verdict.cost[1] == float(costs.mean())
    assert track.verdict.cost[1] < track.verdict.cost[0] - 0.05
    assert track.verdict.weights[1] > 0.99 > verdict0.weights[1]


def test_the_gate_and_a_winner_that_fits_leave_the_verdict_as_it_was(robi_catalog):
    # the wrong winner's refined pose costs less than a gate set above it: not challenged
    scene, track, (verdict0, refined0) = _challenged(robi_catalog, best=0, challenge_cost=None)
    assert track.verdict is verdict0 and track.refined is refined0
    wrong = track.refined
    cost_wrong = float(
        score_hypotheses(
            scene["edges"],
            scene["views"],
            wrong.R_world_obj[None] if wrong.accepted else scene["hyps"][:1],
            wrong.t_world_obj,
            TrackerConfig().verification,
        ).mean()
    )
    _, track, (verdict0, refined0) = _challenged(robi_catalog, 0, challenge_cost=cost_wrong + 0.01)
    assert track.verdict is verdict0 and track.refined is refined0
    # the right winner, challenged whatever its cost (gate 0): the flip costs more, it stays
    _, track, (verdict0, refined0) = _challenged(robi_catalog, best=1, challenge_cost=0.0)
    assert track.verdict is verdict0 and track.refined is refined0
