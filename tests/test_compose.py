"""docker-compose.yml and the Dockerfile name what the cell needs (no Docker engine runs here)."""

from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]


def test_compose_file_parses_and_wires_the_cell():
    compose = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    services = compose["services"]
    assert set(services) == {"router", "estimator", "camera"}
    image = services["router"]["image"]
    assert image.startswith("eclipse/zenoh:") and not image.endswith(":latest")
    est = " ".join(services["estimator"]["command"])
    assert "posefuse serve" in est and "--mode client" in est and "tcp/router:7447" in est
    # published on the host's loopback only: exposing them is a decision (docs/security.md)
    assert services["estimator"]["ports"] == ["127.0.0.1:8000:8000"]
    assert services["router"]["ports"] == ["127.0.0.1:7447:7447"]
    env = services["estimator"]["environment"]
    assert "POSEFUSE_API_TOKEN" in env and env["POSEFUSE_STATE_DIR"] == "/state"
    cam = " ".join(services["camera"]["command"])
    assert "posefuse publish" in cam and "tcp/router:7447" in cam
    assert "router" in services["estimator"]["depends_on"]


def test_dockerfile_installs_and_serves():
    text = (ROOT / "Dockerfile").read_text()
    assert "pip install" in text and '"posefuse", "serve"' in text
    for folder in ("estimator", "service", "catalogs", "models"):
        assert f"COPY {folder} {folder}" in text
