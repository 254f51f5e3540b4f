"""Pinhole projection on numpy arrays: a camera-frame point's pixel, its Jacobian, and whether
it lies in front of the camera.

The conventions are :mod:`estimator.core.geometry`'s (vectorised over leading batch dimensions,
float64, a wrong shape raises ``ValueError``). Pixels ``uv`` follow OpenCV: (0, 0) is the centre
of the top-left pixel, u right, v down; camera points are in the optical frame (x right, y
down, z forward), metres. Lens distortion is :class:`estimator.core.camera.Camera`'s.
"""

from __future__ import annotations

import numpy as np

from posefuse.estimator.core.geometry import _as_array

__all__ = ["in_front", "project", "project_jacobian"]


def _check_K(K: np.ndarray, name: str) -> np.ndarray:
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"{name}: K must have shape (3, 3), got {K.shape}")
    if not np.array_equal(K[2], [0.0, 0.0, 1.0]):
        raise ValueError(f"{name}: the last row of K must be [0, 0, 1], got {K[2]}")
    return K


def in_front(pts_cam: np.ndarray, min_z: float = 1e-6) -> np.ndarray:
    """Whether camera-frame points are in front of the camera (``z > min_z``, finite).

    Use it to mask points before or after :func:`project`, which does not check depth.

    Args:
        pts_cam: (..., 3) points in the camera optical frame, metres.
        min_z: smallest accepted depth, metres.

    Returns:
        (...) bool.
    """
    pts_cam = _as_array(pts_cam, (3,), "in_front: pts_cam")
    return np.all(np.isfinite(pts_cam), axis=-1) & (pts_cam[..., 2] > min_z)


def project(pts_cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pinhole projection without distortion: ``uv = K[:2] @ [x/z, y/z, 1]``.

    Computes the formula regardless of depth: a point behind the camera (z < 0) gets the
    pixel of its mirror image and z == 0 gives inf/nan, without warnings. Check depth with
    :func:`in_front`.

    Args:
        pts_cam: (..., 3) points in the camera optical frame, metres.
        K: (3, 3) intrinsics ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]``, pixels.

    Returns:
        (..., 2) pixel coordinates ``uv`` (OpenCV: (0, 0) is the centre of the top-left pixel).
    """
    pts_cam = _as_array(pts_cam, (3,), "project: pts_cam")
    K = _check_K(K, "project")
    with np.errstate(divide="ignore", invalid="ignore"):  # z = 0 gives inf / nan, quietly
        xy = pts_cam[..., :2] / pts_cam[..., 2:3]
        return xy @ K[:2, :2].T + K[:2, 2]


def project_jacobian(pts_cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Jacobian of :func:`project` with respect to the camera-frame point.

    ``d uv / d p = K[:2, :2] @ [[1/z, 0, -x/z^2], [0, 1/z, -y/z^2]]``.

    Args:
        pts_cam: (..., 3) points in the camera optical frame, metres.
        K: (3, 3) intrinsics.

    Returns:
        (..., 2, 3), pixels per metre.
    """
    pts_cam = _as_array(pts_cam, (3,), "project_jacobian: pts_cam")
    K = _check_K(K, "project_jacobian")
    x, y, z = pts_cam[..., 0], pts_cam[..., 1], pts_cam[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_z = 1.0 / z
        d = np.zeros(pts_cam.shape[:-1] + (2, 3))
        d[..., 0, 0] = inv_z
        d[..., 1, 1] = inv_z
        d[..., 0, 2] = -x * inv_z * inv_z
        d[..., 1, 2] = -y * inv_z * inv_z
        return np.matmul(K[:2, :2], d)
