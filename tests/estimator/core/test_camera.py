import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from posefuse.estimator.core.camera import Camera

K = np.array([[924.0, 0.0, 644.0], [0.0, 921.0, 361.0], [0.0, 0.0, 1.0]])
DIST = np.array([0.08, -0.15, 0.001, -0.0008, 0.05])

coords = st.floats(-0.35, 0.35)
depths = st.floats(0.2, 3.0)


@given(coords, coords, depths)
@settings(max_examples=60, deadline=None)
def test_project_back_project_round_trip_with_distortion(x, y, z):
    cam = Camera(K, 1280, 720, DIST)
    pts = np.array([x * z, y * z, z])
    uv = cam.project(pts)
    back = cam.back_project(uv, z)
    np.testing.assert_allclose(back, pts, atol=1e-8)


def test_project_matches_opencv():
    cam = Camera(K, 1280, 720, DIST)
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-0.3, 0.3, (50, 2)), rng.uniform(0.4, 1.5, 50)])
    ours = cam.project(pts)
    theirs, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, DIST)
    np.testing.assert_allclose(ours, theirs.reshape(-1, 2), atol=1e-9)


def test_undistort_inverts_distortion():
    cam = Camera(K, 1280, 720, DIST)
    ideal = Camera(K, 1280, 720)
    pts = np.array([[0.1, -0.05, 1.0], [-0.2, 0.15, 0.8], [0.0, 0.0, 2.0]])
    np.testing.assert_allclose(
        cam.undistort_points(cam.project(pts)), ideal.project(pts), atol=1e-8
    )


def test_batch_shapes():
    cam = Camera(K, 1280, 720, DIST)
    pts = np.ones((4, 5, 3))
    assert cam.project(pts).shape == (4, 5, 2)
    assert cam.back_project(np.zeros((4, 5, 2)), np.ones((4, 5))).shape == (4, 5, 3)
    assert cam.ray_directions(np.zeros((7, 2))).shape == (7, 3)


def test_scaled_camera_maps_pixel_centres_like_resize():
    cam = Camera(K, 1280, 720)
    half = cam.scaled(0.5)
    assert (half.width, half.height) == (640, 360)
    pts = np.array([[0.1, -0.05, 1.0], [-0.2, 0.15, 0.8]])
    uv = cam.project(pts)
    np.testing.assert_allclose(half.project(pts), (uv + 0.5) * 0.5 - 0.5, atol=1e-12)
    # A rendered dot moves where cv2.resize moves it.
    img = np.zeros((720, 1280), np.float32)
    img[300:310, 600:610] = 1.0
    small = cv2.resize(img, (640, 360), interpolation=cv2.INTER_AREA)
    ys, xs = np.nonzero(small > 0)
    centre_small = np.array(
        [np.average(xs, weights=small[ys, xs]), np.average(ys, weights=small[ys, xs])]
    )
    np.testing.assert_allclose(
        centre_small, (np.array([604.5, 304.5]) + 0.5) * 0.5 - 0.5, atol=1e-6
    )


def test_resized_and_contains():
    cam = Camera(K, 1280, 720)
    assert cam.resized(320, 180).width == 320
    assert cam.contains(np.array([[0, 0], [1279, 719], [-1, 5], [5, 720]])).tolist() == [
        True,
        True,
        False,
        False,
    ]


@pytest.mark.parametrize(
    "bad",
    [
        np.eye(2),
        np.array([[0.0, 0, 1], [0, 1, 1], [0, 0, 1]]),
        np.array([[1.0, 0, 1], [0, 1, 1], [0, 0, 2]]),
        np.full((3, 3), np.nan),
    ],
)
def test_bad_intrinsics_raise(bad):
    with pytest.raises(ValueError, match="Camera"):
        Camera(bad, 640, 480)


def test_bad_size_and_distortion_raise():
    with pytest.raises(ValueError, match="width and height"):
        Camera(K, 0, 480)
    with pytest.raises(ValueError, match="dist"):
        Camera(K, 640, 480, np.zeros(8))
    with pytest.raises(ValueError, match="pts_cam"):
        Camera(K, 640, 480).project(np.zeros((3, 2)))
