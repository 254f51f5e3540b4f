"""The learned front end: voting, the ONNX model and its card, bad input, a training smoke test."""

import json
import shutil

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from posefuse.estimator.errors import PosefuseError
from posefuse.estimator.frontend.network import ModelError, NetworkFrontend, load_card
from posefuse.estimator.frontend.voting import (
    VotingConfig,
    _least_squares_center,
    _percentile_90,
    vote_instances,
)


def _field(centers, size=60, noise=0.0, seed=0):
    """Pixels of discs around each center with unit vectors pointing at it."""
    rng = np.random.default_rng(seed)
    pix, vec = [], []
    ys, xs = np.mgrid[0:size, 0:size]
    for c in centers:
        d = np.hypot(xs - c[0], ys - c[1])
        sel = (d < 8) & (d > 0.5)
        p = np.stack([xs[sel], ys[sel]], 1).astype(float)
        v = np.asarray(c)[None] - p
        v += rng.normal(0, noise, v.shape) * np.linalg.norm(v, axis=1, keepdims=True)
        pix.append(p)
        vec.append(v / np.linalg.norm(v, axis=1, keepdims=True))
    return np.concatenate(pix), np.concatenate(vec)


def test_voting_separates_instances_and_finds_centers():
    centers = [(15.3, 20.7), (40.2, 35.5), (22.0, 45.0)]
    pix, vec = _field(centers, noise=0.02)
    found = vote_instances(pix, vec, VotingConfig(), seed=1)
    assert len(found) == 3
    got = np.array(sorted(tuple(f.center) for f in found))
    np.testing.assert_allclose(got, sorted(centers), atol=0.3)
    for f in found:
        assert f.cov.shape == (2, 2) and np.all(np.linalg.eigvalsh(f.cov) > 0)
    again = vote_instances(pix, vec, VotingConfig(), seed=1)
    for a, b in zip(found, again, strict=True):
        np.testing.assert_array_equal(a.center, b.center)


def test_voting_ignores_too_few_pixels():
    pix, vec = _field([(10.0, 10.0)])
    assert vote_instances(pix[:10], vec[:10], VotingConfig(min_inliers=25), seed=0) == []


@pytest.fixture(scope="module")
def tiny_model(robi_catalog, tmp_path_factory):
    pytest.importorskip("torch", reason="the training smoke test needs the train extra")
    from posefuse.service.resources import DEFAULT_CATALOG
    from posefuse.sim.train import TrainConfig, train

    path = tmp_path_factory.mktemp("model") / "tiny.onnx"
    config = TrainConfig(
        n_scenes=1, views_per_scene=1, val_scenes=1, max_iterations=3, workers=1, batch=2
    )
    card = train(DEFAULT_CATALOG, path, config)
    assert card["training"]["iterations"] == 3
    return path


def test_training_smoke_export_reload_infer(tiny_model, robi_catalog):
    frontend = NetworkFrontend(tiny_model, robi_catalog)
    image = np.random.default_rng(0).integers(0, 255, (720, 1280, 3), dtype=np.uint8)
    out = frontend.infer(image)
    assert out.shape == (len(robi_catalog) + 3, 184, 320)
    dets = frontend.detect(image)
    assert isinstance(dets, list)
    card = load_card(tiny_model)
    assert [n for _, n in card.classes] == [m.name for m in robi_catalog.values()]


def test_bad_input_gives_one_clear_error(tiny_model, robi_catalog, tmp_path):
    frontend = NetworkFrontend(tiny_model, robi_catalog)
    with pytest.raises(ValueError, match="expects 1280x720 images, got 640x480"):
        frontend.detect(np.zeros((480, 640, 3), np.uint8))
    with pytest.raises(ValueError, match=r"expected \(H, W, 3\) RGB"):
        frontend.detect(np.zeros((720, 1280), np.uint8))
    with pytest.raises(ValueError, match="uint8"):
        frontend.detect(np.zeros((720, 1280, 3), np.float32))
    with pytest.raises(ModelError, match="model file not found"):
        NetworkFrontend(tmp_path / "missing.onnx", robi_catalog)
    # a model for another catalog
    other = tmp_path / "other.onnx"
    shutil.copy(tiny_model, other)
    card = json.loads(tiny_model.with_suffix(".json").read_text())
    card["classes"] = card["classes"][:2]
    other.with_suffix(".json").write_text(json.dumps(card))
    with pytest.raises(ModelError, match="retrain it with posefuse train"):
        NetworkFrontend(other, robi_catalog)
    assert issubclass(ModelError, PosefuseError)
    # a damaged model file
    (tmp_path / "bad.onnx").write_bytes(b"not an onnx file")
    (tmp_path / "bad.json").write_text(tiny_model.with_suffix(".json").read_text())
    with pytest.raises(ModelError, match="onnxruntime cannot load it"):
        NetworkFrontend(tmp_path / "bad.onnx", robi_catalog)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(0.0, 100.0), min_size=1, max_size=300))
def test_percentile_90_equals_numpys(values):
    x = np.array(values)
    assert _percentile_90(x) == pytest.approx(float(np.percentile(x, 90)), rel=1e-12, abs=1e-12)


def test_least_squares_center_equals_the_sum_of_projections():
    rng = np.random.default_rng(5)
    center = np.array([40.0, 25.0])
    p = rng.uniform(0, 80, (200, 2))
    v = center - p + rng.normal(0, 0.5, (200, 2))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    proj = np.eye(2)[None] - v[:, :, None] * v[:, None, :]  # (n, 2, 2) I - v v^T
    A = proj.sum(0)
    x = np.linalg.solve(A, np.einsum("nij,nj->i", proj, p))
    r = np.einsum("nij,nj->ni", proj, x - p)
    cov = (r * r).sum() / (len(p) - 2) * np.linalg.inv(A)
    got_x, got_cov = _least_squares_center(p, v)
    np.testing.assert_allclose(got_x, x, rtol=0, atol=1e-10)
    np.testing.assert_allclose(got_cov, cov, rtol=1e-10)
    assert np.linalg.norm(got_x - center) < 0.5
