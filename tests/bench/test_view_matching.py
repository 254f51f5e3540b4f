"""bench.view_matching: the rotation step alone, view by view, at the true translation."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from posefuse.bench import view_matching
from posefuse.evaluation.dataset import load_dataset


def test_the_angle_to_the_truth_is_to_its_closest_symmetric_equivalent():
    R_true = Rotation.from_euler("xyz", [10, 20, 30], degrees=True).as_matrix()
    half_turn = Rotation.from_euler("z", 180, degrees=True).as_matrix()
    tilt = Rotation.from_euler("x", 12, degrees=True).as_matrix()
    templates = np.stack([R_true, R_true @ half_turn, R_true @ half_turn @ tilt])
    alone = view_matching._angles_to_truth(templates, R_true, np.eye(3)[None])
    np.testing.assert_allclose(alone, [0, 180, 180], atol=1e-6)
    both = view_matching._angles_to_truth(templates, R_true, np.stack([np.eye(3), half_turn]))
    np.testing.assert_allclose(both, [0, 0, 12], atol=1e-6)


def test_rendered_views_match_near_the_truth_with_their_silhouettes(
    small_dataset_root, default_banks, capsys
):
    dataset = load_dataset(small_dataset_root)
    matches = view_matching.view_matches(dataset, "silhouette")
    seen = sum(g.visib_fract >= 0.5 and g.bbox_visib[2] > 0 for v in dataset.views() for g in v.gts)
    assert len(matches) == seen > 0
    # our own renders, our own templates: most views hand the mixture a hypothesis near the truth
    assert np.mean([m.handed for m in matches]) > 0.6
    assert all(m.handed or m.best_deg >= 15 for m in matches)
    with pytest.raises(ValueError, match="masks must be"):
        view_matching.view_matches(dataset, "polygon")
    assert view_matching.main(["--dataset", str(small_dataset_root), "--masks", "box"]) == 0
    assert "| **all** |" in capsys.readouterr().out
