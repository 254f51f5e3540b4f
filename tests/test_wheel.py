"""The built wheel alone: installed into a new virtual environment and run from a folder outside
the checkout, it answers ``posefuse --help``, replays the shipped demo recording offline with the
shipped catalog and model (package data, found through importlib.resources) and serves. The
wheel holds one top-level package, ``posefuse``. Under a minute on 2 cores."""

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
from loopback import free_port, get_json
from test_demo_replay import _assert_above_the_floor

REPO = Path(__file__).resolve().parents[1]
# the folders a checkout ships as package data of posefuse (pyproject.toml's package-data)
DATA = ("catalogs", "models", "recordings")


def _checkout_files() -> list[str]:
    """The files a fresh clone of this checkout has (tracked, or new and not ignored): a wheel
    built from them holds nothing this working tree happens to have lying around (build/,
    runs/, caches)."""
    try:
        out = subprocess.run(
            ["git", "-C", str(REPO), "ls-files", "-co", "--exclude-standard", "-z"],
            capture_output=True,
            check=True,
            timeout=60,
        ).stdout
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("the wheel test builds from a git checkout")
    return [f for f in out.decode().split("\0") if f and (REPO / f).is_file()]


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """(venv's python, its site-packages/posefuse, the source tree the wheel was built from,
    the files copied into it)."""
    tmp = tmp_path_factory.mktemp("wheel")
    src = tmp / "src"
    files = _checkout_files()
    for f in files:
        (src / f).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(REPO / f, src / f)
    dist = tmp / "dist"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            str(src),
            "--no-deps",
            "--no-build-isolation",
            "-q",
            "--disable-pip-version-check",
            "-w",
            str(dist),
        ],
        check=True,
        timeout=180,
    )
    (wheel,) = dist.glob("posefuse-*.whl")
    # the dependencies come from this environment; posefuse itself only from the wheel. A venv
    # made with --system-site-packages would see the base interpreter's packages, not those of
    # the environment the tests run in (a user's venv): this environment's package folders are
    # put on the new venv's path instead, after its own, by a .pth file
    venv = tmp / "venv"
    subprocess.run(
        [sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=120
    )
    python = venv / "bin" / "python"
    site = _purelib(python)
    (Path(site) / "_test_environment.pth").write_text("\n".join(_environment_paths()) + "\n")
    subprocess.run(
        [
            str(python),
            "-m",
            "pip",
            "install",
            "--no-deps",
            "--no-index",
            "--ignore-installed",
            "-q",
            "--disable-pip-version-check",
            str(wheel),
        ],
        check=True,
        timeout=180,
    )
    return python, Path(site) / "posefuse", src, files


def _purelib(python: Path) -> str:
    """The site-packages folder of a venv's python."""
    return subprocess.run(
        [str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        capture_output=True,
        text=True,
        check=True,
        timeout=60,
    ).stdout.strip()


def _environment_paths() -> list[str]:
    """The package folders of the environment the tests run in (a venv's, a conda
    environment's or the system interpreter's), without the checkout an editable install of
    posefuse points at."""
    import site

    paths = [*site.getsitepackages(), site.getusersitepackages()]
    return [p for p in dict.fromkeys(paths) if Path(p).is_dir() and Path(p).resolve() != REPO]


def _run(command, cwd, timeout=120):
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    return subprocess.run(
        command, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout
    )


def test_the_wheel_holds_one_top_level_package_with_every_subpackage_and_the_data(installed):
    python, package, src, files = installed
    (info,) = package.parent.glob("posefuse-*.dist-info")
    records = [line.split(",")[0] for line in (info / "RECORD").read_text().splitlines()]
    tops = {r.split("/")[0] for r in records if not r.startswith("../")}  # ../../../bin/posefuse
    assert tops == {"posefuse", info.name}, tops
    # what `pip show -f posefuse` lists: posefuse/..., the dist-info and the console script
    assert [r for r in records if r.startswith("../")] == ["../../../bin/posefuse"]
    # every package of the source tree is in it, under posefuse
    inits = [f for f in files if f.endswith("__init__.py") and not f.startswith("tests/")]
    assert "estimator/frontend/__init__.py" in inits
    for rel in inits:
        assert (package / rel).is_file(), rel
    # the shipped files, byte for byte: whatever models/ holds (crop model, card, checkpoint)
    shipped = [f for f in files if f.split("/")[0] in DATA]
    assert any(f.endswith(".onnx") for f in shipped) and any(f.endswith(".mcap") for f in shipped)
    for rel in shipped:
        assert (package / rel).read_bytes() == (src / rel).read_bytes(), rel


def test_the_installed_wheel_helps_replays_and_serves_outside_the_checkout(installed, tmp_path):
    python, package, _, _ = installed
    bin_dir = python.parent
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    # every posefuse module, and every default path, comes from the venv, not this checkout
    probe = (
        "import json, sys, posefuse.cli.main, posefuse.service.daemon\n"
        "from posefuse.service import resources as r\n"
        "mods = [m.__file__ for n, m in list(sys.modules.items())\n"
        "        if n.split('.')[0] == 'posefuse' and getattr(m, '__file__', None)]\n"
        "print(json.dumps([*mods, r.DEFAULT_CATALOG, r.DEFAULT_MODEL, r.DEFAULT_RECORDING]))\n"
    )
    proc = _run([str(python), "-c", probe], elsewhere)
    assert proc.returncode == 0, proc.stderr
    paths = json.loads(proc.stdout)
    assert len(paths) > 10
    assert all(Path(p).resolve().is_relative_to(package.resolve()) for p in paths), paths

    help_ = _run([str(bin_dir / "posefuse"), "--help"], elsewhere)
    assert help_.returncode == 0, help_.stderr
    assert "replay" in help_.stdout and "bench" in help_.stdout  # bench: the entry point

    # the shipped demo recording, replayed offline with the shipped catalog and model
    out = tmp_path / "replay"
    recording = package / "recordings" / "demo.mcap"
    replay = _run(
        [str(bin_dir / "posefuse"), "replay", str(recording), "--offline", "--out", str(out)],
        elsewhere,
        timeout=300,
    )
    assert replay.returncode == 0, replay.stdout[-2000:] + replay.stderr[-2000:]
    _assert_above_the_floor(json.loads((out / "estimates.json").read_text())["segments"])

    # and the daemon: ready, its objects and its /docs (local Swagger assets) answered
    zport, hport = free_port(), free_port()
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    daemon = subprocess.Popen(
        [
            str(bin_dir / "posefuse"),
            "serve",
            "--listen",
            f"tcp/127.0.0.1:{zport}",
            "--http-port",
            str(hport),
        ],
        cwd=elsewhere,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
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
                daemon.kill()
                raise AssertionError(f"daemon did not start:\n{daemon.stdout.read()}")
            time.sleep(0.3)
        assert get_json(f"{base}/objects") == []
        import urllib.request

        with urllib.request.urlopen(f"{base}/docs", timeout=5) as r:
            page = r.read().decode()
        assert "swagger" in page.lower()
    finally:
        daemon.terminate()
        try:
            daemon.wait(30)
        except subprocess.TimeoutExpired:
            daemon.kill()
            daemon.wait(10)
