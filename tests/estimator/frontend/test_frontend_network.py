"""The learned front end: voting, the ONNX model and its card, the shipped model against a
rendered bin's truth, bad input, a training smoke test."""

import dataclasses
import json
import re
import shutil
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from posefuse.estimator.core.errors import PosefuseError
from posefuse.estimator.frontend.network import ModelError, NetworkFrontend, load_card, normalised
from posefuse.estimator.frontend.voting import (
    VotingConfig,
    _least_squares_center,
    _percentile_90,
    vote_instances,
)
from posefuse.estimator.tracker import TrackerConfig
from posefuse.evaluation.dataset import load_dataset
from posefuse.service.resources import DEFAULT_MODEL


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


def test_voting_takes_vectors_of_a_rounded_normalisation_as_unit_ones():
    """An int8 network's vectors are unit only to its rounding (lengths 0.9 to 1.1 were seen):
    the voting finds the same centres with a definite covariance; a float network's unit
    vectors are used as they are."""
    from posefuse.estimator.frontend.voting import _unit

    centers = [(15.3, 20.7), (40.2, 35.5)]
    pix, vec = _field(centers, noise=0.02)
    assert _unit(vec) is vec
    rounded = vec * np.random.default_rng(3).uniform(0.9, 1.1, (len(vec), 1))
    found = vote_instances(pix, rounded, VotingConfig(), seed=1)
    reference = vote_instances(pix, vec, VotingConfig(), seed=1)
    assert len(found) == len(reference) == 2
    for a, b in zip(found, reference, strict=True):
        np.testing.assert_allclose(a.center, b.center, atol=1e-9)
        assert np.all(np.linalg.eigvalsh(a.cov) > 0)


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
    assert card["training"]["steps"] == 3
    return path


def _well_formed(dets, image_hw, catalog):
    for d in dets:
        assert d.obj_id in catalog
        assert np.all(np.isfinite(d.center_uv)) and np.all(np.linalg.eigvalsh(d.center_cov) > 0)
        assert d.mask is None or d.mask.shape == image_hw
        assert 0.0 <= d.score <= 1.0


def test_training_smoke_export_reload_infer(tiny_model, robi_catalog):
    """Three steps of training export a model the front end loads and runs (what it finds after
    three steps is noise: the shipped model's accuracy is checked below)."""
    frontend = NetworkFrontend(tiny_model, robi_catalog)
    card = load_card(tiny_model)
    assert [n for _, n in card.classes] == [m.name for m in robi_catalog.values()]
    image = np.random.default_rng(0).integers(0, 255, (720, 1280, 3), dtype=np.uint8)
    out = frontend.infer(image)
    extra = 4 if card.kind == "two_stage" else 3  # box size and offset / unit vectors
    assert out.shape[0] == len(robi_catalog) + extra and np.all(np.isfinite(out))
    _well_formed(frontend.detect(image), (720, 1280), robi_catalog)


def _projected_origin(camera, T_cam_obj):
    p = camera.K @ T_cam_obj[:3, 3]
    return p[:2] / p[2]


def test_shipped_model_finds_the_visible_parts_where_they_are(full_res_dataset, robi_catalog):
    """On a rendered mixed bin (4 views, 6-8 parts): of the parts more than 75% visible, a
    floor share has a detection of its class within 5 px of its projected origin, and a floor
    share of the detections lies within 5 px of a part of their class. Measured with the shipped
    model: recall 0.87 (20 of 23), precision 0.84. Centers shifted by 6 px score 0.26 / 0.24,
    classes swapped or random centers 0 / 0."""
    dataset = load_dataset(full_res_dataset)
    frontend = NetworkFrontend(DEFAULT_MODEL, robi_catalog)
    n_parts = found = n_dets = near = 0
    for view in dataset.views():
        image = dataset.scene(view.scene_id).load_rgb(view.im_id)
        dets = frontend.detect(image)
        _well_formed(dets, image.shape[:2], robi_catalog)
        parts = [
            (g.obj_id, _projected_origin(view.camera, g.T_cam_obj), g.visib_fract)
            for g in view.gts
            if g.T_cam_obj[2, 3] > 0
        ]
        n_dets += len(dets)
        near += sum(
            any(o == d.obj_id and np.linalg.norm(d.center_uv - uv) <= 5.0 for o, uv, _ in parts)
            for d in dets
        )
        for obj_id, uv, visib in parts:
            if visib > 0.75:
                n_parts += 1
                found += any(
                    d.obj_id == obj_id and np.linalg.norm(d.center_uv - uv) <= 5.0 for d in dets
                )
    assert n_parts >= 20
    assert found / n_parts >= 0.6, f"{found} of {n_parts} visible parts found within 5 px"
    assert near / n_dets >= 0.6, f"{near} of {n_dets} detections within 5 px of a part"


