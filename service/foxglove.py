"""A cell's traffic as Foxglove messages, so that a recording opens in Foxglove.

:class:`FoxgloveMirror` turns each message of the wire (camera info, image, camera pose,
ObjectEstimate, reset, the demo's ground truth) into messages of the Foxglove schemas
``foxglove.CameraCalibration``, ``foxglove.CompressedImage``, ``foxglove.FrameTransform`` and
``foxglove.SceneUpdate``, JSON-encoded (bytes as base64, times as ``{sec, nsec}``), which the
recorder writes on channels of their own beside the raw ones. Topics, under ``/{cell}``:

- ``/{cell}/{cam}/image``, ``/{cell}/{cam}/calibration``: the camera's frames and intrinsics;
- ``/tf``: ``world -> {cam}`` from each camera pose, ``world -> obj/{object_id}`` from each
  estimate;
- ``/{cell}/objects``: a scene entity per object, its mesh (decimated for display) at the
  estimated pose, coloured by status, with class, confidence and views as metadata;
- ``/{cell}/groundtruth``: the true parts of a demo scene.

The schemas written into the file are this module's own statement of the fields it fills;
tests validate the messages against the published Foxglove schemas too.
"""

from __future__ import annotations

import base64
import json
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from posefuse.service.codec import (
    DecodeError,
    decode_camera_info,
    decode_camera_pose,
    decode_estimate,
    decode_groundtruth,
    decode_image_compressed,
    decode_reset,
)
from posefuse.service.keys import Keys

DISPLAY_FACES = 800  # meshes are decimated to this many faces for the scene entities

# ---------------------------------------------------------------------------- schemas

_TIME = {
    "type": "object",
    "properties": {
        "sec": {"type": "integer", "minimum": 0},
        "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999},
    },
    "required": ["sec", "nsec"],
}


def _obj(fields: dict, title: str | None = None) -> dict:
    out = {"type": "object", "properties": fields, "required": list(fields)}
    if title:
        out["title"] = title
    return out


_NUM = {"type": "number"}
_STR = {"type": "string"}
_BOOL = {"type": "boolean"}
_BYTES = {"type": "string", "contentEncoding": "base64"}
_VEC3 = _obj({"x": _NUM, "y": _NUM, "z": _NUM}, "foxglove.Vector3")
_QUAT = _obj({"x": _NUM, "y": _NUM, "z": _NUM, "w": _NUM}, "foxglove.Quaternion")
_POSE = _obj({"position": _VEC3, "orientation": _QUAT}, "foxglove.Pose")
_COLOR = _obj({"r": _NUM, "g": _NUM, "b": _NUM, "a": _NUM}, "foxglove.Color")


def _numbers(n: int | None = None) -> dict:
    out: dict = {"type": "array", "items": _NUM}
    if n is not None:
        out.update(minItems=n, maxItems=n)
    return out


_ARRAY = {"type": "array"}  # primitive lists this module leaves empty
_MODEL = _obj(
    {
        "pose": _POSE,
        "scale": _VEC3,
        "color": _COLOR,
        "override_color": _BOOL,
        "url": _STR,
        "media_type": _STR,
        "data": _BYTES,
    },
    "foxglove.ModelPrimitive",
)
_ENTITY = _obj(
    {
        "timestamp": _TIME,
        "frame_id": _STR,
        "id": _STR,
        "lifetime": _TIME,
        "frame_locked": _BOOL,
        "metadata": {"type": "array", "items": _obj({"key": _STR, "value": _STR})},
        "arrows": _ARRAY,
        "cubes": _ARRAY,
        "spheres": _ARRAY,
        "cylinders": _ARRAY,
        "lines": _ARRAY,
        "triangles": _ARRAY,
        "texts": _ARRAY,
        "models": {"type": "array", "items": _MODEL},
    },
    "foxglove.SceneEntity",
)
_DELETION = _obj(
    {"timestamp": _TIME, "type": {"type": "integer", "enum": [0, 1]}, "id": _STR},
    "foxglove.SceneEntityDeletion",
)

SCHEMAS: dict[str, dict] = {
    "foxglove.CompressedImage": _obj(
        {"timestamp": _TIME, "frame_id": _STR, "data": _BYTES, "format": _STR}
    ),
    "foxglove.CameraCalibration": _obj(
        {
            "timestamp": _TIME,
            "frame_id": _STR,
            "width": {"type": "integer", "minimum": 0},
            "height": {"type": "integer", "minimum": 0},
            "distortion_model": _STR,
            "D": _numbers(),
            "K": _numbers(9),
            "R": _numbers(9),
            "P": _numbers(12),
        }
    ),
    "foxglove.FrameTransform": _obj(
        {
            "timestamp": _TIME,
            "parent_frame_id": _STR,
            "child_frame_id": _STR,
            "translation": _VEC3,
            "rotation": _QUAT,
        }
    ),
    "foxglove.SceneUpdate": _obj(
        {
            "deletions": {"type": "array", "items": _DELETION},
            "entities": {"type": "array", "items": _ENTITY},
        }
    ),
}
for _name, _schema in SCHEMAS.items():
    _schema["title"] = _name
    _schema["$schema"] = "http://json-schema.org/draft-07/schema#"


