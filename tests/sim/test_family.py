"""The procedural part family: seeded, sound solids of every kind in real parts' sizes; a
generalist trained on it says "a part" for any catalog; onboarding starts every class from it."""

from __future__ import annotations

import json

import numpy as np
import pytest

from posefuse.estimator.core.objects import Catalog
from posefuse.sim.family import KINDS, family_models, family_shape, family_shapes
from posefuse.sim.materials import random_material
from posefuse.sim.parts import PARTS
from posefuse.sim.train_data import RenderSpec


def test_a_shape_is_a_function_of_its_seed_and_index_alone():
    name_a, a = family_shape(7, 3)
    name_b, b = family_shape(7, 3)
    _, c = family_shape(8, 3)
    assert name_a == name_b == "bracket_7_0003"
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.faces, b.faces)
    assert a.vertices.shape != c.vertices.shape or not np.allclose(a.vertices, c.vertices)
    # a family's first shapes are those of any larger family of the same seed
    small = family_shapes(12, 7, with_catalog_parts=False)
    assert small[3][0] == name_a and np.array_equal(small[3][1].vertices, a.vertices)


def test_every_kind_gives_watertight_centred_solids_in_real_parts_sizes():
    shapes = family_shapes(3 * len(KINDS), seed=11, with_catalog_parts=False)
    kinds = {name.split("_")[0] for name, _ in shapes}
    assert kinds == {k for k, _ in KINDS}
    for name, mesh in shapes:
        assert mesh.is_watertight, name
        assert 19.9 <= mesh.extents.max() <= 130.1, (name, mesh.extents)
        lo, hi = mesh.bounds
        assert np.allclose((lo + hi) / 2, 0, atol=1e-6), name
        assert mesh.volume > 0, name


def test_a_larger_family_scales_some_shapes_up_and_leaves_the_others_as_they_were():
    count = 30
    default = family_shapes(count, seed=11, with_catalog_parts=False)
    large = family_shapes(count, seed=11, with_catalog_parts=False, max_mm=200.0)
    scaled = 0
    for (name, a), (name_b, b) in zip(default, large, strict=True):
        assert name == name_b and b.is_watertight
        ratio = b.extents.max() / a.extents.max()
        if np.isclose(ratio, 1.0):
            assert np.array_equal(a.vertices, b.vertices), name
        else:
            scaled += 1
            assert 130.0 - 1e-6 <= b.extents.max() <= 200.0 + 1e-6, (name, b.extents)
            assert np.allclose(b.vertices / ratio, a.vertices), name  # the same shape, larger
    assert 3 <= scaled <= 18  # LARGE_SHARE of 30, give or take the draw
    with pytest.raises(ValueError, match="max_mm"):
        family_shapes(1, seed=11, max_mm=100.0)


def test_the_five_catalog_parts_stay_in_the_family_and_models_are_in_metres():
    models = family_models(7, seed=3)
    assert [m.name for m in models[:5]] == [n for n, _ in PARTS]
    assert [m.obj_id for m in models] == list(range(1, 8))
    for m in models:
        assert 0.019 < m.mesh.extents.max() < 0.131
        assert len(m.symmetries_discrete) == 0 and not m.symmetries_continuous
    with pytest.raises(ValueError, match="at least 1"):
        family_shapes(0, seed=3)


def test_random_materials_span_matte_to_mirror_and_repeat_with_their_seed():
    draws = [random_material(np.random.default_rng([5, k])) for k in range(200)]
    again = [random_material(np.random.default_rng([5, k])) for k in range(200)]
    assert draws == again
    reflect = np.array([m.reflect for m in draws])
    assert reflect.min() == 0.0 and reflect.max() > 0.7
    for m in draws:
        assert all(0.0 <= c <= 1.0 for c in m.color)
        assert 0 < m.diffuse <= 1 and m.shininess > 0


