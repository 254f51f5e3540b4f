"""The two-stage front end's geometry: what training asks the networks for, decoded by the
front end's own code, gives back the truth (boxes, centers, masks), on a rendered view."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from posefuse.estimator.frontend.crops import box_mask, crop_transform, warp_crop
from posefuse.estimator.frontend.two_stage import (
    TwoStageConfig,
    box_masks,
    crop_boxes,
    decode_boxes,
    suppress_duplicates,
    vote_in_crop,
)
from posefuse.estimator.frontend.voting import VotingConfig
from posefuse.service.resources import DEFAULT_CATALOG
from posefuse.sim.train_data import render_scene
from posefuse.sim.train_targets import (
    BatchConfig,
    crop_batch,
    crop_targets,
    det_targets,
    dihedral_crop,
    flip_detector_sample,
)


@pytest.fixture(scope="module")
def view():
    """One robi-profile view: (rgb, instance map, small rgb, instance rows (K, 11))."""
    rgb, inst, small, rows = render_scene((str(DEFAULT_CATALOG), 3, 1, 123_456, "robi", 0.5))[0]
    rows = np.concatenate([np.zeros((len(rows), 1)), rows], 1)
    return rgb, inst, small, rows


def test_crop_transform_centres_the_crop_and_warp_reads_it():
    image = np.zeros((100, 120), np.uint8)
    image[40, 70] = 255  # one bright pixel
    a, b = crop_transform(np.array([70.0, 40.0]), side=20.0, size=40)
    crop = warp_crop(image, a, b, 40, 0)  # nearest
    ys, xs = np.nonzero(crop)
    # the crop's center pixels (19.5, 19.5) map to (70, 40): the bright pixel covers 2x2 there
    assert np.allclose([xs.mean(), ys.mean()], [19.5, 19.5], atol=0.6)
    assert np.allclose(a * np.array([19.5, 19.5]) + b, [70.0, 40.0])
    with pytest.raises(ValueError, match="positive"):
        crop_transform(np.zeros(2), 0.0, 40)
    with pytest.raises(ValueError, match="finite"):
        warp_crop(image, a, np.array([np.inf, 3.0]), 40, 0)


@pytest.mark.parametrize("center", [(2.0, 3.0), (118.0, 97.0), (-30.0, 50.0), (60.0, 140.0)])
def test_a_crop_over_the_images_border_repeats_the_border_as_a_copy_would(center):
    """Crops are cut from a view of the image (rows read by their stride): at and beyond the
    border the same pixels as from a contiguous copy of the region."""
    image = np.random.default_rng(0).integers(0, 255, (100, 120, 3), np.uint8)
    a, b = crop_transform(np.array(center), side=37.0, size=24)
    got = warp_crop(image, a, b, 24, 1)
    x0 = min(max(int(np.floor(b[0])) - 1, 0), 119)
    y0 = min(max(int(np.floor(b[1])) - 1, 0), 99)
    x1 = min(max(int(np.ceil(b[0] + a * 24)) + 2, x0 + 1), 120)
    y1 = min(max(int(np.ceil(b[1] + a * 24)) + 2, y0 + 1), 100)
    region = np.ascontiguousarray(image[y0:y1, x0:x1])
    M = np.array([[a, 0.0, b[0] - x0], [0.0, a, b[1] - y0]])
    want = cv2.warpAffine(
        region, M, (24, 24), flags=1 | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE
    )
    assert np.array_equal(got, want)


def test_detector_targets_decode_to_the_visible_boxes(view):
    _, _, small, rows = view
    scale = 0.5
    h, w = small.shape[0] // 4, small.shape[1] // 4
    heat, weight, box, box_mask = det_targets(rows, scale, (0, 0), (h, w), 5)
    out = np.concatenate([heat, box], 0)
    boxes = decode_boxes(out, scale, TwoStageConfig(min_score=0.99))
    positives = rows[rows[:, 9] >= 0.3]
    assert len(boxes) == len(positives) > 10
    truth = np.stack(
        [
            (positives[:, 5] + positives[:, 7]) / 2 - 0.5,
            (positives[:, 6] + positives[:, 8]) / 2 - 0.5,
        ],
        1,
    )
    for b in boxes:
        d = np.linalg.norm(truth - b.center, axis=1)
        j = int(np.argmin(d))
        assert d[j] < 0.6  # the offset restores the center to a fraction of an image pixel
        assert int(positives[j, 2]) - 1 == b.class_index
        size = positives[j, 7:9] - positives[j, 5:7]
        assert np.allclose(b.size, size, rtol=0.02, atol=1.0)
    # barely visible parts are ignored, not taught as background
    assert weight.shape == heat.shape
    assert (weight[0] == 0).sum() >= 9 * (rows[:, 9] < 0.3).sum() * 0.5


def test_a_perfect_crop_output_votes_the_true_center_and_mask(view):
    rgb, inst, _, rows = view
    config = TwoStageConfig()
    voting = VotingConfig(min_inliers=config.min_votes)
    rng = np.random.default_rng(0)
    checked = 0
    for r in rows[rows[:, 9] > 0.75][:8]:
        k = int(r[1])
        side = max(r[7] - r[5], r[8] - r[6])
        center = np.array([(r[5] + r[7]) / 2 - 0.5 + 3.0, (r[6] + r[8]) / 2 - 0.5 - 2.0])
        a, b = crop_transform(center, BatchConfig().box_scale * side, config.crop_size)
        label, vec = crop_targets(inst, k, r[3:5], a, b, config.crop_size)
        out = np.concatenate([(label * 20 - 10)[None], vec], 0)
        det = vote_in_crop(out, a, b, inst.shape, 7, 0.9, voting, config, rng)
        assert det is not None and det.obj_id == 7
        assert np.linalg.norm(det.center_uv - r[3:5]) < 0.5
        truth_mask = inst == k + 1
        iou = (det.mask & truth_mask).sum() / (det.mask | truth_mask).sum()
        assert iou > 0.6  # the mask is the label at a quarter of the crop's resolution
        checked += 1
    assert checked >= 5


def test_an_empty_crop_output_gives_no_detection():
    config = TwoStageConfig()
    g = config.crop_size // config.crop_stride
    out = np.zeros((3, g, g), np.float32)
    out[0] = -5.0
    a, b = crop_transform(np.array([50.0, 50.0]), 40.0, config.crop_size)
    assert (
        vote_in_crop(
            out, a, b, (100, 100), 1, 1.0, VotingConfig(), config, np.random.default_rng(0)
        )
        is None
    )


def test_crops_of_boxes_and_duplicates(view):
    rgb, _, small, rows = view
    heat, _, box, _ = det_targets(rows, 0.5, (0, 0), (small.shape[0] // 4, small.shape[1] // 4), 5)
    boxes = decode_boxes(np.concatenate([heat, box], 0), 0.5, TwoStageConfig(min_score=0.99))
    crops, transforms = crop_boxes(rgb, boxes, TwoStageConfig())
    assert crops.shape == (len(boxes), 96, 96, 3) and crops.dtype == np.uint8
    for bx, (a, b) in zip(boxes, transforms, strict=True):
        assert np.allclose(a * 47.5 + b, bx.center)
    from posefuse.estimator.frontend.detection import Detection

    def det(x, score):
        return Detection(1, [x - 10, 0, 20, 20], [x, 10], np.eye(2), None, score)

    kept = suppress_duplicates([det(10, 0.5), det(12, 0.9), det(40, 0.4)], 0.3)
    assert [d.score for d in kept] == [0.9, 0.4]


def test_the_box_channel_marks_the_crop_pixels_inside_the_box(view):
    rgb, _, small, rows = view
    heat, _, box, _ = det_targets(rows, 0.5, (0, 0), (small.shape[0] // 4, small.shape[1] // 4), 5)
    config = TwoStageConfig(min_score=0.99)
    boxes = decode_boxes(np.concatenate([heat, box], 0), 0.5, config)
    _, transforms = crop_boxes(rgb, boxes, config)
    masks = box_masks(boxes, transforms, config)
    assert masks.shape == (len(boxes), 96, 96) and masks.dtype == np.uint8 and len(boxes) > 2
    p = np.arange(96.0)
    for bx, (a, b), m in zip(boxes, transforms, masks, strict=True):
        # a crop pixel is marked exactly when its center, in image pixels, lies in the box
        x, y = a * p + b[0], a * p + b[1]
        lo, hi = bx.center - bx.size / 2, bx.center + bx.size / 2
        inside = ((y >= lo[1]) & (y <= hi[1]))[:, None] & ((x >= lo[0]) & (x <= hi[0]))[None]
        assert np.array_equal(m.astype(bool), inside)
        # the crop is box_scale x the longer side: that side spans 96 / 1.2 = 80 crop pixels
        extent = max(m.any(0).sum(), m.any(1).sum())
        assert abs(extent - 96 / config.box_scale) <= 1
    # a wide box and a tall one in the same square crop tell themselves apart
    a, b = crop_transform(np.array([50.0, 50.0]), 48.0, 96)
    wide = box_mask(np.array([50.0, 50.0]), np.array([40.0, 10.0]), a, b, 96)
    tall = box_mask(np.array([50.0, 50.0]), np.array([10.0, 40.0]), a, b, 96)
    assert np.array_equal(wide, tall.T) and wide.any(0).sum() == 80 and wide.any(1).sum() == 20


def test_training_crops_carry_the_box_they_were_cut_around(view):
    from types import SimpleNamespace

    rgb, inst, _, rows = view
    ts = SimpleNamespace(full_rgb=rgb[None], full_inst=inst[None], instances=rows)
    candidates = np.flatnonzero(rows[:, 9] > 0.75)
    config = BatchConfig(crop_batch=24, background_crops=0.0, box_channel=True)
    crops, masks, labels, _ = crop_batch(ts, config, np.random.default_rng(3), candidates)
    assert masks.shape == crops.shape[:3] and labels.shape == (24, 24, 24)
    inside = []
    for m, lab in zip(masks, labels, strict=True):
        assert m.any()
        on_part = lab > 0
        if on_part.any():  # the part's pixels (mirrored with the crop) lie in its box
            inside.append(m[1::4, 1::4][on_part].mean())
    assert np.median(inside) > 0.9
    # without the channel the masks are zeros and the crops are those of before
    plain = BatchConfig(crop_batch=24, background_crops=0.0)
    crops0, masks0, _, _ = crop_batch(ts, plain, np.random.default_rng(3), candidates)
    assert not masks0.any() and crops0.shape == crops.shape


@pytest.mark.parametrize("axis", [0, 1])
def test_a_flipped_detector_sample_decodes_to_the_flipped_boxes(view, axis):
    """Mirrors and upside-down flips (training's augmentation) keep the targets exact: decoding
    the flipped targets gives the truth's box centers flipped in the detector's input pixels."""
    _, _, small, rows = view
    scale = 0.5
    h, w = small.shape[0] // 4, small.shape[1] // 4
    heat, weight, box, box_mask = det_targets(rows, scale, (0, 0), (h, w), 5)
    image, heat, weight, box, box_mask = flip_detector_sample(
        small, heat, weight, box, box_mask, axis
    )
    assert image.shape == small.shape and np.array_equal(image, np.flip(small, axis))
    boxes = decode_boxes(np.concatenate([heat, box], 0), scale, TwoStageConfig(min_score=0.99))
    positives = rows[rows[:, 9] >= 0.3]
    assert len(boxes) == len(positives) > 10
    # box centers in input pixels (pixel-center coordinates), flipped along the axis
    truth = np.stack(
        [
            (positives[:, 5] + positives[:, 7]) / 2 * scale - 0.5,
            (positives[:, 6] + positives[:, 8]) / 2 * scale - 0.5,
        ],
        1,
    )
    extent = small.shape[axis]
    truth[:, 1 - axis] = extent - 1 - truth[:, 1 - axis]
    for b in boxes:
        center_in = (b.center + 0.5) * scale - 0.5
        d = np.linalg.norm(truth - center_in, axis=1)
        j = int(np.argmin(d))
        assert d[j] < 0.3
        assert int(positives[j, 2]) - 1 == b.class_index
        size = positives[j, 7:9] - positives[j, 5:7]
        assert np.allclose(b.size, size, rtol=0.02, atol=1.0)


@pytest.mark.parametrize("seed", range(6))
def test_a_turned_or_flipped_crop_still_points_at_its_center(view, seed):
    """Stage two's dihedral augmentation: after any flip and transpose the crop's pixels and
    label move together, and every labelled cell's vector points at the transformed center."""
    rgb, inst, _, rows = view
    r = rows[rows[:, 9] > 0.75][seed]
    k, S = int(r[1]), 96
    side = max(r[7] - r[5], r[8] - r[6])
    a, b = crop_transform(np.array([(r[5] + r[7]) / 2, (r[6] + r[8]) / 2]), 1.2 * side, S)
    crop = warp_crop(rgb, a, b, S, 1)
    label, vec = crop_targets(inst, k, r[3:5], a, b, S)
    mask = np.zeros((S, S), np.uint8)
    mask[10:30, 50:60] = 1
    rng = np.random.default_rng(seed)
    flip, transpose = rng.random() < 0.5, rng.random() < 0.5  # the draws dihedral_crop makes
    out = dihedral_crop(crop, mask, label, vec, np.random.default_rng(seed))
    crop2, mask2, label2, vec2 = out
    # the center in output-cell coordinates: cell j is crop pixel 4 j + 1.5
    center = ((r[3:5] - b) / a - 1.5) / 4
    expect_crop, expect_mask, expect_label = crop, mask, label
    g = label.shape[0]
    if flip:
        center[1] = g - 1 - center[1]
        expect_crop, expect_mask, expect_label = crop[::-1], mask[::-1], label[::-1]
    if transpose:
        center = center[::-1]
        expect_crop = expect_crop.transpose(1, 0, 2)
        expect_mask, expect_label = expect_mask.T, expect_label.T
    assert np.array_equal(crop2, expect_crop) and np.array_equal(mask2, expect_mask)
    assert np.array_equal(label2, expect_label) and label2.sum() > 20
    ys, xs = np.nonzero(label2)
    to_center = center[None] - np.stack([xs, ys], 1)
    to_center /= np.maximum(np.linalg.norm(to_center, axis=1, keepdims=True), 1e-9)
    far = np.linalg.norm(center[None] - np.stack([xs, ys], 1), axis=1) > 1.0
    cosines = np.sum(vec2[:, ys, xs].T * to_center, axis=1)
    assert np.all(cosines[far] > 0.999)


def test_a_crop_at_another_scale_teaches_its_own_classes_only(view):
    """``class_scale_factors``' training: in a sample drawn at a factor, the classes found at
    another scale are neither targets nor negatives (weight 0 on their heatmaps everywhere),
    and the taught ones decode to their visible boxes at that factor's scale."""
    from posefuse.sim.train_targets import _resized_view

    _, _, small, rows = view
    rows = rows.copy()
    rows[:, 2] = 1 + np.arange(len(rows)) % 2  # two classes, alternating
    factor, scale = 0.5, 0.5 * 0.5
    image = _resized_view(small, factor, (256, 320))
    assert image.shape[0] >= 256 and image.shape[1] >= 320
    assert image.shape[0] % 16 == 0 and image.shape[1] % 16 == 0
    import cv2

    rh, rw = round(small.shape[0] * factor), round(small.shape[1] * factor)
    resized = cv2.resize(small, (rw, rh), interpolation=cv2.INTER_AREA)
    assert np.array_equal(image[:rh, :rw], resized)  # padded at the bottom and right only
    h, w = image.shape[0] // 4, image.shape[1] // 4
    taught = np.array([True, False, False, False, False])
    heat, weight, box, box_mask = det_targets(rows, scale, (0, 0), (h, w), 5, taught)
    assert not heat[1:].any() and not weight[1:].any()
    assert weight[0].all() or (weight[0] == 0).sum() < weight[0].size  # cells still taught
    boxes = decode_boxes(np.concatenate([heat, box], 0), scale, TwoStageConfig(min_score=0.99))
    positives = rows[(rows[:, 9] >= 0.3) & (rows[:, 2] == 1)]
    assert len(boxes) == len(positives) == box_mask.sum() > 3
    truth = np.stack(
        [(positives[:, 5] + positives[:, 7]) / 2, (positives[:, 6] + positives[:, 8]) / 2], 1
    )
    for b in boxes:
        assert b.class_index == 0
        assert np.linalg.norm(truth - (b.center + 0.5), axis=1).min() < 1.5  # a quarter cell
    # every class taught: the targets of before, to the bit
    everything = det_targets(rows, scale, (0, 0), (h, w), 5)
    all_taught = det_targets(rows, scale, (0, 0), (h, w), 5, np.ones(5, bool))
    for a, b in zip(everything, all_taught, strict=True):
        assert np.array_equal(a, b)


def test_detector_batches_draw_each_sample_at_one_of_the_class_scales(view):
    """Each sample of a batch with ``class_scale_factors`` teaches the classes of one factor
    only, both factors are drawn, and factors all 1 give the one-scale batch to the bit."""
    from types import SimpleNamespace

    from posefuse.sim.train_targets import detector_batch

    _, _, small, rows = view
    rows = rows.copy()
    rows[:, 2] = 1 + np.arange(len(rows)) % 2
    ts = SimpleNamespace(small_rgb=small[None], n_views=1, meta={"spec": {"small_scale": 0.5}})
    two = BatchConfig(det_batch=12, class_scale_factors=(1.0, 0.5, 1.0, 1.0, 1.0))
    rng = np.random.default_rng(1)
    images, heat, weight, _, _ = detector_batch(ts, [rows], 5, two, rng)
    assert images.shape[1:3] == (256, 320) and weight.shape == heat.shape
    taught = weight.reshape(12, 5, -1).any(-1)  # (B, C): the classes each sample teaches
    half = taught[:, 1]
    assert half.any() and not half.all()  # both scales drawn
    assert not taught[half][:, [0, 2, 3, 4]].any() and taught[half][:, 1].all()
    assert taught[~half][:, [0, 2, 3, 4]].all() and not taught[~half][:, 1].any()
    one = BatchConfig(det_batch=12)
    ones = dataclasses.replace(one, class_scale_factors=(1.0,) * 5)
    a = detector_batch(ts, [rows], 5, one, np.random.default_rng(2))
    b = detector_batch(ts, [rows], 5, ones, np.random.default_rng(2))
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    with pytest.raises(ValueError, match="2 factors for 5 classes"):
        wrong = dataclasses.replace(one, class_scale_factors=(1.0, 0.5))
        detector_batch(ts, [rows], 5, wrong, np.random.default_rng(2))


def test_class_balanced_sampling_draws_each_class_by_its_weight(view):
    """``class_weights``: a part is drawn with its class's weight (a class weighted 0 never),
    and the weights are the inverse of each class's share (``sim.train.class_weights``); both
    stages' batches draw with them."""
    from types import SimpleNamespace

    from posefuse.sim.train import class_weights
    from posefuse.sim.train_targets import detector_batch, draw_parts

    assert class_weights(np.array([1, 1, 1, 2, 3, 3]), 4) == (2.0, 6.0, 3.0, 0.0)
    classes = np.array([1, 2, 3] * 100)
    drawn = classes[draw_parts(classes, (1.0, 3.0, 0.0), np.random.default_rng(0), 4000)]
    assert not (drawn == 3).any()
    assert abs((drawn == 2).mean() - 0.75) < 0.03
    # weights by the inverse share draw a rare class as often as a common one
    skewed = np.array([1] * 90 + [2] * 10)
    drawn = skewed[draw_parts(skewed, class_weights(skewed, 2), np.random.default_rng(1), 4000)]
    assert abs((drawn == 2).mean() - 0.5) < 0.03
    # both batches run with weights, every crop holding its part
    rgb, inst, small, rows = view
    rows = rows.copy()
    rows[:, 2] = 1 + np.arange(len(rows)) % 2
    ts = SimpleNamespace(full_rgb=rgb[None], full_inst=inst[None], instances=rows)
    candidates = np.flatnonzero(rows[:, 9] > 0.3)
    only_second = BatchConfig(crop_batch=40, background_crops=0.0, class_weights=(0.0, 1.0))
    _, _, label, _ = crop_batch(ts, only_second, np.random.default_rng(0), candidates)
    assert label.reshape(40, -1).any(1).all()
    spec = {"spec": {"small_scale": 0.5}}
    ts_small = SimpleNamespace(small_rgb=small[None], n_views=1, meta=spec)
    det = BatchConfig(det_batch=16, on_part=1.0, class_weights=(0.0, 1.0, 0.0, 0.0, 0.0))
    _, heat, _, _, _ = detector_batch(ts_small, [rows], 5, det, np.random.default_rng(0))
    assert (heat[:, 1].reshape(16, -1).max(1) == 1.0).all()
