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
    assert main([*args, "--frontend", "network"]) == 2
    assert "not available yet" in capsys.readouterr().err
