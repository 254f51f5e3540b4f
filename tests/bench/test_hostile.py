"""bench.hostile: its rows are named, and a row that needs a scene says so."""

import pytest

from posefuse.bench import hostile


def test_an_unknown_row_or_a_missing_scene_is_one_clear_error(capsys):
    with pytest.raises(SystemExit):
        hostile.main(["--rows", "flod"])
    assert "no row 'flod'" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        hostile.main(["--rows", "overload"])
    assert "--scene DIR:SCENE" in capsys.readouterr().err


def test_the_events_row_measures_a_quiet_stop(tmp_path):
    import json

    out = tmp_path / "rows.json"
    assert hostile.main(["--rows", "events", "--json", str(out)]) == 0
    events = json.loads(out.read_text())["events"]
    assert events["returncode"] == 0 and events["tracebacks"] == 0
