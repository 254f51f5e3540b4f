"""The wire messages (docs/protocol.md): msgpack maps with ``"v": 1``, validated on decoding.

This is the only module that turns bytes into messages and messages into bytes. Every decoder
checks types, sizes and finiteness, that rotations are rotations, and the payload size; a bad
message raises :class:`DecodeError` naming the field, and nothing else. A JPEG or PNG image is
checked on its own header and structure before it is decoded (:mod:`service.image_checks`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import msgpack
import numpy as np
from scipy.spatial.transform import Rotation

from posefuse.estimator.core.camera import Camera
from posefuse.service.camera_checks import implausible_intrinsics
from posefuse.service.errors import DecodeError
from posefuse.service.image_checks import check_compressed_image

VERSION = 1
ENCODINGS = ("jpeg", "png", "mono8", "rgb8", "bgr8")
MAX_IMAGE_SIDE = 8192
DEFAULT_MAX_PAYLOAD = 16 * 1024 * 1024
DEFAULT_MAX_PIXELS = 4096 * 4096


@dataclass(frozen=True, eq=False)
class CameraInfoMsg:
    stamp_ns: int
    frame_id: str
    camera: Camera


@dataclass(frozen=True, eq=False)
class ImageMsg:
    """image: (H, W, 3) uint8 RGB, decoded."""

    stamp_ns: int
    frame_id: str
    image: np.ndarray
    seq: int | None = None  # the publisher's image counter, when it sends one


@dataclass(frozen=True, eq=False)
class CameraPoseMsg:
    """T_world_cam: (4, 4) metres (the pose of frame_id in parent_frame)."""

    stamp_ns: int
    frame_id: str
    parent_frame: str
    T_world_cam: np.ndarray
    seq: int | None = None  # the publisher's pose counter, when it sends one


@dataclass(frozen=True)
class ResetRequest:
    class_id: int | None = None
    object_id: str | None = None


MAX_NBV_CANDIDATES = 1000


@dataclass(frozen=True, eq=False)
class NbvCandidate:
    """T_world_cam: (4, 4) metres; camera: its intrinsics, or None for the named camera's."""

    T_world_cam: np.ndarray
    camera: Camera | None = None


@dataclass(frozen=True, eq=False)
class NbvRequest:
    """Candidates to rank (None: the default hemisphere over the bin), the camera whose
    intrinsics they use when they carry none (None: the first camera with an info), how many
    of the best to return."""

    candidates: tuple[NbvCandidate, ...] | None = None
    camera_id: str | None = None
    top_k: int = 10


# ---------------------------------------------------------------------------- helpers


def _unpack(payload: bytes, kind: str, max_bytes: int) -> dict:
    if not isinstance(payload, (bytes, bytearray, memoryview)):
        raise DecodeError(kind, "payload must be bytes")
    if len(payload) > max_bytes:
        raise DecodeError(kind, f"payload of {len(payload)} bytes exceeds {max_bytes}", "too_large")
    try:
        msg = msgpack.unpackb(bytes(payload), raw=False, strict_map_key=True)
    except Exception as exc:  # msgpack raises several unrelated types
        raise DecodeError(kind, f"not msgpack ({type(exc).__name__})") from None
    if not isinstance(msg, dict):
        raise DecodeError(kind, "not a map")
    if msg.get("v") != VERSION:
        raise DecodeError(kind, f"field 'v' must be {VERSION}, got {msg.get('v')!r}")
    return msg


def _int(msg: dict, key: str, kind: str, lo: int = 0, hi: int = 2**63 - 1) -> int:
    v = msg.get(key)
    if not isinstance(v, int) or isinstance(v, bool) or not lo <= v <= hi:
        raise DecodeError(kind, f"field {key!r} must be an integer in [{lo}, {hi}]")
    return v


def _str(msg: dict, key: str, kind: str, max_len: int = 256, default: str | None = None) -> str:
    v = msg.get(key, default)
    if not isinstance(v, str) or len(v) > max_len:
        raise DecodeError(kind, f"field {key!r} must be a string of at most {max_len} characters")
    return v


def _floats(msg: dict, key: str, kind: str, n: int | None = None, max_n: int = 64) -> np.ndarray:
    v = msg.get(key)
    if not isinstance(v, (list, tuple)) or len(v) > max_n or (n is not None and len(v) != n):
        raise DecodeError(kind, f"field {key!r} must be a list of {n or f'<= {max_n}'} numbers")
    if not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v):
        raise DecodeError(kind, f"field {key!r} must hold numbers only")
    a = np.asarray(v, dtype=np.float64)
    if not np.all(np.isfinite(a)):
        raise DecodeError(kind, f"field {key!r} must be finite")
    return a