def test_a_training_set_of_catalog_materials_keeps_its_name_and_random_ones_get_their_own():
    spec = RenderSpec(10, 4, 7_000_000)
    assert spec.key() == "s10_v4_b7000000_r0.5_x0.5"
    assert RenderSpec(10, 4, 7_000_000, materials="random").key().endswith("_mrandom")
    with pytest.raises(ValueError, match="materials"):
        RenderSpec(10, 4, 7_000_000, materials="gold")


def test_a_generalist_says_a_part_for_any_catalog_and_onboarding_starts_every_class_from_it(
    tmp_path,
):
    torch = pytest.importorskip("torch")
    from posefuse.estimator.core.objects import write_catalog
    from posefuse.estimator.frontend.network import AGNOSTIC_CLASSES, NetworkFrontend
    from posefuse.service.resources import DEFAULT_CATALOG
    from posefuse.sim.train import TrainConfig, _Nets, train

    family_dir = write_catalog(tmp_path / "family", Catalog(family_models(8, seed=4)))
    config = TrainConfig(
        n_scenes=1,
        views_per_scene=1,
        val_scenes=1,
        minutes=1e6,
        max_iterations=3,
        warmup=1,
        batch=2,
        crop_batch=4,
        workers=1,
        data_dir=str(tmp_path / "data"),
        threads=1,
        agnostic=True,
        materials="random",
    )
    card = train(family_dir, tmp_path / "g.onnx", config)
    assert card["agnostic"] is True
    assert card["classes"] == [{"obj_id": 0, "name": "part"}]
    assert any(p.name.endswith("_mrandom") for p in (tmp_path / "data").iterdir())
    # another catalog's parts are "a part" too: the card is not refused
    from posefuse.estimator.core.objects import load_catalog

    fe = NetworkFrontend(tmp_path / "g.onnx", load_catalog(DEFAULT_CATALOG))
    image = np.full((720, 1280, 3), 90, np.uint8)
    assert all(d.obj_id == AGNOSTIC_CLASSES[0][0] for d in fe.detect(image))
    state = torch.load(tmp_path / "g.ckpt", map_location="cpu", weights_only=False)
    assert state["config"]["agnostic"] is True
    assert state["nets"]["det"]["heatmap.weight"].shape[0] == 1
    # a part set's classes each start as the generalist's "a part"
    onboarded = _Nets(3, TrainConfig(threads=1))
    fresh = onboarded.init_from(state["nets"])
    assert fresh == [
        "heatmap.weight (every class from the generalist's one)",
        "heatmap.bias (every class from the generalist's one)",
    ]
    w = onboarded.det.heatmap.weight.detach()
    for c in range(3):
        assert torch.equal(w[c], state["nets"]["det"]["heatmap.weight"][0])
    assert json.loads((tmp_path / "g.json").read_text())["agnostic"] is True


def test_catalog_family_writes_the_shapes_and_their_picture_and_refuses_bad_counts(
    tmp_path, capsys
):
    import cv2

    from posefuse.cli.main import main
    from posefuse.estimator.core.objects import load_catalog

    out = tmp_path / "fam"
    assert main(["catalog", "--family", "7", "--family-seed", "3", "--out", str(out)]) == 0
    catalog = load_catalog(out)
    assert [catalog[k].name for k in sorted(catalog)][:5] == [n for n, _ in PARTS]
    assert catalog[7].name == "fastener_3_0001"
    picture = cv2.imread(str(out / "family.png"))
    assert picture is not None and picture.shape[0] > 100 and picture.std() > 5
    for argv, message in (
        (["--family", "0"], "--family: 0: must be at least 1"),
        (["--family", "3", "--mesh", "x.stl"], "--family and --mesh"),
        (["--family", "3", "--family-max-mm", "90"], "--family-max-mm: 90.0: must be in"),
    ):
        capsys.readouterr()
        assert main(["catalog", "--out", str(tmp_path / "bad"), *argv]) == 2
        assert message in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()  # refused before anything was written
