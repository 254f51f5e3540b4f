"""ROS 2 on the same bus: estimates out as ROS 2 messages, camera input in, CDR via ``rosbags``.

Two key layouts (``POSEFUSE_ROS2``):

- ``bridge``: that of ``zenoh-bridge-ros2dds``, the topic name without its leading slash as
  the key (``posefuse/a/detections``), the payload CDR with its encapsulation header;
- ``rmw_zenoh``: that of ``rmw_zenoh_cpp`` (Jazzy and later),
  ``{domain_id}/{topic}/{package}::msg::dds_::{Type}_/{RIHS01 type hash}``, each sample with the
  attachment ``rmw_zenoh`` expects: sequence number (int64 LE), source timestamp (int64 LE,
  ns), the publisher's 16-byte gid (Zenoh's ext serialisation of those three fields).

Topics of a cell (``{cell}`` is the cell's key prefix):

===================================  ===================================  ===========
topic                                type                                 direction
===================================  ===================================  ===========
/posefuse/{cell}/detections          vision_msgs/msg/Detection3DArray     out
/tf                                  tf2_msgs/msg/TFMessage               out
/posefuse/{cell}/{cam}/image_raw     sensor_msgs/msg/Image                in
/posefuse/{cell}/{cam}/image_raw/compressed  sensor_msgs/msg/CompressedImage  in
/posefuse/{cell}/{cam}/camera_info   sensor_msgs/msg/CameraInfo           in
/posefuse/{cell}/{cam}/pose          geometry_msgs/msg/PoseStamped        in
===================================  ===================================  ===========

A ``Detection3D`` per updated object: ``id`` = object id; ``results[0]`` the estimate
(``hypothesis.class_id`` = part name, ``score`` = confidence, ``pose.pose`` = T_world_obj in the
cell's world frame, ``pose.covariance`` = our 6x6 in ROS order x, y, z, rotation about X, Y, Z
(fixed world axes), row-major); ``results[1:]`` the other rotation hypotheses of the mixture
(same position, their rotation, ``score`` = their weight); ``bbox`` the part's box in its own
frame, centred at the pose. The TF message carries one ``TransformStamped`` per updated object,
``world`` -> ``{cell}/{object_id}``.

Camera input is turned into the native messages and validated by the native decoders
(:mod:`service.codec`): the same size limits, header checks and errors.
"""

from __future__ import annotations

import struct
from functools import lru_cache

import msgpack
import numpy as np
from scipy.spatial.transform import Rotation

from posefuse.service.codec import VERSION, DecodeError
from posefuse.service.image_checks import compressed_image_size

LAYOUTS = ("off", "bridge", "rmw_zenoh")
DETECTIONS = "vision_msgs/msg/Detection3DArray"
TF = "tf2_msgs/msg/TFMessage"
IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
POSE = "geometry_msgs/msg/PoseStamped"
INPUTS = {  # topic suffix after /posefuse/{cell}/{cam}/ -> (ROS type, native kind)
    "image_raw": (IMAGE, "image"),
    "image_raw/compressed": (COMPRESSED, "image"),
    "camera_info": (CAMERA_INFO, "info"),
    "pose": (POSE, "pose"),
}

# vision_msgs 4.x (Humble and later), not in rosbags' stores: registered from their definitions
VISION_MSGS = {
    "vision_msgs/msg/ObjectHypothesis": "string class_id\nfloat64 score\n",
    "vision_msgs/msg/ObjectHypothesisWithPose": (
        "vision_msgs/ObjectHypothesis hypothesis\ngeometry_msgs/PoseWithCovariance pose\n"
    ),
    "vision_msgs/msg/BoundingBox3D": "geometry_msgs/Pose center\ngeometry_msgs/Vector3 size\n",
    "vision_msgs/msg/Detection3D": (
        "std_msgs/Header header\nvision_msgs/ObjectHypothesisWithPose[] results\n"
        "vision_msgs/BoundingBox3D bbox\nstring id\n"
    ),
    "vision_msgs/msg/Detection3DArray": (
        "std_msgs/Header header\nvision_msgs/Detection3D[] detections\n"
    ),
}


