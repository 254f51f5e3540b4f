"""Bad input on the command line: one clear error naming the file, non-zero exit, no traceback."""

import subprocess
import sys

import pytest

from posefuse.cli.main import main


def run_cli(*args):
    proc = subprocess.run(
        [sys.executable, "-m", "posefuse.cli", *args], capture_output=True, text=True, timeout=120
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
        (["--workers", "0"], "--workers: 0: must be at least 1"),
    ],
)
def test_synth_rejects_bad_arguments(tmp_path, capsys, args, message):
    code = main(["synth", "--out", str(tmp_path / "o"), *args])
    assert code == 2
    assert message in capsys.readouterr().err


def test_replay_needs_a_mode_and_lockstep_needs_the_api(tmp_path, capsys):
    from posefuse.service.resources import DEFAULT_RECORDING

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


def _commands():
    """(name, parser) of every sub-command, the entry points' included."""
    import argparse

    from posefuse.cli.main import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices


def test_service_imports_no_layer_above_it():
    """service/ is used by clients/, bench/ and cli/, never the other way round."""
    import ast
    from pathlib import Path

    import posefuse.service as service

    above = {"bench", "clients", "cli"}
    offences = []
    for path in sorted(Path(service.__file__).parent.glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            offences += [
                f"{path.name}:{node.lineno} {n}"
                for n in names
                if n.removeprefix("posefuse.").split(".")[0] in above
            ]
    assert not offences


def test_every_option_of_every_command_has_help_and_shows_its_default():
    from posefuse.cli.common import HelpFormatter

    commands = _commands()
    assert {"catalog", "synth", "run-dataset", "quickstart", "train", "serve", "objects"} <= set(
        commands
    )
    assert "bench" in commands  # the project's own posefuse.commands entry point
    for name, parser in commands.items():
        assert issubclass(parser.formatter_class, HelpFormatter), name
        for action in parser._actions:
            assert action.help and action.help.strip(), (name, action.dest)
        text = parser.format_help()
        for action in parser._actions:
            if action.required and action.option_strings:
                assert "(required)" in text, (name, action.dest)
    text = commands["synth"].format_help()
    assert "(default: 8)" in text and "(default: mixed)" in text
    assert "default: None" not in text


def test_outputs_go_under_runs_unless_told_otherwise():
    from posefuse.cli.main import build_parser

    parser = build_parser()
    defaults = {
        "make-demo": ["make-demo"],
        "replay": ["replay", "x.mcap"],
        "quickstart": ["quickstart"],
        "bench": ["bench", "--dataset", "d"],
    }
    for name, argv in defaults.items():
        args = parser.parse_args(argv)
        for dest in ("out", "work"):
            value = getattr(args, dest, None)
            if value is not None:
                assert str(value).startswith("runs/"), (name, dest, value)


def test_plugin_command_groups_come_after_the_built_in_ones_by_name(monkeypatch, capsys):
    from importlib.metadata import EntryPoint

    import posefuse.cli.main

    def register_zz(sub):
        sub.add_parser("zz-extra", help="a plugin's command").set_defaults(func=lambda a: 7)

    def register_aa(sub):
        sub.add_parser("aa-extra", help="another").set_defaults(func=lambda a: 0)

    monkeypatch.setattr(
        posefuse.cli.main,
        "entry_points",
        lambda group: [
            EntryPoint("zz", f"{__name__}:_never_used", group),
            EntryPoint("aa", f"{__name__}:_never_used", group),
            EntryPoint("broken", "no_such_module_anywhere:register", group),
        ],
    )
    loaders = {"zz": register_zz, "aa": register_aa}
    monkeypatch.setattr(EntryPoint, "load", lambda self: loaders.get(self.name) or _fail())
    names = list(_commands())
    assert names.index("make-demo") < names.index("aa-extra") < names.index("zz-extra")
    assert "broken" in capsys.readouterr().err
    assert posefuse.cli.main.main(["zz-extra"]) == 7


def _fail():
    raise ImportError("no module named no_such_module_anywhere")


def test_objects_table_names_its_units():
    from posefuse.clients.query import table

    estimate = {
        "object_id": "gear-1",
        "status": "confirmed",
        "n_views": 4,
        "confidence": 0.9,
        "t": [0.1, -0.2, 0.55],
        "q": [0.0, 0.0, 0.0, 1.0],
        "cov": [0.0] * 36,
    }
    header, row = table([estimate]).splitlines()[:2]
    for unit in ("x (m)", "y (m)", "z (m)", "roll (deg)", "pitch (deg)", "yaw (deg)", "(mm)"):
        assert unit in header
    # a map without the field (an older daemon's) is not verified; one with it says so
    assert "verified" in header and row.split()[4] == "no"
    assert table([{**estimate, "verified": True}]).splitlines()[1].split()[4] == "yes"


def test_quickstart_runs_the_estimator_and_says_what_next(tmp_path):
    """The whole quickstart in its own process: about a minute when the templates are cached."""
    out = tmp_path / "qs"
    code, stdout, err = run_cli("quickstart", "--out", str(out))
    assert code == 0, err
    assert "| object | views | instances | estimates | ADD-sym-0.1d | MSSD-0.1d |" in stdout
    assert "| **all** | 4 |" in stdout and "| **all** | 8 |" in stdout
    assert any(line.startswith("next:") for line in stdout.splitlines())
    assert (out / "run" / "detection_rate.md").is_file()
    assert (out / "overlay_000000_000000.png").is_file()


@pytest.mark.parametrize("command", ["serve", "demo"])
def test_a_busy_http_port_is_refused_before_anything_starts(command, capsys):
    import socket

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen(1)
        port = busy.getsockname()[1]
        code = main([command, "--http-port", str(port)])
    err = capsys.readouterr()
    assert code == 2
    assert f"127.0.0.1:{port} is not free" in err.err and "--http-port 0" in err.err
    assert "HTTP on" not in err.out and "[1/3]" not in err.out  # nothing announced


def test_http_port_zero_picks_a_free_port():
    from posefuse.cli.common import claim_http_port
    from posefuse.service.settings import Settings

    settings = claim_http_port(Settings(http_port=0))
    assert settings.http_port > 0


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--threads", "0"], "--threads: 0: must be at least 1"),
        (["--width", "0"], "--width: 0: must be at least 1"),
        (["--input-scale", "2"], "--input-scale: 2.0: must be in [0.1, 1]"),
    ],
)
def test_train_rejects_bad_arguments_before_any_work(tmp_path, capsys, args, message):
    out = tmp_path / "m.onnx"
    code = main(["train", "--out", str(out), *args, "--data-dir", str(tmp_path)])
    assert code == 2
    assert message in capsys.readouterr().err
    assert not out.exists() and not any(tmp_path.iterdir())
