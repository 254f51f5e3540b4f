"""Wire messages: round trips, and one clear DecodeError for every kind of bad input."""

import math

import msgpack
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from posefuse.service.codec import (
    DecodeError,
    decode_camera_info,
    decode_camera_pose,
    decode_image,
    decode_reset,
    encode_camera_info,
    encode_camera_pose,
    encode_image,
    encode_reset,
)
from posefuse.sim.scenes import REALSENSE_1280x720 as CAM


def _pack(d):
    return msgpack.packb(d, use_bin_type=True)


def test_round_trips():
    info = decode_camera_info(encode_camera_info(5, "cam0", CAM))
    np.testing.assert_allclose(info.camera.K, CAM.K)
    assert (info.camera.width, info.camera.height, info.stamp_ns) == (1280, 720, 5)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0.3, -0.2, 1.0]).as_matrix()
    T[:3, 3] = [0.1, 0.2, 0.7]
    pose = decode_camera_pose(encode_camera_pose(7, "cam0", T))
    np.testing.assert_allclose(pose.T_world_cam, T, atol=1e-12)
    image = np.random.default_rng(0).integers(0, 255, (48, 64, 3), dtype=np.uint8)
    for enc in ("png", "rgb8"):
        back = decode_image(encode_image(9, "cam0", image, enc))
        np.testing.assert_array_equal(back.image, image)
    jpeg = decode_image(encode_image(9, "cam0", image, "jpeg"))
    assert jpeg.image.shape == image.shape
    assert decode_reset(encode_reset(class_id=3)).class_id == 3
    assert decode_reset(b"").class_id is None


GOOD_POSE = {"v": 1, "stamp_ns": 1, "frame_id": "c", "t": [0, 0, 0], "q": [0, 0, 0, 1]}


@pytest.mark.parametrize(
    "payload, reason",
    [
        (b"\xc1garbage", "not msgpack"),
        (_pack([1, 2, 3]), "not a map"),
        (_pack({**GOOD_POSE, "v": 2}), "'v' must be 1"),
        (_pack({**GOOD_POSE, "stamp_ns": -1}), "stamp_ns"),
        (_pack({**GOOD_POSE, "stamp_ns": "now"}), "stamp_ns"),
        (_pack({**GOOD_POSE, "t": [0, 0]}), "'t' must be a list of 3"),
        (_pack({**GOOD_POSE, "t": [0, math.nan, 0]}), "finite"),
        (_pack({**GOOD_POSE, "t": [0, math.inf, 0]}), "finite"),
        (_pack({**GOOD_POSE, "q": [0, 0, 0, 2]}), "unit quaternion"),
        (_pack({**GOOD_POSE, "q": [0, 0, 0, 0]}), "unit quaternion"),
        (_pack({**GOOD_POSE, "q": ["a", 0, 0, 1]}), "numbers only"),
        (_pack({**GOOD_POSE, "frame_id": 3}), "frame_id"),
    ],
)
def test_bad_poses(payload, reason):
    with pytest.raises(DecodeError, match=reason):
        decode_camera_pose(payload)


def test_bad_images_and_infos():
    good = {
        "v": 1,
        "stamp_ns": 1,
        "frame_id": "c",
        "encoding": "rgb8",
        "width": 4,
        "height": 2,
        "data": bytes(24),
    }
    assert decode_image(_pack(good)).image.shape == (2, 4, 3)
    with pytest.raises(DecodeError, match="expected 24"):
        decode_image(_pack({**good, "data": bytes(23)}))
    with pytest.raises(DecodeError, match="encoding"):
        decode_image(_pack({**good, "encoding": "yuv"}))
    with pytest.raises(DecodeError, match="JPEG stream"):
        decode_image(_pack({**good, "encoding": "jpeg", "data": b"\xff\xd8nope"}))
    with pytest.raises(DecodeError, match="width"):
        decode_image(_pack({**good, "width": 100_000}))
    with pytest.raises(DecodeError, match="exceeds"):
        decode_image(_pack(good), max_bytes=10)
    info = msgpack.unpackb(encode_camera_info(1, "c", CAM))
    with pytest.raises(DecodeError, match="'K' must be a list of 9"):
        decode_camera_info(_pack({**info, "K": [1, 2, 3]}))
    with pytest.raises(DecodeError, match="fx,fy>0"):
        decode_camera_info(_pack({**info, "K": [0, 0, 640, 0, 924, 360, 0, 0, 1]}))
    with pytest.raises(DecodeError, match="distortion_model"):
        decode_camera_info(_pack({**info, "distortion_model": "fisheye"}))
    with pytest.raises(DecodeError, match="not both"):
        decode_reset(_pack({"v": 1, "class_id": 1, "object_id": "a"}))