def _optional_seq(msg: dict, kind: str) -> int | None:
    if msg.get("seq") is None:
        return None
    return _int(msg, "seq", kind, 0, 2**63 - 1)


# ---------------------------------------------------------------------------- decoders


def decode_camera_info(payload: bytes, max_bytes: int = DEFAULT_MAX_PAYLOAD) -> CameraInfoMsg:
    kind = "CameraInfo"
    msg = _unpack(payload, kind, max_bytes)
    stamp = _int(msg, "stamp_ns", kind)
    frame_id = _str(msg, "frame_id", kind)
    width = _int(msg, "width", kind, 1, MAX_IMAGE_SIDE)
    height = _int(msg, "height", kind, 1, MAX_IMAGE_SIDE)
    K = _floats(msg, "K", kind, 9)
    model = _str(msg, "distortion_model", kind, 32, "plumb_bob")
    D = _floats({"D": msg.get("D", [])}, "D", kind, max_n=8)
    if model not in ("plumb_bob", "none", ""):
        raise DecodeError(kind, f"distortion_model {model!r} is not supported (use plumb_bob)")
    if len(D) > 5:
        if np.any(D[5:] != 0):
            raise DecodeError(kind, "only 5 plumb_bob coefficients are supported")
        D = D[:5]
    try:
        camera = Camera(K.reshape(3, 3), width, height, D if len(D) else None)
    except ValueError as exc:
        raise DecodeError(kind, str(exc)) from None
    why = implausible_intrinsics(camera.K, width, height, D)
    if why is not None:
        raise DecodeError(kind, f"no real camera has this: {why}", "implausible")
    return CameraInfoMsg(stamp, frame_id, camera)


def decode_image(
    payload: bytes, max_bytes: int = DEFAULT_MAX_PAYLOAD, max_pixels: int = DEFAULT_MAX_PIXELS
) -> ImageMsg:
    """An Image message, decoded to (H, W, 3) RGB. The declared size is checked against
    ``max_pixels`` and, for PNG and JPEG, against the stream's own header before decoding."""
    kind = "Image"
    msg = _unpack(payload, kind, max_bytes)
    stamp = _int(msg, "stamp_ns", kind)
    frame_id = _str(msg, "frame_id", kind)
    encoding = _str(msg, "encoding", kind, 16)
    width = _int(msg, "width", kind, 1, MAX_IMAGE_SIDE)
    height = _int(msg, "height", kind, 1, MAX_IMAGE_SIDE)
    seq = _optional_seq(msg, kind)
    data = msg.get("data")
    if not isinstance(data, (bytes, bytearray)):
        raise DecodeError(kind, "field 'data' must be bytes")
    if encoding not in ENCODINGS:
        raise DecodeError(kind, f"encoding {encoding!r} is not one of {list(ENCODINGS)}")
    if width * height > max_pixels:
        raise DecodeError(
            kind, f"{width}x{height} exceeds the limit of {max_pixels} pixels", "too_large"
        )
    if encoding in ("jpeg", "png"):
        check_compressed_image(data, encoding, width, height)  # bombs refused undecoded
        buf = np.frombuffer(data, np.uint8)
        image = cv2.imdecode(buf, cv2.IMREAD_COLOR) if len(buf) else None
        if image is None:
            raise DecodeError(kind, f"data is not a decodable {encoding} image")
        image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    else:
        channels = 1 if encoding == "mono8" else 3
        if len(data) != width * height * channels:
            raise DecodeError(
                kind, f"{encoding} data has {len(data)} bytes, expected {width * height * channels}"
            )
        image = np.frombuffer(data, np.uint8).reshape(height, width, channels)
        if encoding == "mono8":
            image = np.repeat(image, 3, axis=2)
        elif encoding == "bgr8":
            image = image[..., ::-1]
        image = np.ascontiguousarray(image)
    if image.shape[:2] != (height, width):
        raise DecodeError(
            kind, f"image is {image.shape[1]}x{image.shape[0]}, the message says {width}x{height}"
        )
    return ImageMsg(stamp, frame_id, image, seq)


