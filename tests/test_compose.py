"""docker-compose.yml and the Dockerfile name what the cell needs (no Docker engine runs here)."""

from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]


def test_compose_file_parses_and_wires_two_cells():
    compose = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    services = compose["services"]
    assert set(services) == {"router", "estimator-a", "estimator-b", "camera-a", "camera-b"}
    image = services["router"]["image"]
    assert image.startswith("eclipse/zenoh:") and not image.endswith(":latest")
    # published on the host's loopback only: exposing them is a decision (docs/security.md)
    assert services["router"]["ports"] == ["127.0.0.1:7447:7447"]
    cells = {}
    for name, port in (("estimator-a", 8000), ("estimator-b", 8001)):
        est = services[name]
        command = " ".join(est["command"])
        assert "posefuse serve" in command and "--mode client" in command
        assert "tcp/router:7447" in command and "router" in est["depends_on"]
        assert est["ports"] == [f"127.0.0.1:{port}:8000"]
        env = est["environment"]
        assert "POSEFUSE_API_TOKEN" in env and env["POSEFUSE_STATE_DIR"] == "/state"
        assert "state:/state" in est["volumes"]  # shared: a standby takes over from it
        cells[env["POSEFUSE_CELLS"]] = env["POSEFUSE_STANDBY_CELLS"]
    assert cells == {"a": "b", "b": "a"}  # each serves one cell and backs up the other
    for cell in "ab":
        cam = " ".join(services[f"camera-{cell}"]["command"])
        assert "posefuse publish" in cam and "tcp/router:7447" in cam and f"--cell {cell}" in cam


def test_dockerfile_installs_and_serves():
    text = (ROOT / "Dockerfile").read_text()
    assert "pip install" in text and '"posefuse", "serve"' in text
    for folder in ("estimator", "service", "catalogs", "models"):
        assert f"COPY {folder} {folder}" in text
