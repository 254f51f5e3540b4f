"""ROS 2 on the same bus: our Detection3DArray and TFMessage output read back with rosbags'
CDR deserialiser from the bus (rmw_zenoh layout: keys, type hashes, attachments), and ROS 2
camera input (CDR CompressedImage, CameraInfo, PoseStamped) giving the estimates of the native
path."""

import time

import msgpack
import numpy as np
import pytest
from loopback import ServeProcess, wait_until, zenoh_peer
from rosbags.typesys.stores.ros2_jazzy import builtin_interfaces__msg__Time as Time
from rosbags.typesys.stores.ros2_jazzy import std_msgs__msg__Header as Header
from scipy.spatial.transform import Rotation

from posefuse.clients.camera import scene_messages
from posefuse.estimator.tracker import MultiViewEstimator
from posefuse.evaluation.dataset import load_dataset
from posefuse.service import ros2
from posefuse.service.daemon import Daemon
from posefuse.service.settings import Settings
from posefuse.service.worker import EstimatorWorker, make_detector, now_ns


def _same_rotation(q1, q2, atol=1e-9):
    return min(np.abs(np.subtract(q1, q2)).max(), np.abs(np.add(q1, q2)).max()) <= atol


# ----------------------------------------------------------------------------- keys
def test_key_layouts():
    bridge = ros2.Ros2Layout("bridge")
    assert bridge.key("/posefuse/a/detections", ros2.DETECTIONS) == "posefuse/a/detections"
    assert bridge.parse_input("posefuse/a/cam0/image_raw/compressed", "a") == (
        "cam0",
        ros2.COMPRESSED,
        "image",
    )
    assert bridge.parse_input("posefuse/a/cam0/unknown", "a") is None
    assert bridge.attachment("/tf", 5, b"x" * 16) is None
    rmw = ros2.Ros2Layout("rmw_zenoh", domain_id=7)
    key = rmw.key("/tf", ros2.TF)
    domain, topic, dds, rihs = key.split("/")
    assert (domain, topic, dds) == ("7", "tf", "tf2_msgs::msg::dds_::TFMessage_")
    assert rihs.startswith("RIHS01_") and len(rihs) == 7 + 64 and int(rihs[7:], 16) >= 0
    info = rmw.key("/posefuse/a/cam0/camera_info", ros2.CAMERA_INFO)
    assert rmw.parse_input(info, "a") == ("cam0", ros2.CAMERA_INFO, "info")
    wrong_type = info.replace("CameraInfo_", "Image_")
    assert rmw.parse_input(wrong_type, "a") is None
    assert rmw.parse_input(rmw.key("/posefuse/b/cam0/pose", ros2.POSE), "a") is None
    a1 = ros2.parse_attachment(rmw.attachment("/tf", 123, b"g" * 16))
    a2 = ros2.parse_attachment(rmw.attachment("/tf", 456, b"g" * 16))
    assert (a1[0], a1[1], a2[0], a2[1], a2[2]) == (1, 123, 2, 456, b"g" * 16)
    with pytest.raises(ValueError, match="layout"):
        ros2.Ros2Layout("dds")


