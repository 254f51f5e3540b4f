"""bench.real: a dataset and its rendered twin, side by side, per front end."""

import json

from posefuse.bench import real


def test_a_dataset_and_its_twin_side_by_side(small_dataset_root, tmp_path, capsys):
    out = tmp_path / "rates.json"
    assert (
        real.main(
            [
                "--real",
                str(small_dataset_root),
                "--out",
                str(tmp_path),
                "--json",
                str(out),
                "--quiet",
            ]
        )
        == 0
    )
    rates = json.loads(out.read_text())
    assert set(rates) == {
        f"{f} / {d}"
        for f in ("oracle, silhouettes", "oracle, boxes")
        for d in ("real", "rendered twin")
    }
    for row in rates.values():
        assert set(row) == {"2"}  # 3 views a scene: the 2-view checkpoint only
        assert row["2"]["instances"] > 0 and 0.0 <= row["2"]["add_sym"] <= 1.0
    printed = capsys.readouterr().out
    assert "| oracle, boxes | rendered twin |" in printed and "per object at 4 views" in printed
    assert (tmp_path / "twin" / "camera.json").is_file()  # rendered where it was missing