@settings(max_examples=30, deadline=None)
@given(
    n=st.integers(0, 3),
    h=st.integers(1, 9),
    w=st.integers(1, 9),
    seed=st.integers(0, 2**31 - 1),
    mean=st.lists(st.floats(0.0, 1.0, width=32), min_size=3, max_size=3),
    std=st.lists(st.floats(0.0625, 1.0, width=32), min_size=3, max_size=3),
)
def test_the_networks_input_is_the_whole_array_expression_to_the_bit(n, h, w, seed, mean, std):
    """``normalised`` writes each channel in place; its bits are those of ``(x / 255 - mean) /
    std`` on the whole float32 array, transposed to planes (what the networks were fed before),
    so the detections do not move."""
    images = np.random.default_rng(seed).integers(0, 256, (n, h, w, 3), dtype=np.uint8)
    expected = (images.astype(np.float32) / 255.0 - np.float32(mean)) / np.float32(std)
    got = normalised(images, mean, std)
    assert got.shape == (n, 3, h, w) and got.dtype == np.float32 and got.flags.c_contiguous
    assert np.array_equal(got, expected.transpose(0, 3, 1, 2))
    # a strided view (a crop's rows reversed) is read as its values, not its memory
    flipped = normalised(images[:, ::-1], mean, std)
    assert np.array_equal(flipped, expected[:, ::-1].transpose(0, 3, 1, 2))


def test_the_networks_input_must_be_rgb_bytes():
    with pytest.raises(ValueError, match="uint8"):
        normalised(np.zeros((1, 4, 4, 4), np.uint8), (0.5,) * 3, (0.2,) * 3)
    with pytest.raises(ValueError, match="uint8"):
        normalised(np.zeros((1, 4, 4, 3), np.float32), (0.5,) * 3, (0.2,) * 3)


def test_sleeping_threads_find_what_spinning_ones_find(full_res_dataset, robi_catalog):
    """``spin=False`` (the default) tells onnxruntime's pools to sleep after a run; the
    detections are those of spinning pools, to the bit."""
    dataset = load_dataset(full_res_dataset)
    view = next(iter(dataset.views()))
    image = dataset.scene(view.scene_id).load_rgb(view.im_id)
    spinning = NetworkFrontend(DEFAULT_MODEL, robi_catalog, spin=True)
    sleeping = NetworkFrontend(DEFAULT_MODEL, robi_catalog)
    key = "session.intra_op.allow_spinning"
    for session in (sleeping.session, sleeping.crop_session):
        assert session.get_session_options().get_session_config_entry(key) == "0"
    a = spinning.detect(image)
    b = sleeping.detect(image)
    assert len(a) == len(b) > 0
    for x, y in zip(a, b, strict=True):
        assert x.obj_id == y.obj_id and x.score == y.score
        assert np.array_equal(x.center_uv, y.center_uv)
        assert np.array_equal(x.center_cov, y.center_cov)


def _same_detections(a, b) -> bool:
    return len(a) == len(b) and all(
        x.obj_id == y.obj_id
        and x.score == y.score
        and np.array_equal(x.center_uv, y.center_uv)
        and np.array_equal(x.mask, y.mask)
        for x, y in zip(a, b, strict=True)
    )