# ----------------------------------------------------------------------------- input
def _ros_message(key: str, payload: bytes, cell: str, layout: ros2.Ros2Layout):
    """The ROS 2 message a ROS 2 camera driver (and the robot's TF) would send for one native
    message: same stamp, same JPEG bytes, same intrinsics and pose."""
    store = ros2.typestore()
    T = store.types
    msg = msgpack.unpackb(payload)
    cam, kind = key.split("/")[-2:]
    stamp = Time(sec=msg["stamp_ns"] // 10**9, nanosec=msg["stamp_ns"] % 10**9)
    header = Header(stamp=stamp, frame_id=f"{cam}_optical")
    if kind == "image":
        suffix, msgtype = "image_raw/compressed", ros2.COMPRESSED
        ros = T[msgtype](
            header=header, format=msg["encoding"], data=np.frombuffer(msg["data"], np.uint8)
        )
    elif kind == "info":
        suffix, msgtype = "camera_info", ros2.CAMERA_INFO
        K = np.array(msg["K"], float)
        ros = T[msgtype](
            header=header,
            height=msg["height"],
            width=msg["width"],
            distortion_model="plumb_bob",
            d=np.array(msg.get("D") or [0.0] * 5, float),
            k=K,
            r=np.eye(3).reshape(9),
            p=np.hstack([K.reshape(3, 3), np.zeros((3, 1))]).reshape(12),
            binning_x=0,
            binning_y=0,
            roi=T["sensor_msgs/msg/RegionOfInterest"](
                x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
            ),
        )
    else:
        suffix, msgtype = "pose", ros2.POSE
        t, q = msg["t"], msg["q"]
        ros = T[msgtype](
            header=Header(stamp=stamp, frame_id=msg["parent_frame"]),
            pose=T["geometry_msgs/msg/Pose"](
                position=T["geometry_msgs/msg/Point"](x=t[0], y=t[1], z=t[2]),
                orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
            ),
        )
    topic = f"/posefuse/{cell}/{cam}/{suffix}"
    return layout.key(topic, msgtype), bytes(store.serialize_cdr(ros, msgtype))


def _feed(daemon: Daemon, messages, ros: bool) -> None:
    """Each message through the daemon's own decode and synchronisation, the ready frames
    through the estimator, in arrival order (as its threads would, without the timing)."""
    for key, payload in messages:
        assert (daemon.ingest_ros2 if ros else daemon.ingest)(key, payload)
        daemon.drain()
        while (frame := daemon.sync.pop(now_ns())) is not None:
            daemon.worker.process(frame)
    time.sleep(0.01)
    while (frame := daemon.sync.pop(now_ns() + 10**10)) is not None:
        daemon.worker.process(frame)


@pytest.mark.parametrize("layout", ["bridge", "rmw_zenoh"])
def test_ros2_camera_input_gives_the_estimates_of_the_native_path(
    full_res_dataset, robi_catalog, layout
):
    cell = "ros"
    settings = Settings(cell=cell, ros2=layout)
    dataset = load_dataset(full_res_dataset)
    native = [(k, p) for _, k, p in scene_messages(dataset, 0, cell, "cam0", 2.0)]
    converted = [_ros_message(k, p, cell, ros2.Ros2Layout(layout)) for k, p in native]
    detect = make_detector(settings, robi_catalog)
    shared = MultiViewEstimator(robi_catalog)
    shared.warm_up()

    def daemon():
        estimator = MultiViewEstimator(robi_catalog, banks=shared.banks())
        return Daemon(settings, EstimatorWorker(estimator, detect))

    a, b = daemon(), daemon()
    _feed(a, native, ros=False)
    _feed(b, converted, ros=True)
    ours, theirs = a.worker.snapshot(), b.worker.snapshot()
    assert a.stats.processed == b.stats.processed == len(dataset.scene(0).im_ids)
    assert sum(b.stats.decode_errors.values()) == 0
    assert len(ours) >= 3 and [e.object_id for e in ours] == [e.object_id for e in theirs]
    for e, f in zip(ours, theirs, strict=True):
        np.testing.assert_allclose(f.T_world_obj, e.T_world_obj, atol=1e-9)  # physical: 1 nm
        np.testing.assert_allclose(f.cov, e.cov, rtol=1e-6, atol=1e-15)
        assert (f.n_views, f.status, f.class_id) == (e.n_views, e.status, e.class_id)


def test_bad_ros2_input_is_counted_not_raised(robi_catalog):
    settings = Settings(cell="ros", ros2="bridge")
    daemon = Daemon(settings, EstimatorWorker(MultiViewEstimator(robi_catalog), lambda *a: []))
    assert daemon.ingest_ros2("posefuse/ros/cam0/camera_info", b"\x00\x01garbage")
    assert daemon.ingest_ros2("posefuse/ros/cam0/pose", b"")
    assert not daemon.ingest_ros2("posefuse/ros/cam0/depth", b"")
    daemon.drain()
    assert daemon.stats.decode_reasons == {"info_malformed": 1, "pose_malformed": 1}
    assert daemon.ingest_dropped["not_an_input_key"] == 1


# ----------------------------------------------------------------------------- output
def test_ros2_output_read_back_from_the_bus(full_res_dataset, robi_catalog):
    """posefuse serve with the rmw_zenoh layout; every Detection3DArray and TFMessage on the
    bus is deserialised by rosbags and checked field by field against the native estimate of
    the same object and stamp."""
    cell = "rosout"
    daemon = ServeProcess("--cell", cell, env={"POSEFUSE_ROS2": "rmw_zenoh"})
    layout = ros2.Ros2Layout("rmw_zenoh")
    store = ros2.typestore()
    captured: list = []
    native: dict = {}
    dataset = load_dataset(full_res_dataset)
    try:
        with zenoh_peer(daemon.endpoint) as session:
            session.declare_subscriber(
                "0/**",
                lambda s: captured.append(
                    (str(s.key_expr), s.payload.to_bytes(), s.attachment.to_bytes())
                ),
            )

            def on_native(s):
                # an object may be published twice with one stamp: at once, then verified
                e = msgpack.unpackb(s.payload.to_bytes())
                native.setdefault((e["object_id"], e["stamp_ns"]), []).append(e)

            session.declare_subscriber(f"{cell}/@v1/objects/*", on_native)
            time.sleep(0.5)
            images = 0
            for _, key, payload in scene_messages(dataset, 0, cell, "cam0", 2.0):
                session.put(key, payload)
                images += key.endswith("/image")
                if key.endswith("/pose"):  # as a camera the daemon keeps up with
                    wait_until(lambda n=images: daemon.stats()["frames_handled"] >= n, 60)
            wait_until(
                lambda: daemon.stats()["frames_processed"] == images, 30, context=daemon.stats
            )
            time.sleep(0.5)
    finally:
        daemon.stop()
    det_key = layout.key(f"/posefuse/{cell}/detections", ros2.DETECTIONS)
    tf_key = layout.key("/tf", ros2.TF)
    detections = [(p, a) for k, p, a in captured if k == det_key]
    tfs = [(p, a) for k, p, a in captured if k == tf_key]
    assert {k for k, _, _ in captured} == {det_key, tf_key}
    # one of each per frame that updated objects (a first view only holds its detections),
    # and one per object verified after it
    n_native = sum(len(v) for v in native.values())
    assert len(detections) == len(tfs) >= len({s for _, s in native}) >= images - 1
    assert len(detections) < n_native
    boxes = {k: m.points.max(0) - m.points.min(0) for k, m in robi_catalog.items()}
    n_checked = 0
    for i, ((payload, att), (tf_payload, tf_att)) in enumerate(zip(detections, tfs, strict=True)):
        msg = store.deserialize_cdr(payload, ros2.DETECTIONS)
        stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
        seq, att_stamp, gid = ros2.parse_attachment(att)
        assert (seq, att_stamp, len(gid)) == (i + 1, stamp, 16)
        assert ros2.parse_attachment(tf_att)[:2] == (i + 1, stamp)
        assert msg.header.frame_id == "world"
        tf = store.deserialize_cdr(tf_payload, ros2.TF)
        assert len(tf.transforms) == len(msg.detections) >= 1
        for det, tr in zip(msg.detections, tf.transforms, strict=True):
            e = native[(det.id, stamp)].pop(0)  # in the order published
            assert det.header.frame_id == e["frame_id"] == "world"
            assert det.header.stamp.sec * 10**9 + det.header.stamp.nanosec == stamp
            assert len(det.results) == max(1, len(e["hypotheses"]))
            best = det.results[0]
            assert best.hypothesis.class_id == e["class_name"]
            assert best.hypothesis.score == pytest.approx(e["confidence"], abs=1e-12)
            p, q = best.pose.pose.position, best.pose.pose.orientation
            np.testing.assert_allclose([p.x, p.y, p.z], e["t"], atol=1e-12)
            assert _same_rotation([q.x, q.y, q.z, q.w], e["q"])
            np.testing.assert_allclose(best.pose.covariance, e["cov"], rtol=0, atol=0)
            for r, h in zip(det.results[1:], e["hypotheses"][1:], strict=True):
                assert r.hypothesis.class_id == e["class_name"]
                assert r.hypothesis.score == pytest.approx(h["weight"], abs=1e-12)
                q = r.pose.pose.orientation
                assert _same_rotation([q.x, q.y, q.z, q.w], h["q"])
                np.testing.assert_allclose(
                    [r.pose.pose.position.x, r.pose.pose.position.y, r.pose.pose.position.z],
                    e["t"],
                    atol=1e-12,
                )
            c = det.bbox.center
            np.testing.assert_allclose([c.position.x, c.position.y, c.position.z], e["t"])
            size = [det.bbox.size.x, det.bbox.size.y, det.bbox.size.z]
            np.testing.assert_allclose(size, boxes[e["class_id"]], atol=1e-12)
            assert tr.child_frame_id == f"{cell}/{det.id}" and tr.header.frame_id == "world"
            t, r = tr.transform.translation, tr.transform.rotation
            np.testing.assert_allclose([t.x, t.y, t.z], e["t"], atol=1e-12)
            assert _same_rotation([r.x, r.y, r.z, r.w], e["q"])
            R = Rotation.from_quat([r.x, r.y, r.z, r.w]).as_matrix()
            np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
            n_checked += 1
    assert n_checked == n_native


# ----------------------------------------------------------------------------- rosbag2
def test_record_ros2_writes_a_rosbag2_that_rosbags_reads(full_res_dataset, tmp_path):
    """The native messages of a scene and two estimates through the --ros2 recorder; rosbags'
    Reader opens the folder and every message deserialises to its ROS 2 type."""
    from rosbags.rosbag2 import Reader

    from posefuse.estimator.tracker import ObjectEstimate, RotationHypothesis
    from posefuse.service.codec import decode_camera_info, encode_estimate

    cell = "bag"
    dataset = load_dataset(full_res_dataset)
    messages = [(k, p) for _, k, p in scene_messages(dataset, 0, cell, "cam0", 2.0)]
    T = np.eye(4)
    T[:3, 3] = [0.1, -0.2, 0.3]
    estimate = ObjectEstimate(
        5_000_000_123,
        "gear-1",
        4,
        "gear",
        T,
        np.diag(np.arange(1.0, 7.0)) * 1e-4,
        0.8,
        (
            RotationHypothesis(np.array([0, 0, 0, 1.0]), 0.7, 3),
            RotationHypothesis(np.array([0, 0, 1.0, 0]), 0.3, 1),
        ),
        4,
        "confirmed",
    )
    messages.append((f"{cell}/@v1/objects/gear-1", encode_estimate(estimate)))
    messages.append((f"{cell}/@v1/estimator/state", b"not a camera message"))
    out = tmp_path / "bag"
    recorder = ros2.Ros2BagRecorder(out, cell)
    for k, (key, payload) in enumerate(messages):
        recorder.write(key, payload, 1_000 + k)
    assert recorder.close() and recorder.skipped == 1
    store = ros2.typestore()
    seen: dict = {}
    with Reader(out) as reader:
        assert reader.message_count == len(messages)  # 1 skipped, the estimate twice (tf)
        for conn, log_time, raw in reader.messages():
            msg = store.deserialize_cdr(raw, conn.msgtype)
            seen.setdefault((conn.topic, conn.msgtype), []).append((log_time, msg))
    n_views = len(dataset.scene(0).im_ids)
    assert len(seen[(f"/posefuse/{cell}/cam0/image_raw/compressed", ros2.COMPRESSED)]) == n_views
    infos = seen[(f"/posefuse/{cell}/cam0/camera_info", ros2.CAMERA_INFO)]
    native_info = decode_camera_info(next(p for k, p in messages if k.endswith("/info")))
    np.testing.assert_array_equal(infos[0][1].k.reshape(3, 3), native_info.camera.K)
    assert len(seen[(f"/posefuse/{cell}/cam0/pose", ros2.POSE)]) == sum(
        k.endswith("/pose") for k, _ in messages
    )
    [(_, det)] = seen[(f"/posefuse/{cell}/detections", ros2.DETECTIONS)]
    d = det.detections[0]
    assert d.id == "gear-1" and d.results[0].hypothesis.class_id == "gear"
    assert d.results[0].hypothesis.score == pytest.approx(0.8)
    assert [r.hypothesis.score for r in d.results[1:]] == [pytest.approx(0.3)]
    np.testing.assert_allclose(d.results[0].pose.covariance.reshape(6, 6), estimate.cov)
    [(_, tf)] = seen[("/tf", ros2.TF)]
    assert tf.transforms[0].child_frame_id == f"{cell}/gear-1"
    assert tf.transforms[0].transform.translation.z == pytest.approx(0.3)
