"""The Foxglove mirror of a cell's messages: what each message becomes, in numbers."""

import base64
import io
import json

import cv2
import msgpack
import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from posefuse.estimator.core.camera import Camera
from posefuse.estimator.tracker import ObjectEstimate
from posefuse.service.codec import (
    encode_camera_info,
    encode_camera_pose,
    encode_estimate,
    encode_groundtruth,
    encode_image,
    encode_reset,
)
from posefuse.service.foxglove import DISPLAY_FACES, FoxgloveMirror
from posefuse.service.keys import Keys

KEYS = Keys("posefuse")


def _pose(seed: int) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    T[:3, 3] = np.random.default_rng(seed).normal(size=3)
    return T


def _matrix(message: dict, position: str, orientation: str) -> np.ndarray:
    T = np.eye(4)
    q = message[orientation]
    T[:3, :3] = Rotation.from_quat([q["x"], q["y"], q["z"], q["w"]]).as_matrix()
    T[:3, 3] = [message[position][a] for a in "xyz"]
    return T


def _estimate(object_id: str, class_id: int, T: np.ndarray, status="confirmed") -> bytes:
    return encode_estimate(
        ObjectEstimate(
            stamp_ns=5 * 10**9 + 7,
            object_id=object_id,
            class_id=class_id,
            class_name="x",
            T_world_obj=T,
            cov=np.eye(6),
            confidence=0.5,
            hypotheses=(),
            n_views=2,
            status=status,
        )
    )


def test_camera_pose_and_info_become_transform_and_calibration():
    T = _pose(1)
    [tf] = FoxgloveMirror().convert(KEYS.camera("cam0", "pose"), encode_camera_pose(3, "cam0", T))
    assert tf.topic == "/tf" and tf.schema == "foxglove.FrameTransform"
    assert tf.message["parent_frame_id"] == "world" and tf.message["child_frame_id"] == "cam0"
    assert np.allclose(_matrix(tf.message, "translation", "rotation"), T, atol=1e-12)
    camera = Camera(np.array([[500.0, 0, 320], [0, 510, 240], [0, 0, 1]]), 640, 480)
    [cal] = FoxgloveMirror().convert(
        KEYS.camera("cam0", "info"), encode_camera_info(3_000_000_123, "cam0", camera)
    )
    m = cal.message
    assert m["timestamp"] == {"sec": 3, "nsec": 123}
    assert m["K"] == [500.0, 0, 320, 0, 510, 240, 0, 0, 1]
    assert m["P"] == [500.0, 0, 320, 0, 0, 510, 240, 0, 0, 0, 1, 0]
    assert (m["width"], m["height"], len(m["D"])) == (640, 480, 5)


def test_images_pass_through_compressed_or_become_png():
    rng = np.random.default_rng(0)
    image = rng.integers(0, 255, (24, 32, 3), dtype=np.uint8)
    jpeg = encode_image(1, "cam0", image, "jpeg")
    [m] = FoxgloveMirror().convert(KEYS.camera("cam0", "image"), jpeg)
    assert base64.b64decode(m.message["data"]) == msgpack.unpackb(jpeg)["data"]
    assert m.message["format"] == "jpeg"
    [m] = FoxgloveMirror().convert(
        KEYS.camera("cam0", "image"), encode_image(1, "cam0", image, "rgb8")
    )
    png = cv2.imdecode(np.frombuffer(base64.b64decode(m.message["data"]), np.uint8), 1)
    assert m.message["format"] == "png" and np.array_equal(png[..., ::-1], image)


def test_estimates_show_the_mesh_at_the_estimated_pose(robi_catalog):
    mirror = FoxgloveMirror("posefuse", robi_catalog)
    T = _pose(2)
    tf, scene = mirror.convert(KEYS.object("a1"), _estimate("a1", 3, T))
    assert tf.message["child_frame_id"] == "obj/a1"
    assert np.allclose(_matrix(tf.message, "translation", "rotation"), T, atol=1e-12)
    [entity] = scene.message["entities"]
    [model] = entity["models"]
    assert entity["id"] == "a1" and entity["frame_id"] == "world"
    assert np.allclose(_matrix(model["pose"], "position", "orientation"), T, atol=1e-12)
    meta = {kv["key"]: kv["value"] for kv in entity["metadata"]}
    assert meta["status"] == "confirmed" and meta["n_views"] == "2"
    mesh = trimesh.load(io.BytesIO(base64.b64decode(model["data"])), file_type="glb", force="mesh")
    assert 0 < len(mesh.faces) <= DISPLAY_FACES
    # the decimated mesh is still the part: same size within a few percent
    assert np.allclose(mesh.extents, robi_catalog[3].mesh.extents, rtol=0.05)
    # the same messages give the same bytes
    again = FoxgloveMirror("posefuse", robi_catalog).convert(
        KEYS.object("a1"), _estimate("a1", 3, T)
    )
    assert [m.data() for m in again] == [tf.data(), scene.data()]
    json.loads(scene.data())


def test_resets_delete_the_entities_they_reset(robi_catalog):
    mirror = FoxgloveMirror("posefuse", robi_catalog)
    for object_id, class_id in (("a", 1), ("b", 2), ("c", 1)):
        mirror.convert(KEYS.object(object_id), _estimate(object_id, class_id, _pose(3)))
    [m] = mirror.convert(KEYS.reset, encode_reset(class_id=1), 9)
    assert [(d["type"], d["id"]) for d in m.message["deletions"]] == [(0, "a"), (0, "c")]
    assert m.message["deletions"][0]["timestamp"] == {"sec": 0, "nsec": 9}
    assert mirror.convert(KEYS.reset, encode_reset(object_id="a"), 10) == []  # already gone
    [m] = mirror.convert(KEYS.reset, encode_reset(), 11)
    assert [(d["type"], d["id"]) for d in m.message["deletions"]] == [(1, "")]


def test_ground_truth_and_bad_messages(robi_catalog):
    mirror = FoxgloveMirror("posefuse", robi_catalog)
    truth = [(1, _pose(4)), (5, _pose(5))]
    [m] = mirror.convert(f"{KEYS.root}/groundtruth/0", encode_groundtruth(0, truth), 42)
    assert m.topic == "/posefuse/groundtruth"
    assert [e["id"] for e in m.message["entities"]] == ["truth/0", "truth/1"]
    assert m.message["deletions"][0]["type"] == 1  # the previous scene's truth goes
    for key in (KEYS.camera("cam0", "pose"), KEYS.camera("cam0", "image"), KEYS.object("x")):
        assert mirror.convert(key, b"\x93garbage") == []
    assert mirror.convert("other/key", encode_reset()) == []
    # without a catalog, an estimate still gives its transform
    assert len(FoxgloveMirror().convert(KEYS.object("a1"), _estimate("a1", 3, _pose(6)))) == 1