def test_a_vote_its_crop_is_centred_on_is_not_cropped_again(full_res_dataset, robi_catalog):
    """``refine_min_offset``: the refinement pass cuts a second crop only around votes at least
    that share of their crop's side from its center. At 0 every vote is cut again (the card's
    behaviour before the setting); beyond any offset none is, which is no refinement pass at
    all, to the bit; in between, fewer crops."""
    from posefuse.estimator.frontend.network import image_seed

    dataset = load_dataset(full_res_dataset)
    views = list(dataset.views())[:2]
    images = [dataset.scene(v.scene_id).load_rgb(v.im_id) for v in views]
    frontend = NetworkFrontend(DEFAULT_MODEL, robi_catalog)
    crops = []
    run = frontend.crop_infer
    frontend.crop_infer = lambda x, masks=None: crops.append(len(x)) or run(x, masks)
    base = frontend.two_stage
    assert base.refine_passes == 1

    def detect(**kw):
        frontend.two_stage = dataclasses.replace(base, **kw)
        crops.clear()
        dets = [frontend.detect(image) for image in images]
        return dets, sum(crops)

    every, n_every = detect(refine_min_offset=0.0)
    # at 0, the votes the refinement pass had before the setting: every kept vote cut again,
    # in order, on the same random stream
    from posefuse.estimator.frontend import network
    from posefuse.estimator.frontend.two_stage import Box

    drawn = []
    draw = network.detection_of
    network.detection_of = lambda v, *a: drawn.append(v) or draw(v, *a)
    try:
        detect(refine_min_offset=0.0)
    finally:
        network.detection_of = draw
    frontend.two_stage = base
    want = []
    for image in images:
        rng = np.random.default_rng([frontend.seed, image_seed(image)])
        boxes = frontend.boxes(image)
        votes = frontend.stage_two_votes(image, boxes, rng)
        kept = [(b, v) for b, v in zip(boxes, votes, strict=True) if v is not None]
        again = frontend.stage_two_votes(
            image, [Box(b.class_index, v.center, b.size, b.score) for b, v in kept], rng
        )
        want += [a if a is not None else v for a, (_, v) in zip(again, kept, strict=True)]
    assert len(drawn) == len(want) > 0
    assert all(np.array_equal(d.center, w.center) for d, w in zip(drawn, want, strict=True))
    none, n_none = detect(refine_min_offset=10.0)
    unrefined, n_unrefined = detect(refine_passes=0)
    some, n_some = detect(refine_min_offset=0.05)
    assert all(_same_detections(a, b) for a, b in zip(none, unrefined, strict=True))
    assert n_none == n_unrefined < n_some < n_every
    assert sum(map(len, every)) > 0 and not all(
        _same_detections(a, b) for a, b in zip(every, unrefined, strict=True)
    )


def test_bad_input_gives_one_clear_error(robi_catalog, tmp_path):
    """The shipped model (no torch needed): wrong images, a missing, foreign or damaged model."""
    model = Path(DEFAULT_MODEL)
    frontend = NetworkFrontend(model, robi_catalog)
    if frontend.card.kind == "two_stage":  # any image size but a tiny one
        with pytest.raises(ValueError, match="16x20 is smaller than 32 px"):
            frontend.detect(np.zeros((20, 16, 3), np.uint8))
    else:
        with pytest.raises(ValueError, match="expects 1280x720 images, got 640x480"):
            frontend.detect(np.zeros((480, 640, 3), np.uint8))
    with pytest.raises(ValueError, match=r"expected \(H, W, 3\) RGB"):
        frontend.detect(np.zeros((720, 1280), np.uint8))
    with pytest.raises(ValueError, match="uint8"):
        frontend.detect(np.zeros((720, 1280, 3), np.float32))
    with pytest.raises(ModelError, match="model file not found"):
        NetworkFrontend(tmp_path / "missing.onnx", robi_catalog)
    card = json.loads(model.with_suffix(".json").read_text())
    # a model for another catalog
    other = tmp_path / "other.onnx"
    shutil.copy(model, other)
    other.with_suffix(".json").write_text(json.dumps({**card, "classes": card["classes"][:2]}))
    with pytest.raises(ModelError, match="retrain it with posefuse train"):
        NetworkFrontend(other, robi_catalog)
    assert issubclass(ModelError, PosefuseError)
    # a two-stage card whose crop model is not beside it
    lone = tmp_path / "lone.onnx"
    shutil.copy(model, lone)
    two_stage = {**card, "kind": "two_stage", "two_stage": {"crop_model": "lone_crop.onnx"}}
    lone.with_suffix(".json").write_text(json.dumps(two_stage))
    with pytest.raises(ModelError, match="crop model of this two-stage card is missing"):
        NetworkFrontend(lone, robi_catalog)
    # a malformed card
    (tmp_path / "mal.onnx").write_bytes(model.read_bytes())
    malformed = {k: v for k, v in card.items() if k != "classes"}
    (tmp_path / "mal.json").write_text(json.dumps(malformed))
    with pytest.raises(ModelError, match="model card is malformed"):
        NetworkFrontend(tmp_path / "mal.onnx", robi_catalog)
    # a damaged model file
    (tmp_path / "bad.onnx").write_bytes(b"not an onnx file")
    (tmp_path / "bad.json").write_text(model.with_suffix(".json").read_text())
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