@pytest.mark.parametrize(
    ("change", "reason"),
    [
        ({"K": [1e-300, 0, 640, 0, 924, 360, 0, 0, 1]}, "fx = 1e-300 px"),
        ({"K": [1e300, 0, 640, 0, 924, 360, 0, 0, 1]}, "fx = 1e[+]300 px"),
        ({"K": [924, 0, 640, 0, 1e300, 360, 0, 0, 1]}, "fy = 1e[+]300 px"),
        ({"K": [924, 1e300, 640, 0, 924, 360, 0, 0, 1]}, "skew"),
        ({"K": [924, 0, 640, 0, 100, 360, 0, 0, 1]}, "fy / fx"),
        ({"K": [924, 0, 5000, 0, 924, 360, 0, 0, 1]}, "principal point"),
        ({"D": [1e12, 0, 0, 0, 0]}, "distortion coefficient is 1e[+]12"),
    ],
)
def test_camera_infos_no_real_camera_has_are_refused_with_their_reason(change, reason):
    """Well-formed infos that describe no camera (a focal length of 1e-300 or 1e300 pixels, a
    skew of 1e300, a distortion of 1e12) are refused as implausible, with why."""
    info = msgpack.unpackb(encode_camera_info(1, "c", CAM))
    assert decode_camera_info(_pack(info)).camera.width == CAM.width  # the real one passes
    with pytest.raises(DecodeError, match=reason) as refused:
        decode_camera_info(_pack({**info, **change}))
    assert refused.value.code == "implausible"


def test_the_lenses_of_robot_cells_are_plausible():
    """From a 160 degree wide angle to a 2 degree telephoto, with ordinary distortion."""
    from posefuse.service.camera_checks import implausible_intrinsics

    for fov_deg in (2.0, 45.0, 90.0, 160.0):
        f = 320.0 / np.tan(np.radians(fov_deg / 2))
        K = np.array([[f, 0, 320.0], [0, f, 240.0], [0, 0, 1]])
        assert (
            implausible_intrinsics(K, 640, 480, np.array([-0.4, 0.2, 0.001, -0.001, -0.05])) is None
        )


@pytest.mark.parametrize("encoding", ["png", "jpeg"])
def test_decompression_bombs_are_refused_before_decoding(encoding, monkeypatch):
    """20000x20000 declared small: refused from the stream's header, the decoder never called
    and no image allocated; declared honestly, refused by the pixel limit. An honest small
    image goes through the same decoder (so the spy sees the path a bomb would take)."""
    import tracemalloc

    import cv2

    from posefuse.bench.bombs import image_message, jpeg_bomb, png_bomb
    from posefuse.service.image_checks import compressed_image_size

    decoded = []
    real_imdecode = cv2.imdecode

    def spy(buf, flags):
        decoded.append(len(buf))
        if len(decoded) > 1 or len(buf) != len(small):
            raise AssertionError(f"cv2.imdecode called on a {len(buf)}-byte stream")
        return real_imdecode(buf, flags)

    ext = ".png" if encoding == "png" else ".jpg"
    small = cv2.imencode(ext, np.full((24, 32, 3), 128, np.uint8))[1].tobytes()
    stream = png_bomb() if encoding == "png" else jpeg_bomb()
    assert compressed_image_size(stream, encoding) == (20000, 20000)
    monkeypatch.setattr(cv2, "imdecode", spy)
    tracemalloc.start()
    try:
        with pytest.raises(DecodeError, match="header says 20000x20000") as info:
            decode_image(image_message(stream, encoding, 1, declared=(100, 100)))
        assert info.value.code == "header_mismatch"
        with pytest.raises(DecodeError, match="exceeds the limit") as info:
            decode_image(image_message(stream, encoding, 1, declared=(8192, 8192)))
        assert info.value.code == "too_large"
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert decoded == []  # refused before any decoding
    assert peak < 2 * len(stream) + 4 * 2**20, peak  # the message, not a 1.2 GB image
    assert decode_image(image_message(small, encoding, 1, declared=(32, 24))).image.shape == (
        24,
        32,
        3,
    )
    assert decoded == [len(small)]