def schema_bytes(name: str) -> bytes:
    return json.dumps(SCHEMAS[name], sort_keys=True).encode()


# ---------------------------------------------------------------------------- messages


def timestamp(stamp_ns: int) -> dict:
    stamp_ns = max(int(stamp_ns), 0)
    return {"sec": stamp_ns // 1_000_000_000, "nsec": stamp_ns % 1_000_000_000}


def _vec3(v) -> dict:
    return {"x": float(v[0]), "y": float(v[1]), "z": float(v[2])}


def _quat(R: np.ndarray) -> dict:
    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return {"x": float(x), "y": float(y), "z": float(z), "w": float(w)}


def compressed_image(stamp_ns: int, frame_id: str, fmt: str, data: bytes) -> dict:
    return {
        "timestamp": timestamp(stamp_ns),
        "frame_id": frame_id,
        "data": base64.b64encode(data).decode(),
        "format": fmt,
    }


def camera_calibration(stamp_ns: int, frame_id: str, camera) -> dict:
    """camera: estimator.core.camera.Camera (K (3, 3), dist (5,) plumb_bob)."""
    K = np.asarray(camera.K, float)
    P = np.hstack([K, np.zeros((3, 1))])
    return {
        "timestamp": timestamp(stamp_ns),
        "frame_id": frame_id,
        "width": int(camera.width),
        "height": int(camera.height),
        "distortion_model": "plumb_bob",
        "D": [float(x) for x in camera.dist],
        "K": [float(x) for x in K.reshape(-1)],
        "R": [float(x) for x in np.eye(3).reshape(-1)],
        "P": [float(x) for x in P.reshape(-1)],
    }


def frame_transform(stamp_ns: int, parent: str, child: str, T_parent_child: np.ndarray) -> dict:
    """T_parent_child: (4, 4), the pose of ``child`` in ``parent``."""
    return {
        "timestamp": timestamp(stamp_ns),
        "parent_frame_id": parent,
        "child_frame_id": child,
        "translation": _vec3(T_parent_child[:3, 3]),
        "rotation": _quat(T_parent_child[:3, :3]),
    }


def model_entity(
    stamp_ns: int,
    frame_id: str,
    entity_id: str,
    T_frame_obj: np.ndarray,
    glb: bytes,
    rgba: tuple[float, float, float, float],
    metadata: dict[str, str],
) -> dict:
    """A scene entity showing a glTF binary mesh at T_frame_obj (4, 4)."""
    return {
        "timestamp": timestamp(stamp_ns),
        "frame_id": frame_id,
        "id": entity_id,
        "lifetime": {"sec": 0, "nsec": 0},
        "frame_locked": False,
        "metadata": [{"key": k, "value": str(v)} for k, v in metadata.items()],
        "arrows": [],
        "cubes": [],
        "spheres": [],
        "cylinders": [],
        "lines": [],
        "triangles": [],
        "texts": [],
        "models": [
            {
                "pose": {
                    "position": _vec3(T_frame_obj[:3, 3]),
                    "orientation": _quat(T_frame_obj[:3, :3]),
                },
                "scale": {"x": 1.0, "y": 1.0, "z": 1.0},
                "color": dict(zip("rgba", map(float, rgba), strict=True)),
                "override_color": True,
                "url": "",
                "media_type": "model/gltf-binary",
                "data": base64.b64encode(glb).decode(),
            }
        ],
    }


def scene_update(entities: list[dict], deletions: list[dict] | None = None) -> dict:
    return {"deletions": deletions or [], "entities": entities}


def delete_entities(stamp_ns: int, ids: list[str] | None = None) -> list[dict]:
    """Deletions of the given entity ids, or of all entities of the topic (ids None)."""
    if ids is None:
        return [{"timestamp": timestamp(stamp_ns), "type": 1, "id": ""}]
    return [{"timestamp": timestamp(stamp_ns), "type": 0, "id": i} for i in ids]


# ---------------------------------------------------------------------------- the mirror

STATUS_RGBA = {
    "confirmed": (0.15, 0.75, 0.3, 0.9),
    "tentative": (0.95, 0.7, 0.1, 0.6),
}
TRUTH_RGBA = (0.2, 0.45, 0.95, 0.35)


@dataclass(frozen=True)
class FoxgloveMessage:
    topic: str
    schema: str  # a key of SCHEMAS
    message: dict

    def data(self) -> bytes:
        return json.dumps(self.message, separators=(",", ":"), sort_keys=True).encode()


class FoxgloveMirror:
    """Turns (key, payload) messages of a cell into Foxglove messages.

    ``catalog`` (an estimator.core.objects.Catalog) supplies the meshes of the scene entities;
    without it, estimates and ground truth give only transforms. Messages that do not decode
    give nothing (the raw channel still records them). Deterministic: the same messages give
    the same bytes.
    """

    def __init__(self, cell: str = "posefuse", catalog=None):
        self.keys = Keys(cell)
        self.catalog = catalog
        self._glb: dict[int, bytes] = {}
        self._objects: dict[str, int] = {}  # object_id -> class_id, for resets by class
        self.topic_objects = f"/{cell}/objects"
        self.topic_truth = f"/{cell}/groundtruth"

    def mesh_glb(self, class_id: int) -> bytes | None:
        if self.catalog is None or class_id not in self.catalog:
            return None
        if class_id not in self._glb:
            mesh = self.catalog[class_id].mesh
            if len(mesh.faces) > DISPLAY_FACES:
                mesh = mesh.simplify_quadric_decimation(face_count=DISPLAY_FACES)
            self._glb[class_id] = mesh.export(file_type="glb")
        return self._glb[class_id]

    def convert(self, key: str, payload: bytes, log_time_ns: int = 0) -> list[FoxgloveMessage]:
        """log_time_ns stamps the messages that carry no stamp of their own (resets, truth)."""
        try:
            return self._convert(key, payload, int(log_time_ns))
        except (DecodeError, KeyError, TypeError, ValueError):
            return []

    def _convert(self, key: str, payload: bytes, log_time_ns: int) -> list[FoxgloveMessage]:
        keys = self.keys
        cell = keys.cell
        camera = keys.parse_camera(key)
        if camera is not None:
            cam_id, kind = camera
            if kind == "image":
                stamp, frame_id, fmt, data = decode_image_compressed(payload)
                msg = compressed_image(stamp, frame_id, fmt, data)
                return [FoxgloveMessage(f"/{cell}/{cam_id}/image", "foxglove.CompressedImage", msg)]
            if kind == "info":
                info = decode_camera_info(payload)
                msg = camera_calibration(info.stamp_ns, info.frame_id, info.camera)
                return [
                    FoxgloveMessage(
                        f"/{cell}/{cam_id}/calibration", "foxglove.CameraCalibration", msg
                    )
                ]
            pose = decode_camera_pose(payload)
            msg = frame_transform(pose.stamp_ns, pose.parent_frame, pose.frame_id, pose.T_world_cam)
            return [FoxgloveMessage("/tf", "foxglove.FrameTransform", msg)]
        if key.startswith(f"{keys.root}/objects/"):
            return self._estimate(decode_estimate(payload))
        if key == keys.reset:
            return self._reset(payload, log_time_ns)
        if key.startswith(f"{keys.root}/groundtruth/"):
            return self._truth(payload, log_time_ns)
        return []

    def _estimate(self, e: dict) -> list[FoxgloveMessage]:
        T = np.eye(4)
        T[:3, :3] = Rotation.from_quat(e["q"]).as_matrix()
        T[:3, 3] = e["t"]
        stamp, object_id, class_id = int(e["stamp_ns"]), str(e["object_id"]), int(e["class_id"])
        frame = str(e.get("frame_id", "world"))
        self._objects[object_id] = class_id
        out = [
            FoxgloveMessage(
                "/tf",
                "foxglove.FrameTransform",
                frame_transform(stamp, frame, f"obj/{object_id}", T),
            )
        ]
        glb = self.mesh_glb(class_id)
        if glb is not None:
            status = str(e.get("status", "tentative"))
            meta = {
                "class": str(e.get("class_name", class_id)),
                "status": status,
                "confidence": f"{float(e['confidence']):.3f}",
                "n_views": str(e.get("n_views", "")),
                "verified": str(bool(e.get("verified", False))).lower(),
                "ambiguous": str(bool(e.get("alternatives"))).lower(),
            }
            rgba = STATUS_RGBA.get(status, STATUS_RGBA["tentative"])
            entity = model_entity(stamp, frame, object_id, T, glb, rgba, meta)
            out.append(
                FoxgloveMessage(self.topic_objects, "foxglove.SceneUpdate", scene_update([entity]))
            )
        return out

    def _reset(self, payload: bytes, stamp_ns: int) -> list[FoxgloveMessage]:
        request = decode_reset(payload)
        if request.object_id is not None:
            ids = [request.object_id] if request.object_id in self._objects else []
        elif request.class_id is not None:
            ids = sorted(o for o, c in self._objects.items() if c == request.class_id)
        else:
            ids = None
        for o in list(self._objects) if ids is None else ids:
            self._objects.pop(o, None)
        if ids == []:
            return []
        update = scene_update([], delete_entities(stamp_ns, ids))
        return [FoxgloveMessage(self.topic_objects, "foxglove.SceneUpdate", update)]

    def _truth(self, payload: bytes, stamp_ns: int) -> list[FoxgloveMessage]:
        entities = []
        for k, (class_id, T) in enumerate(decode_groundtruth(payload)):
            glb = self.mesh_glb(class_id)
            if glb is not None:
                meta = {"class": self.catalog[class_id].name}
                entities.append(
                    model_entity(stamp_ns, "world", f"truth/{k}", T, glb, TRUTH_RGBA, meta)
                )
        update = scene_update(entities, delete_entities(stamp_ns))
        return [FoxgloveMessage(self.topic_truth, "foxglove.SceneUpdate", update)]
