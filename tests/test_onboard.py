"""`posefuse onboard`: bad meshes refused with one clear message each; a tiny-budget run on one
real mesh gives a part set that `posefuse serve --parts` serves, with estimates of a published
scene."""

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from loopback import free_port, get_json

from posefuse.cli.main import main

SHARED = Path(
    os.environ.get(
        "POSEFUSE_SHARED_OBJECTS", Path(__file__).resolve().parents[2] / "shared" / "objects"
    )
)


def _one_mesh(tmp_path) -> Path:
    """The real bracket of ../shared/objects when present, else the procedural zigzag exported
    as an STL in millimetres (the pipeline is the same)."""
    real = SHARED / "bracket.stl"
    if real.is_file():
        return real
    from posefuse.sim.parts import build_part

    path = tmp_path / "bracket.stl"
    build_part("zigzag").export(path)
    return path


def _run(argv, capsys):
    code = main(argv)
    captured = capsys.readouterr()
    return code, captured.out + captured.err


@pytest.mark.parametrize(
    "case, expected",
    [
        ("missing", "no such mesh file"),
        ("metres", "did you mean --units mm"),
        ("empty", "holds no triangles"),
        ("text", "holds no triangles"),
    ],
)
def test_bad_meshes_get_one_clear_message(tmp_path, capsys, case, expected):
    from posefuse.sim.parts import build_part

    if case == "missing":
        path, units = tmp_path / "nowhere.stl", "mm"
    elif case == "metres":  # a 57 mm screw read as metres: a 57 m part
        path, units = tmp_path / "screw.stl", "m"
        build_part("chrome_screw").export(path)
    elif case == "empty":
        path, units = tmp_path / "empty.stl", "mm"
        path.write_bytes(b"solid empty\nendsolid empty\n")
    else:
        path, units = tmp_path / "notes.stl", "mm"
        path.write_text("this is not a mesh\n")
    code, text = _run(
        ["onboard", str(path), "--units", units, "--out", str(tmp_path / "out")], capsys
    )
    assert code == 2
    lines = [line for line in text.splitlines() if "error" in line]
    assert len(lines) == 1 and expected in lines[0] and str(path) in lines[0], text
    assert not (tmp_path / "out" / "parts.json").exists()


def test_an_open_mesh_is_accepted_with_a_note(tmp_path):
    from posefuse.sim.onboard import OnboardConfig, read_parts
    from posefuse.sim.parts import build_part

    mesh = build_part("zigzag")
    mesh.update_faces(list(range(1, len(mesh.faces))))  # one face removed: not watertight
    mesh.remove_unreferenced_vertices()
    assert not mesh.is_watertight
    path = tmp_path / "open.stl"
    mesh.export(path)
    notes = []
    catalog, reports = read_parts([str(path)], OnboardConfig(), echo=notes.append)
    assert len(catalog) == 1
    assert any("not watertight" in n and "open.stl" in n for n in notes), notes


def test_symmetry_overrides_name_known_parts(tmp_path, capsys):
    from posefuse.sim.parts import build_part

    path = tmp_path / "screw.stl"
    build_part("chrome_screw").export(path)
    code, text = _run(
        ["onboard", str(path), "--out", str(tmp_path / "o"), "--symmetry", "bolt=none"], capsys
    )
    assert code == 2 and "no mesh named ['bolt']" in text


def test_onboard_then_serve_the_part_set(tmp_path, capsys):
    """A tiny budget (4 minutes): every stage runs, the manifest is complete, and a daemon
    serving the part set estimates the parts of a published validation scene."""
    out = tmp_path / "parts"
    code, text = _run(
        [
            "onboard",
            str(_one_mesh(tmp_path)),
            "--out",
            str(out),
            "--minutes",
            "4",
            "--views",
            "2",
            "--held-scenes",
            "1",
            "--held-views",
            "4",
        ],
        capsys,
    )
    assert code == 0, text
    manifest = json.loads((out / "parts.json").read_text())
    assert [p["name"] for p in manifest["parts"]] == ["bracket"]
    assert set(manifest["stage_seconds"]) == {"catalog", "templates", "front end", "validation"}
    assert set(manifest["validation"]) == {"mixed", "robi"}
    assert manifest["training"]["iterations"] > 0
    assert (out / "contact" / "bracket.png").stat().st_size > 10_000
    assert (out / "demo.mcap").is_file() and "next: posefuse demo --parts" in text

    zport, hport = free_port(), free_port()
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    serve = [sys.executable, "-m", "posefuse.cli", "serve", "--parts", str(out), "--cell", "onb"]
    serve += ["--listen", f"tcp/127.0.0.1:{zport}", "--http-port", str(hport)]
    daemon = subprocess.Popen(
        serve, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env
    )
    base = f"http://127.0.0.1:{hport}"
    try:
        deadline = time.time() + 120
        while True:
            try:
                if get_json(f"{base}/readyz", 1)["status"] == "ready":
                    break
            except OSError:
                pass
            if daemon.poll() is not None or time.time() > deadline:
                raise AssertionError(f"daemon did not start:\n{daemon.stdout.read()}")
            time.sleep(0.5)
        publish = [sys.executable, "-m", "posefuse.cli", "publish", "--dataset"]
        publish += [str(out / "validation" / "mixed"), "--scene", "0", "--rate", "4"]
        publish += ["--cell", "onb", "--connect", f"tcp/127.0.0.1:{zport}"]
        publish += ["--listen", f"tcp/127.0.0.1:{free_port()}"]
        done = subprocess.run(publish, capture_output=True, text=True, timeout=120, env=env)
        assert done.returncode == 0, done.stderr
        deadline = time.time() + 60
        while get_json(f"{base}/stats")["frames_processed"] < 4:
            assert time.time() < deadline, get_json(f"{base}/stats")
            time.sleep(0.5)
        objects = get_json(f"{base}/objects")
        # a 4-minute budget trains little, but enough on this part for the daemon to estimate
        assert objects, get_json(f"{base}/stats")
        assert all(o["class_name"] == "bracket" for o in objects)
    finally:
        daemon.terminate()
        daemon.wait(timeout=20)