@lru_cache(maxsize=1)
def typestore():
    """rosbags' Jazzy type store with vision_msgs registered."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    types: dict = {}
    for name, text in VISION_MSGS.items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


def dds_type(msgtype: str) -> str:
    """``pkg/msg/Type`` -> ``pkg::msg::dds_::Type_`` (the DDS name rmw_zenoh keys carry)."""
    pkg, kind, name = msgtype.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


class Ros2Layout:
    """Keys and attachments of one layout (``bridge`` or ``rmw_zenoh``) and domain."""

    def __init__(self, layout: str, domain_id: int = 0):
        if layout not in LAYOUTS[1:]:
            raise ValueError(f"ros2 layout must be one of {list(LAYOUTS[1:])}, got {layout!r}")
        if not 0 <= domain_id <= 232:
            raise ValueError(f"ros2_domain_id must be in [0, 232], got {domain_id}")
        self.layout = layout
        self.domain_id = domain_id
        self._seq: dict[str, int] = {}

    def key(self, topic: str, msgtype: str) -> str:
        name = topic.strip("/")
        if self.layout == "bridge":
            return name
        return f"{self.domain_id}/{name}/{dds_type(msgtype)}/{typestore().hash_rihs01(msgtype)}"

    def input_keys(self, cell: str) -> str:
        """The key expression of every camera topic of a cell."""
        prefix = "" if self.layout == "bridge" else f"{self.domain_id}/"
        return f"{prefix}posefuse/{cell}/*/**"

    def parse_input(self, key: str, cell: str) -> tuple[str, str, str] | None:
        """(camera id, ROS type, native kind) of a camera topic's key, or None."""
        prefix = ("" if self.layout == "bridge" else f"{self.domain_id}/") + f"posefuse/{cell}/"
        if not key.startswith(prefix):
            return None
        parts = key[len(prefix) :].split("/")
        if self.layout == "rmw_zenoh":
            if len(parts) < 4:
                return None
            parts = parts[:-2]  # type and hash
        if len(parts) < 2 or not parts[0]:
            return None
        entry = INPUTS.get("/".join(parts[1:]))
        if entry is None:
            return None
        if self.layout == "rmw_zenoh" and key.split("/")[-2] != dds_type(entry[0]):
            return None
        return parts[0], entry[0], entry[1]

    def attachment(self, topic: str, stamp_ns: int, gid: bytes) -> bytes | None:
        """rmw_zenoh's per-sample attachment (None for the bridge layout)."""
        if self.layout == "bridge":
            return None
        seq = self._seq.get(topic, 0) + 1
        self._seq[topic] = seq
        return struct.pack("<qq", seq, stamp_ns) + gid[:16].ljust(16, b"\0")


def parse_attachment(data: bytes) -> tuple[int, int, bytes]:
    """(sequence number, source timestamp ns, gid) of an rmw_zenoh attachment."""
    if len(data) != 32:
        raise ValueError(f"an rmw_zenoh attachment has 32 bytes, got {len(data)}")
    seq, stamp = struct.unpack("<qq", data[:16])
    return seq, stamp, data[16:]