def decoders(max_bytes: int = DEFAULT_MAX_PAYLOAD, max_pixels: int = DEFAULT_MAX_PIXELS) -> dict:
    """The decoding function of each camera key kind (``info``, ``image``, ``pose``), with
    these limits: payload bytes -> message, or DecodeError."""
    return {
        "info": lambda p: decode_camera_info(p, max_bytes),
        "image": lambda p: decode_image(p, max_bytes, max_pixels),
        "pose": lambda p: decode_camera_pose(p, max_bytes),
    }


def decode_image_compressed(
    payload: bytes, max_bytes: int = DEFAULT_MAX_PAYLOAD
) -> tuple[int, str, str, bytes]:
    """An Image message as (stamp_ns, frame_id, format, data) with data JPEG or PNG bytes.

    JPEG and PNG payloads are passed through untouched; raw encodings are decoded (validated
    as by :func:`decode_image`) and compressed losslessly as PNG.
    """
    decoded = decode_image(payload, max_bytes)  # the estimator's own validation
    msg = _unpack(payload, "Image", max_bytes)
    if msg["encoding"] in ("jpeg", "png"):
        return decoded.stamp_ns, decoded.frame_id, msg["encoding"], bytes(msg["data"])
    ok, buf = cv2.imencode(".png", cv2.cvtColor(decoded.image, cv2.COLOR_RGB2BGR))
    return decoded.stamp_ns, decoded.frame_id, "png", buf.tobytes()


def decode_camera_pose(payload: bytes, max_bytes: int = DEFAULT_MAX_PAYLOAD) -> CameraPoseMsg:
    kind = "CameraPose"
    msg = _unpack(payload, kind, max_bytes)
    stamp = _int(msg, "stamp_ns", kind)
    frame_id = _str(msg, "frame_id", kind)
    parent = _str(msg, "parent_frame", kind, default="world")
    t = _floats(msg, "t", kind, 3)
    q = _floats(msg, "q", kind, 4)
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > 1e-3:
        raise DecodeError(kind, f"q must be a unit quaternion [x, y, z, w], |q| = {norm:.6g}")
    if np.linalg.norm(t) > 1e4:
        raise DecodeError(kind, "t is more than 10 km from the origin")
    seq = _optional_seq(msg, kind)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(q / norm).as_matrix()
    T[:3, 3] = t
    return CameraPoseMsg(stamp, frame_id, parent, T, seq)


def decode_reset(payload: bytes | None, max_bytes: int = 4096) -> ResetRequest:
    """An empty payload resets everything; otherwise {v, class_id?} or {v, object_id?}."""
    kind = "Reset"
    if payload is None or len(payload) == 0:
        return ResetRequest()
    msg = _unpack(payload, kind, max_bytes)
    class_id = msg.get("class_id")
    object_id = msg.get("object_id")
    if class_id is not None and (not isinstance(class_id, int) or isinstance(class_id, bool)):
        raise DecodeError(kind, "class_id must be an integer")
    if object_id is not None and not isinstance(object_id, str):
        raise DecodeError(kind, "object_id must be a string")
    if class_id is not None and object_id is not None:
        raise DecodeError(kind, "give class_id or object_id, not both")
    return ResetRequest(class_id, object_id)


def nbv_request_from_dict(msg: dict) -> NbvRequest:
    """A next-best-view request from its map (msgpack or JSON); DecodeError naming the field."""
    kind = "NbvRequest"
    unknown = set(msg) - {"v", "candidates", "camera_id", "top_k"}
    if unknown:
        raise DecodeError(kind, f"unknown fields {sorted(unknown)}")
    top_k = _int(msg, "top_k", kind, 1, MAX_NBV_CANDIDATES) if "top_k" in msg else 10
    camera_id = _str(msg, "camera_id", kind) if msg.get("camera_id") is not None else None
    raw = msg.get("candidates")
    if raw is None:
        return NbvRequest(None, camera_id, top_k)
    if not isinstance(raw, list) or not 1 <= len(raw) <= MAX_NBV_CANDIDATES:
        raise DecodeError(kind, f"'candidates' must be a list of 1 to {MAX_NBV_CANDIDATES}")
    out = []
    for i, c in enumerate(raw):
        where = f"{kind} candidate {i}"
        if not isinstance(c, dict):
            raise DecodeError(where, "not a map")
        extra = set(c) - {"T_world_cam", "K", "width", "height"}
        if extra:
            raise DecodeError(where, f"unknown fields {sorted(extra)}")
        T = _floats(c, "T_world_cam", where, 16).reshape(4, 4)
        R = T[:3, :3]
        if (
            not np.allclose(R @ R.T, np.eye(3), atol=1e-4)
            or np.linalg.det(R) < 0.5
            or not np.allclose(T[3], [0, 0, 0, 1])
        ):
            raise DecodeError(where, "'T_world_cam' must be a rigid transform (row-major 4x4)")
        camera = None
        if any(k in c for k in ("K", "width", "height")):
            K = _floats(c, "K", where, 9).reshape(3, 3)
            width = _int(c, "width", where, 1, 65535)
            height = _int(c, "height", where, 1, 65535)
            try:
                camera = Camera(K, width, height)
            except ValueError as exc:
                raise DecodeError(where, str(exc)) from None
        out.append(NbvCandidate(T, camera))
    return NbvRequest(tuple(out), camera_id, top_k)