def test_the_daemons_detections_are_a_function_of_the_pixels_alone(full_res_dataset, robi_catalog):
    """The daemon's detector (``service.worker.make_detector``) gives one frame the same
    detections, to the bit, whatever its stamp, and the same as ``detect`` with the image's
    own seed (what ``run-dataset`` calls); a seed is a function of every pixel."""
    from posefuse.estimator.frontend.network import image_seed
    from posefuse.service.settings import Settings
    from posefuse.service.worker import make_detector

    dataset = load_dataset(full_res_dataset)
    view = next(iter(dataset.views()))
    image = dataset.scene(view.scene_id).load_rgb(view.im_id)
    detect = make_detector(Settings(model=DEFAULT_MODEL), robi_catalog)
    by_stamp = [detect(image.copy(), stamp) for stamp in (0, 1_764_800_000_000_000_000)]
    offline = NetworkFrontend(DEFAULT_MODEL, robi_catalog).detect(image)
    assert len(offline) > 0
    for dets in by_stamp:
        assert [d.obj_id for d in dets] == [d.obj_id for d in offline]
        for x, y in zip(dets, offline, strict=True):
            assert np.array_equal(x.center_uv, y.center_uv)
            assert np.array_equal(x.center_cov, y.center_cov) and x.score == y.score
    touched = image.copy()
    touched[-1, -1, 2] ^= 1
    assert image_seed(touched) != image_seed(image) == image_seed(image.copy())
    assert image_seed(image[:, :-1]) != image_seed(image)


def test_the_misses_by_stage_add_up_to_what_the_score_misses(full_res_dataset, robi_catalog):
    """bench.frontend_misses against score_frontend, which counts the same parts on its own:
    every part more than 75% visible gets exactly one fate, and "found" is the score's recall."""
    from posefuse.bench.frontend_misses import FATES, view_fates
    from posefuse.evaluation.frontend_metrics import score_frontend

    dataset = load_dataset(full_res_dataset)
    frontend = NetworkFrontend(DEFAULT_MODEL, robi_catalog)
    images = {v.im_id: dataset.scene(v.scene_id).load_rgb(v.im_id) for v in dataset.views()}

    fates = []
    for view in dataset.views():
        fates += view_fates(frontend, images[view.im_id], view)[0]
    score = score_frontend(
        dataset,
        lambda v: frontend.detect(images[v.im_id]),
        list(dataset.views()),
    )
    assert set(fates) <= set(FATES)
    assert len(fates) == score.n_instances
    assert fates.count("found") == round(score.recall * score.n_instances)
    # scored class by class, the parts, the detections and the found add up to the whole
    detections = {v.im_id: frontend.detect(images[v.im_id]) for v in dataset.views()}
    per_class = [
        score_frontend(dataset, lambda v: detections[v.im_id], list(dataset.views()), obj_id=k)
        for k in sorted({g.obj_id for v in dataset.views() for g in v.gts})
    ]
    assert len(per_class) >= 2
    assert sum(c.n_instances for c in per_class) == score.n_instances
    assert sum(c.n_detections for c in per_class) == score.n_detections
    found = sum(round(c.recall * c.n_instances) for c in per_class if c.n_instances)
    assert found == fates.count("found")
    with pytest.raises(ValueError, match="one class"):
        score_frontend(dataset, lambda v: [], [], any_class=True, obj_id=1)