# ---------------------------------------------------------------------------- out
def _time(stamp_ns: int):
    from rosbags.typesys.stores.ros2_jazzy import builtin_interfaces__msg__Time as Time

    return Time(sec=int(stamp_ns // 1_000_000_000), nanosec=int(stamp_ns % 1_000_000_000))


def _pose(T: np.ndarray, q: np.ndarray | None = None):
    from rosbags.typesys.stores.ros2_jazzy import (
        geometry_msgs__msg__Point as Point,
    )
    from rosbags.typesys.stores.ros2_jazzy import (
        geometry_msgs__msg__Pose as Pose,
    )
    from rosbags.typesys.stores.ros2_jazzy import (
        geometry_msgs__msg__Quaternion as Quaternion,
    )

    x, y, z, w = Rotation.from_matrix(T[:3, :3]).as_quat() if q is None else q
    t = T[:3, 3]
    return Pose(
        position=Point(x=float(t[0]), y=float(t[1]), z=float(t[2])),
        orientation=Quaternion(x=float(x), y=float(y), z=float(z), w=float(w)),
    )


def encode_detections(estimates, cell: str, box_sizes: dict[int, np.ndarray], stamp_ns: int):
    """CDR bytes of a Detection3DArray of ``estimates`` (ObjectEstimate) in the world frame.

    box_sizes: per class id, the part's box extent (3,) in metres."""
    from rosbags.typesys.stores.ros2_jazzy import (
        geometry_msgs__msg__PoseWithCovariance as PoseWithCovariance,
    )
    from rosbags.typesys.stores.ros2_jazzy import (
        geometry_msgs__msg__Vector3 as Vector3,
    )
    from rosbags.typesys.stores.ros2_jazzy import std_msgs__msg__Header as Header

    store = typestore()
    T = store.types
    detections = []
    frame = estimates[0].frame_id if estimates else "world"
    for e in estimates:
        results = []
        hypotheses = list(e.hypotheses) or [None]
        for k, h in enumerate(hypotheses):
            if k == 0:
                pose, score = _pose(e.T_world_obj), e.confidence
            else:
                pose, score = _pose(e.T_world_obj, h.q), h.weight
            results.append(
                T["vision_msgs/msg/ObjectHypothesisWithPose"](
                    hypothesis=T["vision_msgs/msg/ObjectHypothesis"](
                        class_id=e.class_name, score=float(score)
                    ),
                    pose=PoseWithCovariance(
                        pose=pose,
                        covariance=np.asarray(e.cov, np.float64).reshape(36).copy(),
                    ),
                )
            )
        size = np.asarray(box_sizes.get(e.class_id, np.zeros(3)), float)
        detections.append(
            T["vision_msgs/msg/Detection3D"](
                header=Header(stamp=_time(e.stamp_ns), frame_id=e.frame_id),
                results=results,
                bbox=T["vision_msgs/msg/BoundingBox3D"](
                    center=_pose(e.T_world_obj),
                    size=Vector3(x=float(size[0]), y=float(size[1]), z=float(size[2])),
                ),
                id=e.object_id,
            )
        )
    msg = T[DETECTIONS](header=Header(stamp=_time(stamp_ns), frame_id=frame), detections=detections)
    return bytes(store.serialize_cdr(msg, DETECTIONS))


def encode_tf(estimates, cell: str) -> bytes:
    """CDR bytes of a TFMessage: world -> ``{cell}/{object_id}`` for every estimate."""
    from rosbags.typesys.stores.ros2_jazzy import (
        geometry_msgs__msg__Quaternion as Quaternion,
    )
    from rosbags.typesys.stores.ros2_jazzy import (
        geometry_msgs__msg__Transform as Transform,
    )
    from rosbags.typesys.stores.ros2_jazzy import (
        geometry_msgs__msg__TransformStamped as TransformStamped,
    )
    from rosbags.typesys.stores.ros2_jazzy import (
        geometry_msgs__msg__Vector3 as Vector3,
    )
    from rosbags.typesys.stores.ros2_jazzy import std_msgs__msg__Header as Header

    store = typestore()
    transforms = []
    for e in estimates:
        x, y, z, w = Rotation.from_matrix(e.T_world_obj[:3, :3]).as_quat()
        t = e.T_world_obj[:3, 3]
        transforms.append(
            TransformStamped(
                header=Header(stamp=_time(e.stamp_ns), frame_id=e.frame_id),
                child_frame_id=f"{cell}/{e.object_id}",
                transform=Transform(
                    translation=Vector3(x=float(t[0]), y=float(t[1]), z=float(t[2])),
                    rotation=Quaternion(x=float(x), y=float(y), z=float(z), w=float(w)),
                ),
            )
        )
    return bytes(store.serialize_cdr(store.types[TF](transforms=transforms), TF))


# ---------------------------------------------------------------------------- in
def _stamp(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def to_native(msgtype: str, payload: bytes, cam_id: str) -> bytes:
    """A ROS 2 camera message (CDR) as the native message of :mod:`service.codec` (msgpack),
    for the native decoder to validate; DecodeError when the CDR is not a ``msgtype``."""
    kind = msgtype.rsplit("/", 1)[-1]
    try:
        msg = typestore().deserialize_cdr(payload, msgtype)
    except Exception as exc:  # rosbags raises several types on truncated or malformed CDR
        raise DecodeError(kind, f"not a CDR {msgtype}: {exc}") from None
    out: dict = {"v": VERSION, "stamp_ns": _stamp(msg.header), "frame_id": cam_id}
    if msgtype == COMPRESSED:
        fmt = msg.format.lower()
        encoding = "png" if "png" in fmt else "jpeg" if ("jpeg" in fmt or "jpg" in fmt) else ""
        if not encoding:
            raise DecodeError(kind, f"format {msg.format!r} is neither jpeg nor png")
        data = bytes(msg.data)
        try:
            width, height = compressed_image_size(data, encoding)
        except DecodeError:
            raise
        except Exception:
            raise DecodeError(kind, f"data is not a {encoding} stream") from None
        out.update(encoding=encoding, width=width, height=height, data=data)
    elif msgtype == IMAGE:
        if msg.encoding not in ("rgb8", "bgr8", "mono8"):
            raise DecodeError(kind, f"encoding {msg.encoding!r} is not rgb8, bgr8 or mono8")
        channels = 1 if msg.encoding == "mono8" else 3
        data = np.asarray(msg.data, np.uint8)
        if msg.step != msg.width * channels:  # rows padded: drop the padding
            if msg.step < msg.width * channels or len(data) != msg.step * msg.height:
                raise DecodeError(kind, f"step {msg.step} does not fit width {msg.width}")
            data = data.reshape(msg.height, msg.step)[:, : msg.width * channels]
        out.update(
            encoding=msg.encoding,
            width=int(msg.width),
            height=int(msg.height),
            data=np.ascontiguousarray(data).tobytes(),
        )
    elif msgtype == CAMERA_INFO:
        out.update(
            width=int(msg.width),
            height=int(msg.height),
            K=[float(v) for v in msg.k],
            distortion_model=msg.distortion_model or "plumb_bob",
            D=[float(v) for v in msg.d],
        )
    elif msgtype == POSE:
        p, q = msg.pose.position, msg.pose.orientation
        out.update(
            parent_frame=msg.header.frame_id or "world",
            t=[float(p.x), float(p.y), float(p.z)],
            q=[float(q.x), float(q.y), float(q.z), float(q.w)],
        )
    else:
        raise DecodeError(kind, f"{msgtype} is not a camera input")
    return msgpack.packb(out, use_bin_type=True)


def encode_camera_info(stamp_ns: int, camera, frame_id: str) -> bytes:
    """CDR bytes of a camera's sensor_msgs/CameraInfo (plumb_bob, ``P = [K | 0]``)."""
    from rosbags.typesys.stores.ros2_jazzy import std_msgs__msg__Header as Header

    store = typestore()
    T = store.types
    d = np.zeros(5) if camera.dist is None else np.asarray(camera.dist, float)
    K = np.asarray(camera.K, float)
    info = T[CAMERA_INFO](
        header=Header(stamp=_time(stamp_ns), frame_id=frame_id),
        height=camera.height,
        width=camera.width,
        distortion_model="plumb_bob",
        d=d.copy(),
        k=K.reshape(9).copy(),
        r=np.eye(3).reshape(9),
        p=np.hstack([K, np.zeros((3, 1))]).reshape(12),
        binning_x=0,
        binning_y=0,
        roi=T["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        ),
    )
    return bytes(store.serialize_cdr(info, CAMERA_INFO))


# ---------------------------------------------------------------------------- rosbag2
class Ros2BagRecorder:
    """``posefuse record --ros2``: a cell's native messages written as a rosbag2 folder (MCAP
    storage, ROS 2 message definitions, ``cdr`` encoding) that ROS 2 tools and ``rosbags``
    read. Same ``write(key, payload, log_time_ns)`` / ``close()`` as the native Recorder.

    Camera info, images (JPEG/PNG as CompressedImage, raw as Image) and poses go to the camera
    topics of the module docstring; each ObjectEstimate to ``/posefuse/{cell}/detections`` (one
    detection) and ``/tf``. A message that does not decode is skipped and counted.
    """

    def __init__(self, path, cell: str):
        from rosbags.rosbag2 import StoragePlugin, Writer

        from posefuse.service.keys import Keys

        self.cell = cell
        self.keys = Keys(cell)
        self.skipped = 0
        self.written = 0
        self._writer = Writer(path, version=8, storage_plugin=StoragePlugin.MCAP)
        self._writer.open()
        self._connections: dict[str, object] = {}

    def _put(self, topic: str, msgtype: str, data: bytes, log_time_ns: int) -> None:
        conn = self._connections.get(topic)
        if conn is None:
            conn = self._writer.add_connection(topic, msgtype, typestore=typestore())
            self._connections[topic] = conn
        self._writer.write(conn, log_time_ns, data)
        self.written += 1

    def write(self, key: str, payload: bytes, log_time_ns: int) -> None:
        from types import SimpleNamespace

        from posefuse.service.codec import decode_camera_info, decode_camera_pose, decode_estimate

        store = typestore()
        T = store.types
        try:
            parsed = self.keys.parse_camera(key)
            if parsed is not None:
                cam, kind = parsed
                base = f"/posefuse/{self.cell}/{cam}"
                raw = msgpack.unpackb(payload)
                stamp = int(raw["stamp_ns"])
                from rosbags.typesys.stores.ros2_jazzy import std_msgs__msg__Header as Header

                header = Header(stamp=_time(stamp), frame_id=str(raw.get("frame_id", cam)))
                if kind == "image":
                    enc = raw["encoding"]
                    data = np.frombuffer(raw["data"], np.uint8)
                    if enc in ("jpeg", "png"):
                        msg = T[COMPRESSED](header=header, format=enc, data=data)
                        self._put(
                            f"{base}/image_raw/compressed",
                            COMPRESSED,
                            bytes(store.serialize_cdr(msg, COMPRESSED)),
                            log_time_ns,
                        )
                    else:
                        ch = 1 if enc == "mono8" else 3
                        msg = T[IMAGE](
                            header=header,
                            height=int(raw["height"]),
                            width=int(raw["width"]),
                            encoding=enc,
                            is_bigendian=0,
                            step=int(raw["width"]) * ch,
                            data=data,
                        )
                        self._put(
                            f"{base}/image_raw",
                            IMAGE,
                            bytes(store.serialize_cdr(msg, IMAGE)),
                            log_time_ns,
                        )
                elif kind == "info":
                    info = decode_camera_info(payload)
                    data = encode_camera_info(stamp, info.camera, header.frame_id)
                    self._put(f"{base}/camera_info", CAMERA_INFO, data, log_time_ns)
                else:
                    pose = decode_camera_pose(payload)
                    msg = T[POSE](
                        header=Header(stamp=_time(stamp), frame_id=pose.parent_frame),
                        pose=_pose(pose.T_world_cam),
                    )
                    self._put(
                        f"{base}/pose", POSE, bytes(store.serialize_cdr(msg, POSE)), log_time_ns
                    )
                return
            if key.startswith(f"{self.keys.root}/objects/"):
                e = decode_estimate(payload)
                est = SimpleNamespace(
                    stamp_ns=e["stamp_ns"],
                    object_id=e["object_id"],
                    class_id=e["class_id"],
                    class_name=e["class_name"],
                    frame_id=e["frame_id"],
                    T_world_obj=_matrix(e["t"], e["q"]),
                    cov=np.asarray(e["cov"], float).reshape(6, 6),
                    confidence=e["confidence"],
                    hypotheses=[
                        SimpleNamespace(q=np.asarray(h["q"]), weight=h["weight"])
                        for h in e["hypotheses"]
                    ],
                )
                self._put(
                    f"/posefuse/{self.cell}/detections",
                    DETECTIONS,
                    encode_detections([est], self.cell, {}, est.stamp_ns),
                    log_time_ns,
                )
                self._put("/tf", TF, encode_tf([est], self.cell), log_time_ns)
                return
            self.skipped += 1  # queries, replies, anything else of the cell
        except Exception:  # a bad message is skipped; the recording goes on
            self.skipped += 1

    def close(self) -> bool:
        self._writer.close()
        return True


def _matrix(t, q) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(q).as_matrix()
    T[:3, 3] = t
    return T