def decode_nbv_request(payload: bytes | None, max_bytes: int = 1 << 20) -> NbvRequest:
    """An empty payload asks about the default candidates; else {v, candidates?, ...}."""
    if payload is None or len(payload) == 0:
        return NbvRequest()
    return nbv_request_from_dict(_unpack(payload, "NbvRequest", max_bytes))


def encode_nbv_request(
    candidates: list[tuple[np.ndarray, Camera | None]] | None = None,
    camera_id: str | None = None,
    top_k: int = 10,
) -> bytes:
    msg: dict = {"top_k": top_k}
    if camera_id is not None:
        msg["camera_id"] = camera_id
    if candidates is not None:
        items = []
        for T, cam in candidates:
            item = {"T_world_cam": np.asarray(T, float).reshape(16).tolist()}
            if cam is not None:
                item |= {"K": cam.K.reshape(9).tolist(), "width": cam.width, "height": cam.height}
            items.append(item)
        msg["candidates"] = items
    return _pack(msg)


# ---------------------------------------------------------------------------- encoders


def nbv_reply(scores, candidates, tracks, top_k: int) -> dict:
    """The ranked candidates of :func:`estimator.nbv.score_candidates` as a message: the best
    ``top_k``, each with its pose, score (nats) and the objects it would teach something, most
    first (translation and rotation gains in nats, visibility in [0, 1])."""
    ranked = []
    for i in scores.order[:top_k]:
        i = int(i)
        gain = scores.visibility[i] * (scores.translation[i] + scores.rotation[i])
        objects = [
            {
                "object_id": tracks[o].key,
                "translation_gain": float(scores.translation[i, o]),
                "rotation_gain": float(scores.rotation[i, o]),
                "visibility": float(scores.visibility[i, o]),
            }
            for o in np.argsort(-gain, kind="stable")
            if gain[o] > 0
        ]
        ranked.append(
            {
                "index": i,
                "score": float(scores.score[i]),
                "T_world_cam": np.asarray(candidates[i].T_world_cam).reshape(16).tolist(),
                "objects": objects,
            }
        )
    return {"candidates": len(candidates), "ranked": ranked}


def _pack(msg: dict) -> bytes:
    return msgpack.packb({"v": VERSION, **msg}, use_bin_type=True)


def encode_camera_info(stamp_ns: int, frame_id: str, camera: Camera) -> bytes:
    return _pack(
        {
            "stamp_ns": int(stamp_ns),
            "frame_id": frame_id,
            "width": int(camera.width),
            "height": int(camera.height),
            "K": [float(x) for x in camera.K.reshape(-1)],
            "D": [float(x) for x in camera.dist],
            "distortion_model": "plumb_bob",
        }
    )


def encode_image(
    stamp_ns: int,
    frame_id: str,
    image_rgb: np.ndarray,
    encoding: str = "jpeg",
    quality: int = 90,
    seq: int | None = None,
) -> bytes:
    h, w = image_rgb.shape[:2]
    if encoding == "jpeg":
        ok, buf = cv2.imencode(
            ".jpg", cv2.cvtColor(image_rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality]
        )
        data = buf.tobytes()
    elif encoding == "png":
        ok, buf = cv2.imencode(".png", cv2.cvtColor(image_rgb, cv2.COLOR_RGB2BGR))
        data = buf.tobytes()
    elif encoding == "rgb8":
        data = np.ascontiguousarray(image_rgb).tobytes()
    else:
        raise ValueError(f"encode_image: unsupported encoding {encoding!r}")
    return _pack(
        {
            "stamp_ns": int(stamp_ns),
            "frame_id": frame_id,
            "encoding": encoding,
            "width": int(w),
            "height": int(h),
            "data": data,
            **({} if seq is None else {"seq": int(seq)}),
        }
    )


