"""ADD / ADI / MSSD as BOP defines them, result files, and the detection rate."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from estimator.dataset import load_dataset
from estimator.errors import ResultsError
from estimator.evaluation import (
    PoseResult,
    add_error,
    adi_error,
    evaluate,
    ground_truth_results,
    mssd_error,
    read_results,
    write_results,
)
from service.cli import main


def _T(R=None, t=(0, 0, 0)):
    T = np.eye(4)
    T[:3, :3] = np.eye(3) if R is None else R
    T[:3, 3] = t
    return T


def test_errors_on_a_translation_and_a_symmetric_rotation():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(500, 3))
    gt = _T(t=(0, 0, 1))
    assert add_error(_T(t=(0.1, 0, 1)), gt, pts) == pytest.approx(0.1)
    assert adi_error(gt, gt, pts) == 0
    # a square's 4-fold symmetry: ADD sees a large error, ADI and MSSD (with the group) none
    square = np.array([[1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0]], float)
    quarter = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    est = _T(quarter, (0, 0, 1))
    assert add_error(est, gt, square) == pytest.approx(np.sqrt(2))
    assert adi_error(est, gt, square) == pytest.approx(0, abs=1e-12)
    group = np.stack(
        [_T(Rotation.from_euler("z", 90 * k, degrees=True).as_matrix()) for k in range(4)]
    )
    assert mssd_error(est, gt, square, group) == pytest.approx(0, abs=1e-12)
    assert mssd_error(est, gt, square, group[:1]) == pytest.approx(np.sqrt(2))


def test_ground_truth_scores_100_and_displaced_poses_0(small_dataset_root, tmp_path):
    ds = load_dataset(small_dataset_root)
    gt = ground_truth_results(ds)
    path = write_results(tmp_path / "gt.csv", gt)
    report = evaluate(ds, read_results(path))
    assert report.n_instances > 0 and report.rate == 1.0
    displaced = []
    for r in gt:
        d = 0.2 * ds.catalog[r.obj_id].diameter
        T = r.T_cam_obj.copy()
        T[:3, 3] += [d, 0, 0]
        displaced.append(PoseResult(r.scene_id, r.im_id, r.obj_id, r.score, T))
    # MSSD of a pure shift is at least the shift (the symmetry axes pass through the model
    # origin); ADD-S can forgive a shift along an elongated part, so it is not used here.
    assert evaluate(ds, displaced, metric="mssd").n_found == 0
    # one estimate can find only one instance: duplicates do not count twice
    doubled = gt + gt
    assert evaluate(ds, doubled).n_found == report.n_found
    assert evaluate(ds, gt, metric="mssd").rate == 1.0
    assert "ADD(-S)-0.1d" in report.to_markdown()
    assert report.to_json()["rate"] == 1.0


def test_results_round_trip(tmp_path):
    R = Rotation.from_rotvec([0.3, -0.2, 0.1]).as_matrix()
    results = [PoseResult(3, 7, 2, 0.75, _T(R, (0.01, -0.02, 0.7)), 0.5)]
    back = read_results(write_results(tmp_path / "r.csv", results))
    assert len(back) == 1
    assert (back[0].scene_id, back[0].im_id, back[0].obj_id) == (3, 7, 2)
    np.testing.assert_allclose(back[0].T_cam_obj, results[0].T_cam_obj, atol=1e-9)


@pytest.mark.parametrize(
    "row, reason",
    [
        ("0,0,1,1.0,1 0 0 0 1 0 0 0 1,0 0 700", "fields"),
        ("0,0,1,abc,1 0 0 0 1 0 0 0 1,0 0 700,1", "not a number"),
        ("0,0,1,1.0,1 0 0 0 1 0 0 0,0 0 700,1", "R needs 9 numbers"),
        ("0,0,1,1.0,2 0 0 0 1 0 0 0 1,0 0 700,1", "not a rotation"),
        ("0,0,1,1.0,1 0 0 0 1 0 0 0 1,0 0 nan,1", "finite"),
    ],
)
def test_malformed_rows_name_the_row(tmp_path, row, reason):
    path = tmp_path / "bad.csv"
    path.write_text(
        "scene_id,im_id,obj_id,score,R,t,time\n0,0,1,1,1 0 0 0 1 0 0 0 1,0 0 7,1\n" + row + "\n"
    )
    with pytest.raises(ResultsError, match=rf"bad.csv, row 3: .*{reason}"):
        read_results(path)


def test_cli_eval_reports_a_bad_file_in_one_line(small_dataset_root, tmp_path, capsys):
    path = tmp_path / "bad.csv"
    path.write_text("scene,im\n")
    assert main(["eval", "--dataset", str(small_dataset_root), "--results", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("posefuse eval: error:") and "row 1" in err and len(err.splitlines()) == 1
