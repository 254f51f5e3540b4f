"""`posefuse run-dataset` with the oracle: per-view-count translation errors on a BOP dataset."""

import csv

from service.cli import main


def test_run_dataset_writes_errors_at_1_2_4_and_more_views(small_dataset_root, tmp_path, capsys):
    out = tmp_path / "run"
    code = main(
        [
            "run-dataset",
            "--dataset",
            str(small_dataset_root),
            "--out",
            str(out),
            "--quiet",
            "--drop-rate",
            "0",
            "--false-positive-rate",
            "0",
        ]
    )
    assert code == 0
    text = capsys.readouterr().out
    assert "| object | 1 view | 2 views | 4 views | 8 views |" in text
    assert "Association: precision 1.0000, recall 1.0000" in text
    rows = list(csv.DictReader((out / "translation_errors.csv").open()))
    counts = {int(r["n_views"]) for r in rows}
    assert counts == {1, 2}  # the fixture has 3 views per scene
    one = [float(r["rel_error"]) for r in rows if r["n_views"] == "1"]
    two = [float(r["rel_error"]) for r in rows if r["n_views"] == "2"]
    # two views triangulate: far better than the bbox-size depth of one view
    assert sorted(two)[len(two) // 2] < 0.02 < sorted(one)[len(one) // 2]


def test_run_dataset_refuses_bad_settings(small_dataset_root, tmp_path, capsys):
    args = ["run-dataset", "--dataset", str(small_dataset_root), "--out", str(tmp_path), "--quiet"]
    assert main([*args, "--drop-rate", "1.5"]) == 2
    assert "drop_rate must be in [0, 1]" in capsys.readouterr().err
    assert main([*args, "--scenes", "9"]) == 2
    assert "no scene 9" in capsys.readouterr().err
    assert main([*args, "--frontend", "magic"]) == 2
    assert "'magic' is not known" in capsys.readouterr().err


def test_both_steps_end_to_end_and_deterministic(small_dataset_root, default_banks):
    import numpy as np

    from estimator.dataset import load_dataset
    from estimator.evaluation import evaluate
    from estimator.frontend.oracle import OracleConfig, OracleFrontend
    from estimator.run_dataset import run_dataset
    from estimator.tracker import MultiViewEstimator

    ds = load_dataset(small_dataset_root)

    def run():
        return run_dataset(
            ds,
            OracleFrontend(ds, OracleConfig(seed=3)),
            show_progress=False,
            rotation=True,
            estimator_factory=lambda: MultiViewEstimator(ds.catalog, banks=default_banks),
        )

    a, b = run(), run()
    assert a.results[1] == [] and len(a.results[2]) > 5  # rotation waits for the translation
    report = evaluate(ds, a.results[2], targets=a.targets[2])
    assert report.n_instances > 5 and report.rate > 0.3, report.to_markdown()
    for x, y in zip(a.results[2], b.results[2], strict=True):
        assert (x.scene_id, x.im_id, x.obj_id, x.score) == (y.scene_id, y.im_id, y.obj_id, y.score)
        np.testing.assert_array_equal(x.T_cam_obj, y.T_cam_obj)