def encode_camera_pose(
    stamp_ns: int,
    frame_id: str,
    T_world_cam: np.ndarray,
    parent_frame: str = "world",
    seq: int | None = None,
) -> bytes:
    q = Rotation.from_matrix(T_world_cam[:3, :3]).as_quat()
    return _pack(
        {
            "stamp_ns": int(stamp_ns),
            "frame_id": frame_id,
            "parent_frame": parent_frame,
            "t": [float(x) for x in T_world_cam[:3, 3]],
            "q": [float(x) for x in q],
            **({} if seq is None else {"seq": int(seq)}),
        }
    )


def estimate_to_dict(e) -> dict:
    """An estimator.tracker.ObjectEstimate as the ObjectEstimate map of the wire (JSON-safe)."""
    q = Rotation.from_matrix(e.T_world_obj[:3, :3]).as_quat()
    return {
        "v": VERSION,
        "stamp_ns": int(e.stamp_ns),
        "object_id": e.object_id,
        "class_id": int(e.class_id),
        "class_name": e.class_name,
        "frame_id": e.frame_id,
        "t": [float(x) for x in e.T_world_obj[:3, 3]],
        "q": [float(x) for x in q],
        "cov": [float(x) for x in e.cov.reshape(-1)],
        "confidence": float(e.confidence),
        "hypotheses": [
            {"q": [float(x) for x in h.q], "weight": float(h.weight), "n": int(h.n)}
            for h in e.hypotheses
        ],
        "n_views": int(e.n_views),
        "status": e.status,
        "verified": bool(e.verified),
        "ambiguity": float(e.ambiguity),
        "alternatives": [
            {"q": [float(x) for x in a.q], "odds": float(a.odds)} for a in e.alternatives
        ],
    }


def encode_estimate(e) -> bytes:
    return msgpack.packb(estimate_to_dict(e), use_bin_type=True)


def encode_estimates(estimates) -> bytes:
    return msgpack.packb(
        {"v": VERSION, "objects": [estimate_to_dict(e) for e in estimates]}, use_bin_type=True
    )


def decode_estimate(payload: bytes) -> dict:
    """An ObjectEstimate map (validated for the fields a client relies on)."""
    kind = "ObjectEstimate"
    msg = _unpack(payload, kind, DEFAULT_MAX_PAYLOAD)
    _str(msg, "object_id", kind)
    _floats(msg, "t", kind, 3)
    _floats(msg, "q", kind, 4)
    _floats(msg, "cov", kind, 36)
    if not math.isfinite(float(msg.get("confidence", float("nan")))):
        raise DecodeError(kind, "confidence must be finite")
    return msg


def encode_reset(class_id: int | None = None, object_id: str | None = None) -> bytes:
    msg = {}
    if class_id is not None:
        msg["class_id"] = int(class_id)
    if object_id is not None:
        msg["object_id"] = object_id
    return _pack(msg)


def encode_groundtruth(scene_id: int, instances: list[tuple[int, np.ndarray]]) -> bytes:
    """The true object poses of a demo scene: instances [(obj_id, T_world_obj (4, 4))]."""
    return _pack(
        {
            "scene_id": scene_id,
            "objects": [
                {"obj_id": int(o), "T_world_obj": [float(x) for x in T.reshape(-1)]}
                for o, T in instances
            ],
        }
    )


def decode_groundtruth(
    payload: bytes, max_bytes: int = DEFAULT_MAX_PAYLOAD
) -> list[tuple[int, np.ndarray]]:
    """The demo's ground truth of a scene: [(obj_id, T_world_obj (4, 4))]."""
    kind = "GroundTruth"
    msg = _unpack(payload, kind, max_bytes)
    objects = msg.get("objects")
    if not isinstance(objects, list):
        raise DecodeError(kind, "field 'objects' must be a list")
    out = []
    for o in objects:
        if not isinstance(o, dict):
            raise DecodeError(kind, "each object must be a map")
        T = _floats(o, "T_world_obj", kind, 16).reshape(4, 4)
        out.append((_int(o, "obj_id", kind), T))
    return out
