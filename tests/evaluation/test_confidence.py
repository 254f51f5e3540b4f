"""evaluation.confidence: the estimates kept above a confidence threshold, scored."""

import numpy as np
import pytest

from posefuse.evaluation.confidence import confidence_markdown, confidence_rows
from posefuse.evaluation.dataset import load_dataset
from posefuse.evaluation.scores import PoseResult, ground_truth_results


def _results(ds):
    """The truth at confidence 0.9, and as many estimates 0.2 d off at confidence 0.4, in
    one checkpoint ("4 views") whose targets are every annotated view."""
    gt = [
        PoseResult(r.scene_id, r.im_id, r.obj_id, 0.9, r.T_cam_obj)
        for r in ground_truth_results(ds)
    ]
    wrong = []
    for r in gt:
        T = r.T_cam_obj.copy()
        T[:3, 3] += [0.2 * ds.catalog[r.obj_id].diameter, 0, 0]
        wrong.append(PoseResult(r.scene_id, r.im_id, r.obj_id, 0.4, T))
    targets = sorted({(v.scene_id, v.im_id) for v in ds.views()})
    return {4: gt + wrong}, {4: targets}, len(gt)


def test_a_threshold_above_the_wrong_estimates_keeps_what_is_right(small_dataset_root):
    ds = load_dataset(small_dataset_root)
    results, targets, n = _results(ds)
    rows = {r.threshold: r for r in confidence_rows(ds, results, targets, (0.0, 0.5, 0.95))}
    every, sure, none = rows[0.0], rows[0.5], rows[0.95]
    assert every.kept == 2 * n and sure.kept == n and none.kept == 0
    # the wrong estimates cost precision, never ADD-sym (each truth is found once)
    assert every.add_sym == sure.add_sym == 1.0
    assert every.precision == pytest.approx(0.5, abs=0.05) and sure.precision == 1.0
    assert none.add_sym == 0.0 and np.isnan(none.precision)
    table = confidence_markdown(list(rows.values()))
    assert "| 0.5 |" in table and "100.0%" in table and "| 0.95 |" in table and "| 1 |" not in table


def test_a_threshold_outside_zero_to_one_is_refused(small_dataset_root):
    ds = load_dataset(small_dataset_root)
    results, targets, _ = _results(ds)
    with pytest.raises(ValueError, match="thresholds"):
        confidence_rows(ds, results, targets, (0.5, 1.5))
