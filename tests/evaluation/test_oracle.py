"""The oracle front end: noisy, seeded, order-independent detections from ground truth."""

import numpy as np

from posefuse.evaluation.dataset import load_dataset
from posefuse.evaluation.oracle import OracleConfig, OracleFrontend


def test_detections_follow_the_ground_truth(small_dataset_root):
    ds = load_dataset(small_dataset_root)
    oracle = OracleFrontend(ds, OracleConfig(center_sigma_px=2.0, seed=1))
    errors = []
    for view in ds.views():
        for det, gt_idx in oracle.detect_with_truth(view):
            gt = view.gts[gt_idx]
            assert det.obj_id == gt.obj_id and gt.visib_fract >= 0.1
            true_uv = view.camera.project(gt.T_cam_obj[:3, 3])
            errors.append(det.center_uv - true_uv)
            np.testing.assert_allclose(det.center_cov, 4.0 * np.eye(2))
            assert det.mask is not None and det.mask.sum() == gt.px_count_visib
    errors = np.array(errors)
    assert len(errors) > 20
    assert np.all(np.abs(errors) < 5 * 2.0)
    assert 1.3 < errors.std() < 2.7


def test_same_seed_same_detections_in_any_order(small_dataset_root):
    ds = load_dataset(small_dataset_root)
    cfg = OracleConfig(drop_rate=0.3, false_positive_rate=0.3, with_masks=False, seed=4)
    views = list(ds.views())
    a = [OracleFrontend(ds, cfg).detect_with_truth(v) for v in views]
    b = [OracleFrontend(ds, cfg).detect_with_truth(v) for v in reversed(views)][::-1]
    for da, db in zip(a, b, strict=True):
        assert [k for _, k in da] == [k for _, k in db]
        for (x, _), (y, _) in zip(da, db, strict=True):
            np.testing.assert_array_equal(x.center_uv, y.center_uv)


def test_drops_and_false_positives(small_dataset_root):
    ds = load_dataset(small_dataset_root)
    views = list(ds.views())
    base = OracleConfig(with_masks=False)
    n_true = sum(len(OracleFrontend(ds, base).detect(v)) for v in views)
    none = OracleConfig(drop_rate=1.0, with_masks=False)
    assert sum(len(OracleFrontend(ds, none).detect(v)) for v in views) == 0
    noisy = OracleConfig(false_positive_rate=1.0, with_masks=False)
    pairs = [p for v in views for p in OracleFrontend(ds, noisy).detect_with_truth(v)]
    assert sum(k == -1 for _, k in pairs) == n_true


def test_box_masks_are_the_filled_visible_boxes(small_dataset_root):
    ds = load_dataset(small_dataset_root)
    silhouettes = OracleFrontend(ds, OracleConfig(seed=1))
    boxes = OracleFrontend(ds, OracleConfig(seed=1, masks="box"))
    view = next(iter(ds.views()))
    for (s, k), (b, j) in zip(
        silhouettes.detect_with_truth(view), boxes.detect_with_truth(view), strict=True
    ):
        assert k == j and np.array_equal(s.center_uv, b.center_uv)
        x, y, w, h = view.gts[k].bbox_visib
        assert b.mask.sum() == w * h and b.mask[y : y + h, x : x + w].all()
        assert (b.mask | ~s.mask).all()  # the silhouette lies inside its box
        assert (s.mask_kind, b.mask_kind) == ("silhouette", "box")
    with np.testing.assert_raises_regex(ValueError, "masks must be 'silhouette' or 'box'"):
        OracleConfig(masks="boxes")
