"""The key space of a cell (docs/protocol.md), built in one place."""

from __future__ import annotations

VERSION = "@v1"


class Keys:
    def __init__(self, cell: str = "posefuse"):
        if not cell or any(c in cell for c in "*$?#") or cell.startswith("/") or cell.endswith("/"):
            raise ValueError(f"cell {cell!r} is not a valid key prefix")
        self.cell = cell
        self.root = f"{cell}/{VERSION}"

    def camera(self, cam_id: str, kind: str) -> str:
        if kind not in ("info", "image", "pose"):
            raise ValueError(f"unknown camera key kind {kind!r}")
        if not cam_id or "/" in cam_id or any(c in cam_id for c in "*$?#"):
            raise ValueError(f"camera id {cam_id!r} is not a single key chunk")
        return f"{self.root}/cam/{cam_id}/{kind}"

    @property
    def camera_inputs(self) -> str:
        return f"{self.root}/cam/*/*"

    def object(self, object_id: str) -> str:
        return f"{self.root}/objects/{object_id}"

    @property
    def objects(self) -> str:
        return f"{self.root}/objects/*"

    @property
    def state(self) -> str:
        return f"{self.root}/estimator/state"

    @property
    def reset(self) -> str:
        return f"{self.root}/estimator/reset"

    @property
    def nbv(self) -> str:
        return f"{self.root}/estimator/nbv"

    @property
    def alive(self) -> str:
        return f"{self.root}/estimator/alive"

    def parse_camera(self, key: str) -> tuple[str, str] | None:
        """(cam_id, kind) of a camera input key, or None."""
        prefix = f"{self.root}/cam/"
        if not key.startswith(prefix):
            return None
        rest = key[len(prefix) :].split("/")
        if len(rest) != 2 or rest[1] not in ("info", "image", "pose") or not rest[0]:
            return None
        return rest[0], rest[1]
