"""The turn judge (estimator.verification.turns): a square plate with a small block near one
corner is 4-fold symmetric but for the block. The samples that tell its quarter turns apart are
the block's; rendered views above the plate pick the turn they show from a wrong start; views
from below, where the plate hides the block, judge nothing."""

from __future__ import annotations

from collections import namedtuple
from dataclasses import replace

import numpy as np
import pytest
import trimesh
from test_verification import _views as rendered_views

from posefuse.estimator.core.geometry import make_transform, rotation_angle, so3_exp
from posefuse.estimator.rotation.render import MATTE, METAL
from posefuse.estimator.verification.edge_maps import EdgeConfig
from posefuse.estimator.verification.turns import (
    TurnJudgeConfig,
    TurnScoreCache,
    distinct_edges,
    judge_turns,
)

EDGES = EdgeConfig()
JUDGE = TurnJudgeConfig()
Part = namedtuple("Part", "mesh diameter")
BLOCK_XY = np.array([0.025, 0.025])  # the block's centre on the plate's top face, metres
BLOCK_HALF = 0.005
QUARTERS = np.array([so3_exp(k * np.pi / 2 * np.array([0.0, 0.0, 1.0])) for k in (1, 2, 3)])


def _plate(with_block: bool = True) -> trimesh.Trimesh:
    """An 80 x 80 x 8 mm plate centred on the origin, and a 10 x 10 x 6 mm block on its top."""
    plate = trimesh.creation.box((0.08, 0.08, 0.008))
    if not with_block:
        return plate
    block = trimesh.creation.box((2 * BLOCK_HALF, 2 * BLOCK_HALF, 0.006))
    block.apply_translation([BLOCK_XY[0], BLOCK_XY[1], 0.004 + 0.003])
    return trimesh.util.concatenate([plate, block])


def _diameter(mesh: trimesh.Trimesh) -> float:
    v = mesh.vertices
    return float(np.max(np.linalg.norm(v[:, None] - v[None], axis=2)))


def _views(mesh, T_world_obj, eyes, material=METAL):
    """EdgeViews of the part alone (no floor: the views from below see its underside)."""
    return rendered_views(Part(mesh, _diameter(mesh)), T_world_obj, eyes, material, floor=False)


T_WORLD_OBJ = make_transform(so3_exp(np.array([0.15, -0.1, 0.4])), np.array([0.0, 0.0, 0.0]))
ABOVE = [(0.25, 0.1, 0.35), (-0.2, 0.2, 0.35), (0.05, -0.3, 0.3)]
BELOW = [(0.2, 0.1, -0.35), (-0.2, 0.15, -0.35), (0.05, -0.25, -0.3)]


def test_the_samples_that_tell_the_quarter_turns_apart_are_the_blocks():
    mesh = _plate()
    d = _diameter(mesh)
    distinct = distinct_edges(mesh, d, QUARTERS, EDGES, JUDGE)
    assert distinct is not None and len(distinct.points) >= 20
    off_block = np.abs(distinct.points[:, :2] - BLOCK_XY).max(axis=1)
    assert np.all(off_block <= BLOCK_HALF + 1e-6)
    assert np.all(distinct.points[:, 2] >= 0.004 - 1e-6)  # on the plate's top face or above
    # capped evenly, and none at all where the turns are symmetries of the part
    capped = distinct_edges(mesh, d, QUARTERS, EDGES, replace(JUDGE, max_distinct=10))
    assert len(capped.points) == 10
    assert distinct_edges(_plate(with_block=False), d, QUARTERS, EDGES, JUDGE) is None
    assert distinct_edges(mesh, d, np.zeros((0, 3, 3)), EDGES, JUDGE) is None


@pytest.mark.parametrize("wrong", [0, 1, 2])
def test_views_that_show_the_block_pick_the_turn_they_show(wrong):
    mesh = _plate()
    d = _diameter(mesh)
    distinct = distinct_edges(mesh, d, QUARTERS, EDGES, JUDGE)
    views = _views(mesh, T_WORLD_OBJ, ABOVE)
    R_true, t = T_WORLD_OBJ[:3, :3], T_WORLD_OBJ[:3, 3]
    # from the truth: kept, every turn ruled out
    kept = judge_turns(distinct, views, R_true, t, QUARTERS, EDGES, JUDGE)
    assert kept is not None and np.allclose(kept.turn, np.eye(3))
    assert kept.samples >= JUDGE.min_samples
    assert np.all(kept.odds < 0.05)
    # from a wrong quarter turn: the judge turns it back to the truth
    start = R_true @ QUARTERS[wrong].T
    judged = judge_turns(distinct, views, start, t, QUARTERS, EDGES, JUDGE)
    assert judged is not None
    assert rotation_angle(start @ judged.turn @ R_true.T) < 1e-6
    assert np.all(judged.odds < 0.05)
    # the alternatives are the other turns, of the winner: the start among them
    alternatives = np.einsum("ij,ajk->aik", start @ judged.turn, judged.alternatives)
    assert min(rotation_angle(a @ start.T) for a in alternatives) < 1e-6
    # one view shows fewer samples than min_samples (60) and judges nothing; with a lower
    # bar it judges alike, on weaker evidence than the three views'
    assert judge_turns(distinct, views[:1], R_true, t, QUARTERS, EDGES, JUDGE) is None
    lower = replace(JUDGE, min_samples=20)
    alone = judge_turns(distinct, views[:1], R_true, t, QUARTERS, EDGES, lower)
    assert alone is not None and np.allclose(alone.turn, np.eye(3))
    assert alone.samples < kept.samples and alone.odds.max() > kept.odds.max()