def test_compressed_image_size_reads_real_headers():
    import cv2

    from posefuse.service.image_checks import compressed_image_size

    image = np.zeros((37, 53, 3), np.uint8)
    for ext, encoding in ((".png", "png"), (".jpg", "jpeg")):
        data = cv2.imencode(ext, image)[1].tobytes()
        assert compressed_image_size(data, encoding) == (53, 37)
    progressive = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])[1].tobytes()
    assert compressed_image_size(progressive, "jpeg") == (53, 37)
    with pytest.raises(DecodeError, match="PNG"):
        compressed_image_size(b"GIF89a" + bytes(30), "png")


def test_sequence_numbers_round_trip():
    image = np.zeros((2, 2, 3), np.uint8)
    assert decode_image(encode_image(5, "c", image, "png", seq=41)).seq == 41
    assert decode_image(encode_image(5, "c", image, "png")).seq is None
    T = np.eye(4)
    assert decode_camera_pose(encode_camera_pose(5, "c", T, seq=7)).seq == 7
    with pytest.raises(DecodeError, match="seq"):
        decode_camera_pose(_pack({**msgpack.unpackb(encode_camera_pose(5, "c", T)), "seq": -1}))


def test_nbv_request_round_trip_and_refusals():
    import msgpack

    from posefuse.service.codec import DecodeError, decode_nbv_request, encode_nbv_request
    from posefuse.sim.scenes import REALSENSE_1280x720 as CAM

    T = np.eye(4)
    T[:3, 3] = [0.1, 0.0, 0.7]
    request = decode_nbv_request(encode_nbv_request([(T, CAM), (T, None)], "cam1", 3))
    assert request.camera_id == "cam1" and request.top_k == 3 and len(request.candidates) == 2
    np.testing.assert_array_equal(request.candidates[0].T_world_cam, T)
    np.testing.assert_array_equal(request.candidates[0].camera.K, CAM.K)
    assert request.candidates[1].camera is None
    assert decode_nbv_request(b"").candidates is None
    bad = [
        {"v": 1, "candidates": []},
        {"v": 1, "candidates": [{"T_world_cam": [1.0] * 16}]},
        {"v": 1, "candidates": [{"T_world_cam": T.reshape(16).tolist(), "K": [1.0] * 9}]},
        {"v": 1, "top_k": 0},
        {"v": 1, "what": 1},
        {"v": 2},
    ]
    for msg in bad:
        with pytest.raises(DecodeError):
            decode_nbv_request(msgpack.packb(msg))


def _png(chunks: list[tuple[bytes, bytes]]) -> bytes:
    import struct
    import zlib

    out = b"\x89PNG\r\n\x1a\n"
    for kind, payload in chunks:
        crc = zlib.crc32(kind + payload) & 0xFFFFFFFF
        out += struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", crc)
    return out


def _ihdr(width: int, height: int) -> tuple[bytes, bytes]:
    import struct

    return b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)


