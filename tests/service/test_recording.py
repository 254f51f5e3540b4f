"""MCAP recordings: round trip, and the messages before the damage of a truncated file."""

import pytest

from posefuse.service.recording import Recorder, RecordingError, read_messages


def _record(path, n=600):
    with Recorder(path, metadata={"scene": "0"}) as rec:
        for k in range(n):
            kind = "image" if k % 3 == 0 else "pose"
            rec.write(f"posefuse/@v1/cam/cam0/{kind}", k.to_bytes(4, "little") * 700, 1000 + k)
    return path


def test_round_trip_in_log_time_order(tmp_path):
    path = _record(tmp_path / "a.mcap")
    msgs = list(read_messages(path))
    assert len(msgs) == 600
    assert [m.log_time_ns for m in msgs] == sorted(m.log_time_ns for m in msgs)
    assert msgs[5].key == "posefuse/@v1/cam/cam0/pose"
    assert msgs[5].payload == (5).to_bytes(4, "little") * 700


def test_damaged_files_give_the_messages_before_the_damage(tmp_path):
    path = _record(tmp_path / "a.mcap")
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    got = []
    with pytest.raises(RecordingError, match="cut.mcap"):
        for m in read_messages(cut):
            got.append(m)
    assert 0 < len(got) < 600
    assert [m.log_time_ns for m in got] == list(range(1000, 1000 + len(got)))
    garbage = tmp_path / "g.mcap"
    garbage.write_bytes(b"not an mcap file at all")
    with pytest.raises(RecordingError, match="g.mcap"):
        list(read_messages(garbage))
    with pytest.raises(RecordingError, match="file not found"):
        list(read_messages(tmp_path / "missing.mcap"))