def test_stage_two_on_each_parts_own_box_places_the_parts_of_the_shipped_model(
    full_res_dataset, robi_catalog, capsys
):
    """bench.frontend_misses --true-boxes: one row per part more than 75% visible, in the
    fates' order; handed the true boxes, the shipped model places its own parts within 15 px,
    and the command prints the table by part type."""
    from posefuse.bench.frontend_misses import main, true_box_errors, view_fates

    dataset = load_dataset(full_res_dataset)
    frontend = NetworkFrontend(DEFAULT_MODEL, robi_catalog)
    rows, fates, moved = [], [], []
    for view in dataset.views():
        image = dataset.scene(view.scene_id).load_rgb(view.im_id)
        view_rows = true_box_errors(frontend, image, view)
        view_fate_rows = view_fates(frontend, image, view)[2]
        assert [r.obj_id for r in view_rows] == [r.obj_id for r in view_fate_rows]
        rows += view_rows
        fates += view_fate_rows
        moved += true_box_errors(frontend, image, view, offset=0.35, size_factor=0.8)
    assert len(rows) >= 5
    within = [r.error is not None and r.error <= 15.0 for r in rows]
    assert np.mean(within) >= 0.8
    # boxes moved well past the jitter stage two was trained with place fewer parts
    assert [r.obj_id for r in moved] == [r.obj_id for r in rows]
    assert np.mean([r.error is not None and r.error <= 15.0 for r in moved]) < np.mean(within)
    assert all(r.side_px == max(f.bbox_visib[2:]) for r, f in zip(rows, fates, strict=True))
    assert main(["--dataset", str(full_res_dataset), "--true-boxes", "--by-object"]) == 0
    printed = capsys.readouterr().out
    table = printed[printed.index("stage two on each part's own box") :]
    assert f"| all | {len(rows)} |" in table
    for obj_id in {r.obj_id for r in rows}:
        assert f"| {robi_catalog[obj_id].name} |" in table


def test_a_part_stage_one_scored_below_its_threshold_is_told_from_one_it_never_saw(
    full_res_dataset, robi_catalog
):
    """With stage one's threshold raised from the card's to 0.9, parts move to "a peak below
    the threshold", and a part with no peak at the card's threshold has none at 0.9 either;
    each part's row names its class; the picture draws both fates."""
    from posefuse.bench.frontend_misses import (
        FATE_COLOURS,
        LEGEND_WIDTH,
        fate_picture,
        view_fates,
    )

    dataset = load_dataset(full_res_dataset)
    card_threshold = NetworkFrontend(DEFAULT_MODEL, robi_catalog)
    strict = NetworkFrontend(DEFAULT_MODEL, robi_catalog)
    strict.two_stage = dataclasses.replace(strict.two_stage, min_score=0.9)
    at_card, at_strict = [], []
    for view in dataset.views():
        image = dataset.scene(view.scene_id).load_rgb(view.im_id)
        rows = view_fates(card_threshold, image, view)[2]
        assert [r.obj_id for r in rows] == [g.obj_id for g in view.gts if g.visib_fract > 0.75]
        at_card += [r.fate for r in rows]
        at_strict += [r.fate for r in view_fates(strict, image, view)[2]]
    below = "a peak below the threshold"
    assert at_strict.count(below) > at_card.count(below)
    picture = fate_picture(strict, image, view)  # the last view's, right of a legend
    assert picture.dtype == np.uint8 and picture.ndim == 3 and picture.shape[2] == 3
    last = Counter(r.fate for r in view_fates(strict, image, view)[2])
    for fate in ("found", below):  # a box's outline in the fate's colour, where there is one
        drawn = np.all(picture[:, LEGEND_WIDTH:] == FATE_COLOURS[fate], axis=2).sum()
        assert (drawn > 100) == (last[fate] > 0)
    assert at_strict.count(below) >= 3
    assert all(b == "no box" for a, b in zip(at_card, at_strict, strict=True) if a == "no box")


