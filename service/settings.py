"""Service settings: environment variables ``POSEFUSE_*``, an optional config file, defaults.

Precedence: explicit arguments, then environment variables, then the JSON file named by
``POSEFUSE_CONFIG``, then the defaults below.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, JsonConfigSettingsSource, SettingsConfigDict

from service.resources import DEFAULT_CATALOG, DEFAULT_MODEL


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="POSEFUSE_", extra="forbid")

    cell: str = Field("posefuse", description="key prefix of the cell: {cell}/@v1/...")
    # Zenoh transport: peer mode listening on loopback by default; client mode to a router
    mode: str = Field("peer", description="zenoh mode: peer or client")
    listen: list[str] = Field(default_factory=lambda: ["tcp/127.0.0.1:7447"])
    connect: list[str] = Field(default_factory=list)
    multicast_scouting: bool = False
    zenoh_config: Path | None = Field(
        None, description="a zenoh JSON5 config file (TLS, access control) merged first"
    )
    # HTTP API
    http_host: str = "127.0.0.1"
    http_port: int = 8000
    # estimator
    catalog: Path = Path(DEFAULT_CATALOG)
    model: Path = Path(DEFAULT_MODEL)
    onnx_threads: int = 2
    # input handling
    max_payload_bytes: int = 16 * 1024 * 1024
    image_queue: int = 4  # frames buffered per camera: the latest win when behind
    pose_buffer: int = 200  # camera poses kept per camera for interpolation
    max_pose_gap_ns: int = 200_000_000  # poses further apart than this are not interpolated
    reorder_window_ns: int = 100_000_000  # images older than the newest by more are dropped
    pose_wait_ns: int = 200_000_000  # how long an image waits for a later pose

    @field_validator("mode")
    @classmethod
    def _mode(cls, v: str) -> str:
        if v not in ("peer", "client", "router"):
            raise ValueError("mode must be peer, client or router")
        return v

    @classmethod
    def settings_customise_sources(
        cls, settings_cls, init_settings, env_settings, dotenv_settings, file_secret_settings
    ):
        sources = [init_settings, env_settings]
        path = os.environ.get("POSEFUSE_CONFIG")
        if path:
            sources.append(JsonConfigSettingsSource(settings_cls, json_file=path))
        return tuple(sources)


def zenoh_config(settings: Settings):
    """The zenoh.Config of these settings (shared transport flags live here only)."""
    import zenoh

    if settings.zenoh_config:
        conf = zenoh.Config.from_file(str(settings.zenoh_config))
    else:
        conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(settings.mode))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(settings.multicast_scouting))
    if settings.listen and settings.mode != "client":
        conf.insert_json5("listen/endpoints", json.dumps(settings.listen))
    if settings.connect:
        conf.insert_json5("connect/endpoints", json.dumps(settings.connect))
    return conf
