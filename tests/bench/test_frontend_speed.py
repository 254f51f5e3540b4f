"""The front end's speed benchmark: what it prints, and the fastest of repeated runs."""

import re

import pytest

from posefuse.bench import frontend_speed


def test_the_speed_benchmark_prints_each_dataset_and_bucket(full_res_dataset, capsys):
    args = ["--dataset", str(full_res_dataset), "--frames", "2", "--repeat", "2"]
    assert frontend_speed.main(args) == 0
    out = capsys.readouterr().out
    line = next(x for x in out.splitlines() if x.startswith(str(full_res_dataset)))
    assert "(2 frames, 2 threads sleeping, fastest of 2)" in line
    numbers = dict(re.findall(r"(median|stage_one|stage_two) ([\d.]+)", line))
    assert set(numbers) == {"median", "stage_one", "stage_two"}
    assert all(float(x) > 0 for x in numbers.values())
    assert re.search(r"frames with (1-10|11-20|21\+) detections", out)


@pytest.mark.parametrize("flag, value", [("--repeat", "0"), ("--refine-min-offset", "-1")])
def test_the_speed_benchmark_refuses_what_it_cannot_time(full_res_dataset, flag, value, capsys):
    with pytest.raises(SystemExit):
        frontend_speed.main(["--dataset", str(full_res_dataset), flag, value])
    assert flag in capsys.readouterr().err