def test_stage_two_where_parts_are_expected_finds_them_and_not_where_none_is(
    full_res_dataset, robi_catalog
):
    """``detect_at`` on a rendered mixed bin: crops centred 3 px off the parts more than 75%
    visible, with their true box side, give a detection of the class within 5 px of the part
    for most; crops on empty floor, two sides from any part, give almost none."""
    from posefuse.estimator.frontend.detection import ExpectedPart

    dataset = load_dataset(full_res_dataset)
    frontend = NetworkFrontend(DEFAULT_MODEL, robi_catalog)
    n_parts = found = n_empty = ghosts = 0
    rng = np.random.default_rng(0)
    for view in dataset.views():
        image = dataset.scene(view.scene_id).load_rgb(view.im_id)
        h, w = image.shape[:2]
        parts = [
            (g.obj_id, _projected_origin(view.camera, g.T_cam_obj), max(g.bbox_obj[2:]))
            for g in view.gts
            if g.T_cam_obj[2, 3] > 0 and g.visib_fract > 0.75
        ]
        expected = [
            ExpectedPart(f"p{k}", obj_id, uv + rng.normal(0, 3.0 / np.sqrt(2), 2), float(side))
            for k, (obj_id, uv, side) in enumerate(parts)
        ]
        dets = frontend.detect_at(image, expected)
        _well_formed(dets, image.shape[:2], robi_catalog)
        n_parts += len(parts)
        found += sum(
            any(d.obj_id == o and np.linalg.norm(d.center_uv - uv) <= 5.0 for d in dets)
            for o, uv, _ in parts
        )
        # empty floor: points two sides (of the largest part) from every part's centre
        side = max(s for _, _, s in parts) if parts else 100.0
        every = [_projected_origin(view.camera, g.T_cam_obj) for g in view.gts]
        empty = []
        for _ in range(200):
            uv = rng.uniform([side, side], [w - side, h - side])
            if all(np.linalg.norm(uv - c) > 2 * side for c in every):
                empty.append(ExpectedPart("none", parts[0][0] if parts else 1, uv, float(side)))
            if len(empty) == 5:
                break
        n_empty += len(empty)
        ghosts += len(frontend.detect_at(image, empty))
    assert n_parts >= 20 and n_empty >= 5
    assert found / n_parts >= 0.6, f"{found} of {n_parts} expected parts found within 5 px"
    assert ghosts <= 0.2 * n_empty, f"{ghosts} detections on {n_empty} crops of empty floor"


def _model_copy(tmp_path, **card_fields) -> Path:
    """The shipped model and its stage two copied into ``tmp_path``, its card changed."""
    model = Path(DEFAULT_MODEL)
    card = json.loads(model.with_suffix(".json").read_text())
    tmp_path.mkdir(parents=True, exist_ok=True)
    copy = tmp_path / model.name
    shutil.copy(model, copy)
    if card.get("two_stage", {}).get("crop_model"):
        shutil.copy(model.parent / card["two_stage"]["crop_model"], tmp_path)
    copy.with_suffix(".json").write_text(json.dumps({**card, **card_fields}))
    return copy


def test_each_class_is_found_at_its_own_scale(full_res_dataset, robi_catalog, tmp_path):
    """With ``class_scale_factors`` stage one runs once per factor, and each class's boxes are
    those of the run at its factor: the same boxes as a model whose one scale is that one."""
    card = json.loads(Path(DEFAULT_MODEL).with_suffix(".json").read_text())
    if card.get("kind") != "two_stage":
        pytest.skip("scales per class are stage one's, of a two-stage model")
    scale = card["input_scale"]
    factors = [0.75, 1.0, 0.75, 1.0, 0.75]
    mixed = NetworkFrontend(_model_copy(tmp_path / "a", class_scale_factors=factors), robi_catalog)
    other = NetworkFrontend(_model_copy(tmp_path / "b", input_scale=scale * 0.75), robi_catalog)
    full = NetworkFrontend(DEFAULT_MODEL, robi_catalog)
    assert mixed.card.class_scale_factors == tuple(factors)
    assert load_card(mixed.model_path).to_json()["class_scale_factors"] == factors
    dataset = load_dataset(full_res_dataset)
    compared = Counter()
    for view in list(dataset.views())[:3]:
        image = dataset.scene(view.scene_id).load_rgb(view.im_id)
        boxes = mixed.boxes(image)
        assert [b.score for b in boxes] == sorted((b.score for b in boxes), reverse=True)
        for k in range(5):
            own = other if factors[k] == 0.75 else full
            want = [b for b in own.boxes(image) if b.class_index == k]
            got = [b for b in boxes if b.class_index == k]
            assert len(got) == len(want)
            for g, w in zip(got, want, strict=True):
                assert np.allclose(g.center, w.center) and np.allclose(g.size, w.size)
            compared[factors[k]] += len(got)
    assert compared[1.0] > 0 and compared[0.75] > 0  # boxes at both scales were compared


@pytest.mark.parametrize(
    "factors, message", [([1.0, 0.5], "2 factors for 5 classes"), ([1, 1, 1, 1, 0], "(0, 1]")]
)
def test_a_card_with_wrong_scale_factors_is_refused(robi_catalog, tmp_path, factors, message):
    with pytest.raises(ModelError, match=re.escape(message)):
        NetworkFrontend(_model_copy(tmp_path, class_scale_factors=factors), robi_catalog)