def test_streams_no_camera_writes_are_refused_by_their_structure_before_decoding():
    """A progressive JPEG repeating one scan 20000 times (minutes of CPU for 0.2 MB, every
    header true), thousands of segments, PNGs of tiny chunks, of compressed text, or with image
    data that deflate cannot turn into the declared image: each refused with its own code."""
    import zlib

    import cv2

    from posefuse.bench.bombs import image_message, png_many_chunks, progressive_scan_bomb
    from posefuse.service.image_checks import MAX_JPEG_SCANS, MAX_JPEG_SEGMENTS

    def refused(stream, encoding, size):
        with pytest.raises(DecodeError) as info:
            decode_image(image_message(stream, encoding, 1, declared=size), max_pixels=4096**2)
        return info.value.code

    assert refused(progressive_scan_bomb(), "jpeg", (4096, 4096)) == "jpeg_scans"
    just_over = progressive_scan_bomb(64, 64, MAX_JPEG_SCANS - 9)  # 10 scans + repeats
    assert refused(just_over, "jpeg", (64, 64)) == "jpeg_scans"
    plain = cv2.imencode(".jpg", np.zeros((64, 64, 3), np.uint8))[1].tobytes()
    comments = b"".join(b"\xff\xfe\x00\x04ab" for _ in range(MAX_JPEG_SEGMENTS))
    assert refused(plain[:2] + comments + plain[2:], "jpeg", (64, 64)) == "jpeg_segments"

    assert refused(png_many_chunks(64, 64, 200_000), "png", (64, 64)) == "png_chunks"
    raw = b"".join(b"\0" + bytes(64 * 3) for _ in range(64))
    idat = (b"IDAT", zlib.compress(raw))
    text = (b"zTXt", b"k\0\0" + np.random.default_rng(0).bytes(70_000))
    assert refused(_png([_ihdr(64, 64), text, idat, (b"IEND", b"")]), "png", (64, 64)) == (
        "png_chunks"
    )
    small = _png([_ihdr(4096, 4096), idat, (b"IEND", b"")])  # 38 kB of pixels for 50 MB
    assert refused(small, "png", (4096, 4096)) == "png_ratio"
    padded = (b"IDAT", zlib.compress(raw) + bytes(100_000))
    assert refused(_png([_ihdr(64, 64), padded, (b"IEND", b"")]), "png", (64, 64)) == ("png_ratio")


def test_what_cameras_and_encoders_write_passes_the_structure_checks():
    import cv2

    from posefuse.service.image_checks import check_decode_cost

    rng = np.random.default_rng(1)
    for h, w in ((1, 1), (37, 53), (720, 1280), (2160, 3840)):
        for image in (np.zeros((h, w, 3), np.uint8), rng.integers(0, 256, (h, w, 3), np.uint8)):
            for params in (
                [],
                [cv2.IMWRITE_JPEG_PROGRESSIVE, 1],
                [cv2.IMWRITE_JPEG_PROGRESSIVE, 1, cv2.IMWRITE_JPEG_OPTIMIZE, 1],
                [cv2.IMWRITE_JPEG_RST_INTERVAL, 4],
            ):
                check_decode_cost(cv2.imencode(".jpg", image, params)[1].tobytes(), "jpeg")
            for level in (0, 1, 9):
                data = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, level])[1]
                check_decode_cost(data.tobytes(), "png")
            check_decode_cost(cv2.imencode(".png", image[..., 0])[1].tobytes(), "png")
            wide = image.astype(np.uint16) * 257
            check_decode_cost(cv2.imencode(".png", wide)[1].tobytes(), "png")
            rgba = np.concatenate([image, image[..., :1]], axis=2)
            check_decode_cost(cv2.imencode(".png", rgba)[1].tobytes(), "png")


def test_an_ambiguous_estimate_round_trips_with_its_alternatives():
    from posefuse.estimator.tracker import AlternativeTurn, ObjectEstimate, RotationHypothesis
    from posefuse.service.codec import decode_estimate, encode_estimate

    flip = Rotation.from_rotvec([np.pi, 0.0, 0.0])
    T = np.eye(4)
    T[:3, 3] = [0.1, 0.0, 0.4]
    alternative = AlternativeTurn(flip.as_quat(), 0.42)
    estimate = ObjectEstimate(
        5,
        "screw-001",
        2,
        "chrome_screw",
        T,
        np.eye(6) * 1e-4,
        0.6,
        (RotationHypothesis(np.array([0.0, 0, 0, 1]), 1.0, 3),),
        3,
        "confirmed",
        verified=True,
        alternatives=(alternative,),
        ambiguity=0.42,
    )
    back = decode_estimate(encode_estimate(estimate))
    assert back["ambiguity"] == 0.42 and back["verified"] is True
    assert len(back["alternatives"]) == 1 and back["alternatives"][0]["odds"] == 0.42
    np.testing.assert_allclose(back["alternatives"][0]["q"], flip.as_quat())
    plain = ObjectEstimate(5, "gear-001", 4, "gear", T, np.eye(6), 0.9, (), 3, "confirmed")
    assert not plain.ambiguous
    assert decode_estimate(encode_estimate(plain))["alternatives"] == []
