"""Bad input on the command line: one clear error naming the file, non-zero exit, no traceback."""

import subprocess
import sys

import pytest

from service.cli import main


def run_cli(*args):
    proc = subprocess.run(
        [sys.executable, "-m", "service.cli", *args], capture_output=True, text=True, timeout=120
    )
    return proc.returncode, proc.stdout, proc.stderr


def test_missing_mesh_names_the_file(tmp_path):
    missing = tmp_path / "nope.stl"
    code, _, err = run_cli("catalog", "--out", str(tmp_path / "cat"), "--mesh", str(missing))
    assert code == 2
    assert str(missing) in err and "no such mesh file" in err
    assert "Traceback" not in err


def test_corrupt_mesh_names_the_file(tmp_path):
    bad = tmp_path / "bad.stl"
    bad.write_bytes(b"solid x\n garbage that is not a facet\nendsolid\n")
    code, _, err = run_cli("catalog", "--out", str(tmp_path / "cat"), "--mesh", str(bad))
    assert code == 2
    assert str(bad) in err
    assert "Traceback" not in err


def test_catalog_folder_without_models_info(tmp_path, capsys):
    (tmp_path / "cat").mkdir()
    assert main(["synth", "--catalog", str(tmp_path / "cat"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "models_info.json" in err and "missing" in err


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--scenes", "0"], "--scenes and --views must be at least 1"),
        (["--instances", "5", "2"], "--instances needs MIN MAX"),
        (["--intrinsics", "kinect"], "--intrinsics: unknown 'kinect'"),
    ],
)
def test_synth_rejects_bad_arguments(tmp_path, capsys, args, message):
    code = main(["synth", "--out", str(tmp_path / "o"), *args])
    assert code == 2
    assert message in capsys.readouterr().err


def test_replay_needs_a_mode_and_lockstep_needs_the_api(tmp_path, capsys):
    from service.cli import DEFAULT_RECORDING

    assert main(["replay", DEFAULT_RECORDING]) == 2
    assert "--offline" in capsys.readouterr().err
    code = main(
        [
            "replay",
            DEFAULT_RECORDING,
            "--live",
            "--lockstep",
            "--url",
            "http://127.0.0.1:9",
            "--listen",
            "tcp/127.0.0.1:0",
        ]
    )
    assert code == 2
    assert "--lockstep needs the daemon's API" in capsys.readouterr().err
