"""sim.composite: views composed from parts rendered alone, their labels exact."""

import numpy as np
import pytest
import trimesh

from posefuse.estimator.rotation.render import MATTE
from posefuse.sim.composite import ComposeSpec, Cutout, compose_view, part_cutout
from posefuse.sim.train_data import RenderSpec, is_composed, profile_of


def _disc(radius: int, class_index: int) -> Cutout:
    size = 2 * radius + 1
    yy, xx = np.mgrid[:size, :size]
    alpha = (xx - radius) ** 2 + (yy - radius) ** 2 <= radius**2
    rgb = np.zeros((size, size, 3), np.uint8)
    rgb[alpha] = (250, 20, 20)
    return Cutout(rgb, alpha, np.array([radius, radius], float), class_index)


def test_a_cutout_shows_its_part_around_the_projection_of_its_origin():
    box = trimesh.creation.box((0.06, 0.04, 0.02))  # centred on its origin
    cut = part_cutout(box, MATTE, 3, 924.0, np.random.default_rng(0), ComposeSpec())
    assert cut.class_index == 3 and cut.rgb.shape[:2] == cut.alpha.shape
    ys, xs = np.nonzero(cut.alpha)
    assert len(xs) > 100
    # a centred box's silhouette is centred on its origin's projection (to perspective's skew)
    assert np.allclose([xs.mean(), ys.mean()], cut.centre, atol=2.0)
    # and the crop holds all of it
    assert xs.min() > 0 and ys.min() > 0 and xs.max() < len(cut.alpha) - 1


def test_a_composed_views_rows_are_its_instance_maps():
    spec = ComposeSpec(mixed_parts=(6, 6), pile_parts=(15, 15), turn=False, scale_log=0.0)
    cutouts = [_disc(20, 1), _disc(30, 2)]
    for pile in (False, True):
        rgb, inst, rows = compose_view(cutouts, pile, 240, 320, np.random.default_rng(5), spec)
        assert rgb.shape == (240, 320, 3) and inst.shape == (240, 320)
        assert set(np.unique(inst)) - {0} == {int(k) + 1 for k in rows[:, 0]}
        for k, cls, u, v, x0, y0, x1, y1, visib, count in rows:
            ys, xs = np.nonzero(inst == k + 1)
            assert count == len(xs) and (x0, y0, x1, y1) == (
                xs.min(),
                ys.min(),
                xs.max() + 1,
                ys.max() + 1,
            )
            assert 0 < visib <= 1 and cls in (1, 2)
            if count == cutouts[int(cls) - 1].alpha.sum():  # a whole disc: centred on (u, v)
                assert np.allclose([xs.mean(), ys.mean()], [u, v], atol=0.5)
        if pile:  # heaped: some hide others
            assert (rows[:, 8] < 1).any()


def test_composed_scenes_are_interleaved_by_pairs_and_named_in_the_key():
    kinds = [(profile_of(k, 0.5), is_composed(k, 0.5)) for k in range(8)]
    assert kinds[:4] == [("mixed", False), ("robi", False), ("mixed", True), ("robi", True)]
    assert sum(c for _, c in kinds) == 4
    assert not any(is_composed(k, 0.0) for k in range(8))
    assert all(is_composed(k, 1.0) for k in range(8))
    assert RenderSpec(4, 2, 7).key() == "s4_v2_b7_r0.5_x0.5"  # sets rendered before: unchanged
    assert RenderSpec(4, 2, 7, composite=0.5).key().endswith("_c0.5")
    with pytest.raises(ValueError, match="composite"):
        RenderSpec(4, 2, 7, composite=1.5)


def test_a_composed_scene_repeats_from_its_seed():
    from posefuse.service.resources import DEFAULT_CATALOG
    from posefuse.sim.train_data import compose_scene

    a = compose_scene(str(DEFAULT_CATALOG), 3, 2, 11, "robi", 0.5)
    b = compose_scene(str(DEFAULT_CATALOG), 3, 2, 11, "robi", 0.5)
    assert len(a) == 2
    for (rgb, inst, small, rows), (rgb2, inst2, _small2, rows2) in zip(a, b, strict=True):
        assert np.array_equal(rgb, rgb2) and np.array_equal(inst, inst2)
        assert np.array_equal(rows, rows2) and small.shape == (368, 640, 3)
        assert len(set(rows[:, 1])) == 1  # a pile is of one part