def test_views_from_where_the_block_is_hidden_judge_nothing():
    mesh = _plate()
    d = _diameter(mesh)
    distinct = distinct_edges(mesh, d, QUARTERS, EDGES, JUDGE)
    views = _views(mesh, T_WORLD_OBJ, BELOW)
    R_true, t = T_WORLD_OBJ[:3, :3], T_WORLD_OBJ[:3, 3]
    assert judge_turns(distinct, views, R_true, t, QUARTERS, EDGES, JUDGE) is None
    assert judge_turns(distinct, [], R_true, t, QUARTERS, EDGES, JUDGE) is None


@pytest.mark.parametrize(
    "field, value",
    [
        ("distinct_frac", 0.0),
        ("effective_share", 0.0),
        ("effective_share", 1.5),
        ("min_samples", 0),
    ],
)
def test_a_malformed_judge_setting_is_refused(field, value):
    with pytest.raises(ValueError, match="turn judge"):
        TurnJudgeConfig(**{field: value})


def test_a_matte_part_is_judged_alike():
    """The judge reads the image's edges, whatever the material shows of them."""
    mesh = _plate()
    d = _diameter(mesh)
    distinct = distinct_edges(mesh, d, QUARTERS, EDGES, JUDGE)
    views = _views(mesh, T_WORLD_OBJ, ABOVE, MATTE)
    center = T_WORLD_OBJ[:3, 3]
    start = T_WORLD_OBJ[:3, :3] @ QUARTERS[1].T
    judged = judge_turns(distinct, views, start, center, QUARTERS, EDGES, JUDGE)
    assert judged is not None
    assert rotation_angle(start @ judged.turn @ T_WORLD_OBJ[:3, :3].T) < 1e-6


def test_the_views_sums_kept_for_the_same_pose_give_the_same_judgement():
    """A settled track keeps its pose as views come: the sums of the views already judged are
    reused, and the judgement is the one of scoring every view again, bit for bit; a new pose
    starts the cache again, and a view no longer kept leaves it."""
    mesh = _plate()
    d = _diameter(mesh)
    distinct = distinct_edges(mesh, d, QUARTERS, EDGES, JUDGE)
    eyes = [*ABOVE, (0.3, -0.1, 0.3)]
    views = [replace(v, stamp_ns=k + 1) for k, v in enumerate(_views(mesh, T_WORLD_OBJ, eyes))]
    start = T_WORLD_OBJ[:3, :3] @ QUARTERS[0].T
    t = T_WORLD_OBJ[:3, 3]
    cache = TurnScoreCache()
    judge_turns(distinct, views[:2], start, t, QUARTERS, EDGES, JUDGE, cache=cache)
    assert len(cache.entries) == 2
    kept = judge_turns(distinct, views, start, t, QUARTERS, EDGES, JUDGE, cache=cache)
    fresh = judge_turns(distinct, views, start, t, QUARTERS, EDGES, JUDGE)
    assert len(cache.entries) == 4
    assert np.array_equal(kept.turn, fresh.turn) and np.array_equal(kept.odds, fresh.odds)
    assert kept.samples == fresh.samples
    # another pose: scored again from nothing
    other = so3_exp(np.array([0.0, 0.02, 0.0])) @ start
    moved = judge_turns(distinct, views[1:], other, t, QUARTERS, EDGES, JUDGE, cache=cache)
    again = judge_turns(distinct, views[1:], other, t, QUARTERS, EDGES, JUDGE)
    assert len(cache.entries) == 3 and np.array_equal(cache.R_world_obj, other)
    assert np.array_equal(moved.odds, again.odds) and moved.samples == again.samples


def test_a_turn_that_shows_too_few_samples_never_wins_and_stays_open():
    """A candidate seen in fewer than min_samples samples may fit best by chance: it is no
    winner, and its odds against the winner are 1 (nothing rules it out)."""
    from posefuse.estimator.verification.turns import _key

    mesh = _plate()
    d = _diameter(mesh)
    distinct = distinct_edges(mesh, d, QUARTERS, EDGES, JUDGE)
    view = _views(mesh, T_WORLD_OBJ, ABOVE[:1])[0]
    R, t = T_WORLD_OBJ[:3, :3], T_WORLD_OBJ[:3, 3]
    cache = TurnScoreCache()
    judge_turns(distinct, [view], R, t, QUARTERS, EDGES, JUDGE, cache=cache)
    n = np.array([100.0, 3.0, 100.0, 100.0])  # the pose, then the three quarter turns
    mean = np.array([2.0, 0.1, 5.0, 6.0])  # the second fits best, on three samples
    cache.entries[_key(view)] = np.stack([n, n * mean, n * (mean**2 + 1.0)])
    judged = judge_turns(distinct, [view], R, t, QUARTERS, EDGES, JUDGE, cache=cache)
    assert np.array_equal(judged.turn, np.eye(3)) and judged.samples == 100
    # the alternatives are the turns in order: the quarter turn seen three times first
    assert np.allclose(judged.alternatives, QUARTERS)
    assert judged.odds[0] == 1.0 and np.all(judged.odds[1:] < 1.0)