@pytest.mark.parametrize("offset", [-0.5, float("nan")])
def test_a_card_with_a_wrong_refinement_offset_is_refused_naming_it(robi_catalog, tmp_path, offset):
    card = json.loads(Path(DEFAULT_MODEL).with_suffix(".json").read_text())
    two_stage = {**card["two_stage"], "refine_min_offset": offset}
    with pytest.raises(ModelError, match="refine_min_offset"):
        NetworkFrontend(_model_copy(tmp_path, two_stage=two_stage), robi_catalog)


def test_a_catalog_model_used_as_a_part_finds_each_part_once_as_obj_id_0(
    full_res_dataset, robi_catalog, tmp_path
):
    """``posefuse onboard --steps 0``'s model: the shipped model's card made a generalist's.
    Its detections are all "a part" (obj_id ``ANY_PART``), no more than the classes give
    however many class heatmaps peak on a part, and nearly every part the classes find is
    found as "a part" too (stage one takes the maximum over the heatmaps, so no peak is
    lost)."""
    from posefuse.estimator.frontend.detection import ANY_PART
    from posefuse.sim.onboard import write_any_part_model

    card = write_any_part_model(str(Path(DEFAULT_MODEL).with_suffix(".ckpt")), tmp_path / "p.onnx")
    assert card["agnostic"] is True and card["classes"] == [{"obj_id": ANY_PART, "name": "part"}]
    any_part = NetworkFrontend(tmp_path / "p.onnx", robi_catalog)  # any catalog: not refused
    shipped = NetworkFrontend(DEFAULT_MODEL, robi_catalog)
    dataset = load_dataset(full_res_dataset)
    n_shipped = matched = 0
    for view in list(dataset.views())[:3]:
        image = dataset.scene(view.scene_id).load_rgb(view.im_id)
        got = any_part.detect(image)
        _well_formed(got, image.shape[:2], {ANY_PART: None})
        assert got and all(d.obj_id == ANY_PART for d in got)
        want = shipped.detect(image)
        n_shipped += len(want)
        matched += sum(
            any(np.linalg.norm(g.center_uv - w.center_uv) <= 3.0 for g in got) for w in want
        )
        # a peak of the heatmaps' maximum is a peak of the class whose heatmap it is, and
        # the classes' duplicates are suppressed as one: never more than the classes find
        assert len(got) <= len(want), (len(got), len(want))
    assert n_shipped >= 10 and matched >= 0.9 * n_shipped, (matched, n_shipped)


def test_an_any_part_model_needs_a_two_stage_model_with_its_card(tmp_path):
    from posefuse.estimator.core.errors import PosefuseError
    from posefuse.sim.onboard import write_any_part_model

    with pytest.raises(PosefuseError, match="must both be there"):
        write_any_part_model(str(tmp_path / "none.ckpt"), tmp_path / "p.onnx")
    copy = _model_copy(tmp_path / "one", kind="center_voting")
    with pytest.raises(PosefuseError, match="not a two-stage model"):
        write_any_part_model(str(copy.with_suffix(".ckpt")), tmp_path / "p.onnx")


def test_a_cards_verification_settings_are_read_written_and_refused_when_they_cannot_be(
    robi_catalog, tmp_path
):
    """A card's ``verification`` (the settings its front end calls for): on the shipped card
    only the error its centres share across views, read and written back where a card has it,
    and refused naming the field where it names an unknown setting or a value that is not a
    finite number >= 0."""
    shipped = load_card(DEFAULT_MODEL)
    assert shipped.verification == {"translation_shared_frac": 0.01}
    assert TrackerConfig().with_card(shipped.verification).translation_shared_frac == 0.01
    settings = {"mask_weight": 0.5, "max_fit": 1.0, "refinement.floor_translation_frac": 0.02}
    card = load_card(_model_copy(tmp_path / "a", verification=settings))
    assert card.verification == settings and card.to_json()["verification"] == settings
    assert "verification" not in (card.extra or {})
    bad = [{"mask_weight": -1.0}, {"mask_weight": "heavy"}, {"mask_weight": float("nan")}]
    bad += [{"temperature": 0.1}, [0.5], {"refinement.damping": 0.1}]
    bad += [{"refinement.floor_rotation_deg": float("inf")}, {"translation_shared_frac": -0.01}]
    for k, values in enumerate(bad):
        with pytest.raises(ModelError, match="verification|could not convert"):
            load_card(_model_copy(tmp_path / f"bad{k}", verification=values))
