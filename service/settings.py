"""Service settings: environment variables ``POSEFUSE_*``, an optional config file, defaults.

Precedence: explicit arguments, then environment variables, then the JSON file named by
``POSEFUSE_CONFIG``, then the defaults below.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Annotated

from pydantic import Field, SecretStr, field_validator, model_validator
from pydantic_settings import (
    BaseSettings,
    JsonConfigSettingsSource,
    NoDecode,
    SettingsConfigDict,
)

from posefuse.service.resources import DEFAULT_CATALOG, DEFAULT_MODEL


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="POSEFUSE_", extra="forbid")

    cell: str = Field("posefuse", description="key prefix of the cell: {cell}/@v1/...")
    # scale-out: the cells this daemon serves (default: ``cell``) and those it backs up
    cells: Annotated[list[str], NoDecode] = Field(
        default_factory=list, description="cells served, comma-separated (default: cell)"
    )
    standby_cells: Annotated[list[str], NoDecode] = Field(
        default_factory=list,
        description="cells this daemon takes over when their daemon disappears",
    )
    takeover_grace_s: float = Field(
        5.0, description="a standby serves a cell nobody claimed within this time of its start"
    )
    # Zenoh transport: peer mode listening on loopback by default; client mode to a router
    mode: str = Field("peer", description="zenoh mode: peer or client")
    listen: list[str] = Field(default_factory=lambda: ["tcp/127.0.0.1:7447"])
    connect: list[str] = Field(default_factory=list)
    multicast_scouting: bool = False
    zenoh_config: Path | None = Field(
        None, description="a zenoh JSON5 config file (TLS, access control) merged first"
    )
    # ROS 2 on the same bus (service/ros2.py): off, bridge (zenoh-bridge-ros2dds keys) or
    # rmw_zenoh (rmw_zenoh_cpp keys and attachments)
    ros2: str = Field("off", description="ROS 2 key layout: off, bridge or rmw_zenoh")
    ros2_domain_id: int = Field(0, description="ROS_DOMAIN_ID of the rmw_zenoh layout")
    # HTTP API
    http_host: str = "127.0.0.1"
    http_port: int = 8000
    api_token: SecretStr | None = Field(
        None,
        description="when set, POST routes (and /events with protect_events) need "
        "'Authorization: Bearer <token>', and Zenoh reset queries carry it as attachment",
    )
    protect_events: bool = False
    max_body_bytes: int = 64 * 1024  # HTTP request bodies larger than this are refused (413)
    # state that survives restarts
    state_dir: Path | None = Field(
        None, description="snapshots of the tracks are kept here and restored at start"
    )
    state_interval_s: float = 5.0
    # estimator
    catalog: Path = Path(DEFAULT_CATALOG)
    model: Path = Path(DEFAULT_MODEL)
    onnx_threads: int = 2
    # the network's threads spin for more work after a run (onnxruntime's default) or sleep:
    # beside the estimator on 2 cores, sleeping gives it the time (docs/performance.md)
    onnx_spin: bool = False
    # input handling (service/sync.py explains each)
    max_payload_bytes: int = 16 * 1024 * 1024
    max_image_pixels: int = 4096 * 4096  # checked on the declared and the header size
    decode_threads: int = 2  # images are decoded off the transport's threads
    # messages waiting for a decoder (service/ingest.py): per camera and kind, served in turn
    ingest_images: int = 4  # images waiting per camera (the oldest dropped)
    ingest_small: int = 1024  # infos, and poses, waiting per camera (the oldest dropped)
    ingest_bytes: int = 256 * 1024 * 1024  # payloads waiting, all cameras together
    image_queue: int = 2  # frames buffered per camera: the latest win when behind
    # verification of rotation hypotheses across views, and refinement (docs/verification.md):
    # deferred, so that no frame waits for it (service/worker.py): a track's pose is published
    # at once from its mixture, then verified when no frame waits (POSEFUSE_VERIFY=0: off)
    verify: bool = True
    # a near-symmetric part's turns (a gear's teeth) judged by the edges that tell them apart
    # (estimator/verification/turns.py); POSEFUSE_VERIFY_TURNS=0: every turn published open,
    # which spares a cell with many such parts in view its cost (docs/verification.md)
    verify_turns: bool = True
    # while frames wait, the share of the worker's time the verification may still take, so
    # that its backlog is never starved; 0: only while no frame waits, which never costs a
    # frame. 0.3 cut the p95 image -> verified pose at 10 Hz with 7 parts from 1.9 to 0.6 s,
    # and cost 12% of the frames (docs/verification.md)
    verify_share: float = Field(0.0, ge=0.0, lt=1.0)
    max_queued_bytes: int = 512 * 1024 * 1024  # decoded frames waiting, all cameras
    max_cameras: int = 16  # at the limit, a camera that never completed a frame yields
    camera_timeout_s: float = 60.0  # silent this long, a camera is forgotten when a slot is needed
    max_future_s: float = Field(
        10.0, gt=0, description="frames and poses stamped further ahead of the clock are refused"
    )
    pose_buffer: int = 200  # camera poses kept per camera for interpolation
    max_pose_gap_ns: int = 200_000_000  # poses further apart than this are not interpolated
    wait_ms: float = 500.0  # how long an image waits for its camera info and a later pose
    reanchor_frames: int = 3  # late frames in a row after which a camera's clock re-anchors
    info_request_s: float = 1.0  # a camera without info is asked for it at most this often

    # the bin the parts lie in (world frame, z up, the inner floor's centre at nbv_bin_center),
    # for next-best-view (estimator/nbv.py), and the default candidates' distances from it
    nbv_bin_center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    nbv_bin_size: tuple[float, float] = (0.42, 0.32)
    nbv_bin_wall_height: float = 0.08
    nbv_distances: tuple[float, ...] = (0.55, 0.75)
    # the nbv_bin_* settings are where the cell's bin really stands: a confirmed track whose
    # centre lies outside it by more than a quarter of its part's diameter is then published
    # tentative (under its floor: detections of different parts that meet there;
    # estimator/core/bin_region.py). Off by default: the defaults above are an example bin,
    # not yours
    bin_known: bool = Field(
        False, description="the nbv_bin_* settings give the real bin: no part lies outside it"
    )

    @field_validator("cells", "standby_cells", mode="before")
    @classmethod
    def _cell_list(cls, v):
        if isinstance(v, str):
            v = [c.strip() for c in v.split(",") if c.strip()]
        return v

    def bin_region(self):
        """The bin of the ``nbv_bin_*`` settings (an
        :class:`~estimator.core.bin_region.BinRegion`); ValueError when it is no bin."""
        import numpy as np  # lazy: settings load without numpy

        from posefuse.estimator.core.bin_region import BinRegion

        T_world_bin = np.eye(4)
        T_world_bin[:3, 3] = self.nbv_bin_center
        return BinRegion(tuple(self.nbv_bin_size), self.nbv_bin_wall_height, T_world_bin)

    def served_cells(self) -> list[tuple[str, bool]]:
        """(cell, primary) of every cell this daemon serves or backs up, in order; ValueError
        when a cell is listed twice."""
        primary = self.cells or [self.cell]
        listed = [*primary, *self.standby_cells]
        if len(set(listed)) != len(listed):
            raise ValueError(f"cells {primary} and standby_cells {self.standby_cells} overlap")
        return [(c, True) for c in primary] + [(c, False) for c in self.standby_cells]

    @field_validator("ros2")
    @classmethod
    def _ros2(cls, v: str) -> str:
        if v not in ("off", "bridge", "rmw_zenoh"):
            raise ValueError("ros2 must be off, bridge or rmw_zenoh")
        return v

    @field_validator("mode")
    @classmethod
    def _mode(cls, v: str) -> str:
        if v not in ("peer", "client", "router"):
            raise ValueError("mode must be peer, client or router")
        return v

    @model_validator(mode="after")
    def _bin(self):
        import math

        if not all(math.isfinite(c) for c in self.nbv_bin_center):
            raise ValueError(f"nbv_bin_center must be finite, got {self.nbv_bin_center}")
        try:
            self.bin_region()
        except ValueError as exc:
            raise ValueError(f"nbv_bin_size, nbv_bin_wall_height: {exc}") from None
        return self

    @classmethod
    def settings_customise_sources(
        cls, settings_cls, init_settings, env_settings, dotenv_settings, file_secret_settings
    ):
        sources = [init_settings, env_settings]
        path = os.environ.get("POSEFUSE_CONFIG")
        if path:
            sources.append(JsonConfigSettingsSource(settings_cls, json_file=path))
        return tuple(sources)


def sync_config(settings: Settings):
    """The FrameSynchronizer configuration of these settings."""
    from posefuse.service.sync import SyncConfig

    return SyncConfig(
        image_queue=settings.image_queue,
        pose_buffer=settings.pose_buffer,
        max_pose_gap_ns=settings.max_pose_gap_ns,
        wait_ns=int(settings.wait_ms * 1e6),
        reanchor_frames=settings.reanchor_frames,
        camera_timeout_ns=int(settings.camera_timeout_s * 1e9),
        max_cameras=settings.max_cameras,
        max_queued_bytes=settings.max_queued_bytes,
        max_future_ns=int(settings.max_future_s * 1e9),
    )


def ingest_config(settings: Settings):
    """The FairIngest configuration of these settings."""
    from posefuse.service.ingest import IngestConfig

    return IngestConfig(
        images_per_camera=settings.ingest_images,
        small_per_camera=settings.ingest_small,
        max_bytes=settings.ingest_bytes,
    )


TRANSPORT_FIELDS = ("mode", "listen", "connect", "multicast_scouting")


def zenoh_config(settings: Settings):
    """The zenoh.Config of these settings (shared transport flags live here only).

    Without a Zenoh config file, the settings (or their defaults) make the whole transport.
    With one (``zenoh_config``: TLS, access control, ...), the file is the base and is kept
    untouched, except for the transport settings given explicitly (argument or environment):
    a default never replaces the file's ``mode``, ``listen`` or ``connect``.
    """
    import zenoh

    if settings.zenoh_config:
        path = Path(settings.zenoh_config)
        if not path.is_file():
            raise ValueError(f"zenoh_config: {path} is not a file")
        conf = zenoh.Config.from_file(str(path))
        given = settings.model_fields_set
    else:
        conf = zenoh.Config()
        given = set(TRANSPORT_FIELDS)
    if "mode" in given:
        conf.insert_json5("mode", json.dumps(settings.mode))
    if "multicast_scouting" in given:
        conf.insert_json5("scouting/multicast/enabled", json.dumps(settings.multicast_scouting))
    if "listen" in given and settings.listen and settings.mode != "client":
        conf.insert_json5("listen/endpoints", json.dumps(settings.listen))
    if "connect" in given and settings.connect:
        conf.insert_json5("connect/endpoints", json.dumps(settings.connect))
    return conf


def wait_for_subscribers(session, keys, timeout_s: float) -> list[str]:
    """Wait until every key in ``keys`` has a matching subscriber (the link is up and the
    subscriptions are known), at most ``timeout_s`` seconds. Messages put before that are
    lost, so a publisher that must not lose its first frames calls this first.

    Returns the keys still without a subscriber (empty when all matched)."""
    import time

    publishers = {key: session.declare_publisher(key) for key in dict.fromkeys(keys)}
    deadline = time.monotonic() + timeout_s
    try:
        while True:
            missing = [k for k, p in publishers.items() if not p.matching_status.matching]
            if not missing or time.monotonic() >= deadline:
                return missing
            time.sleep(0.02)
    finally:
        for p in publishers.values():
            p.undeclare()


def put_camera_message(session, key: str, payload: bytes) -> None:
    """Put one camera message (info, pose or image) so that a busy link delays it instead
    of losing it.

    Zenoh's default for data is to drop a message whose link queue stays full for a
    millisecond: a 200 kB image, fragmented over several batches, was lost that way whenever
    the receiving daemon was slow to read (a loaded machine), while the small poses around it
    got through. A camera's messages wait instead; what the daemon cannot keep up with is
    dropped by its own per-camera queues, where it is counted."""
    import zenoh

    session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)