def _collared_rod():
    """A rod along x (80 mm, radius 10 mm) with a collar at each end, one of radius 16 mm and
    one of 13 mm: turned end over end it is almost, not quite, itself (a tee's two ends)."""
    from posefuse.estimator.core.objects import make_model
    from posefuse.estimator.core.symmetry import ContinuousSymmetry

    body = trimesh.creation.cylinder(radius=0.01, height=0.08, sections=48)
    parts = [body]
    for radius, z in ((0.016, 0.034), (0.013, -0.034)):
        collar = trimesh.creation.cylinder(radius=radius, height=0.006, sections=48)
        collar.apply_translation([0.0, 0.0, z])
        parts.append(collar)
    mesh = trimesh.util.concatenate(parts)
    mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
    x = ContinuousSymmetry((1.0, 0.0, 0.0))
    return make_model(1, "collared_rod", mesh, np.zeros((0, 4, 4)), (x,), detect=False)


def test_how_far_a_turn_moves_the_surface():
    from posefuse.estimator.verification.turns import surface_moves

    model = _collared_rod()
    about_x = so3_exp(np.array([0.7, 0.0, 0.0]))  # the rod's own symmetry
    end_over_end = so3_exp(np.pi * np.array([0.0, 1.0, 0.0]))
    turns = np.stack([np.eye(3), about_x, end_over_end])
    moves = surface_moves(model.points, model.diameter, turns)
    assert moves[0] < 1e-12
    # a symmetry moves it by the samples' spacing (about 2 mm), end over end by the collars' 3 mm
    assert moves[1] < 0.03 < 0.05 < moves[2] < 0.1


def test_the_verifications_near_variants_are_judged_as_turns_from_variants_frac():
    """``TurnJudgeConfig.variants_frac``: the verification's own variant that moves the part's
    surface by no more than it (the rod turned end over end) is judged by the edges that tell
    the two ends apart, beside the catalog's near-symmetric turns; 0 or a share below its move
    (0.06 here) leaves the judge as it was."""
    from posefuse.estimator.core.objects import Catalog
    from posefuse.estimator.tracker import TrackerConfig
    from posefuse.estimator.tracker.pose_stage import PoseStage

    model = _collared_rod()
    for frac, judged in ((0.0, False), (0.06, False), (0.08, True)):
        config = TrackerConfig().with_verification_settings({"turns.variants_frac": frac})
        stage = PoseStage(Catalog([model]), config)
        _, variants = stage.model_edges(1)
        assert len(variants) == 1  # end over end (the turns about x are symmetries)
        if not judged:
            assert len(stage.unasked[1]) == 0 and stage.distinct[1] is None
            continue
        np.testing.assert_allclose(stage.unasked[1], variants)
        distinct = stage.distinct[1]
        assert distinct is not None and len(distinct.points) > 20
        # the samples that tell the ends apart are the collars'
        assert np.all(np.abs(distinct.points[:, 0]) > 0.025)
    with pytest.raises(ValueError, match="turns"):
        TrackerConfig().with_verification_settings({"turns.variants_frac": -0.1})


def test_of_the_shipped_catalog_only_the_chrome_screws_flip_is_judged():
    """Of the shipped catalog's variants only the chrome screw's half turn end over end (0.082
    d) moves its surface by 0.1 d or less: its turn judge asks that flip beside what it asked
    before ``variants_frac``, and nothing else of the catalog changes."""
    from posefuse.estimator.core.objects import load_catalog
    from posefuse.estimator.tracker import TrackerConfig
    from posefuse.estimator.tracker.pose_stage import PoseStage
    from posefuse.service.resources import DEFAULT_CATALOG

    catalog = load_catalog(DEFAULT_CATALOG)
    now = PoseStage(catalog, TrackerConfig())
    before = PoseStage(
        catalog, TrackerConfig().with_verification_settings({"turns.variants_frac": 0})
    )
    assert TrackerConfig().verification.turns.variants_frac == 0.1
    changed = []
    for obj_id in catalog:
        _, variants = now.model_edges(obj_id)
        before.model_edges(obj_id)
        if not np.array_equal(now.unasked[obj_id], before.unasked[obj_id]):
            changed.append(catalog[obj_id].name)
            # the flip is judged beside the turns asked before
            np.testing.assert_array_equal(now.unasked[obj_id][:-1], before.unasked[obj_id])
            flip = now.unasked[obj_id][-1]
            assert any(np.allclose(flip, v) for v in variants)
            assert np.degrees(np.arccos(np.clip((np.trace(flip) - 1) / 2, -1, 1))) > 179
    assert changed == ["chrome_screw"]
