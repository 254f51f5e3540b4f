"""Pinhole camera with OpenCV's plumb_bob distortion (k1, k2, p1, p2, k3).

Pixel coordinates follow OpenCV: (0, 0) is the centre of the top-left pixel, u to the right,
v down. Points are in the camera's optical frame (x right, y down, z forward), in metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


def _as_points(pts: np.ndarray, dim: int, name: str) -> np.ndarray:
    pts = np.asarray(pts, dtype=np.float64)
    if pts.ndim < 1 or pts.shape[-1] != dim:
        raise ValueError(f"{name} must have shape (..., {dim}), got {pts.shape}")
    return pts


@dataclass(frozen=True, eq=False)
class Camera:
    """Intrinsics of one camera.

    Attributes:
        K: (3, 3) intrinsic matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] in pixels.
        width, height: image size in pixels.
        dist: (5,) plumb_bob coefficients k1, k2, p1, p2, k3 (zeros for an ideal pinhole).
    """

    K: np.ndarray  # (3, 3)
    width: int
    height: int
    dist: np.ndarray = None  # (5,)  # type: ignore[assignment]

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=np.float64)
        if K.shape == (9,):
            K = K.reshape(3, 3)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)):
            raise ValueError(f"Camera: K must be a finite 3x3 matrix, got shape {K.shape}")
        if K[0, 0] <= 0 or K[1, 1] <= 0 or K[2, 2] != 1 or K[1, 0] or K[2, 0] or K[2, 1]:
            raise ValueError(f"Camera: K must be [[fx,s,cx],[0,fy,cy],[0,0,1]] with fx,fy>0: {K}")
        dist = np.zeros(5) if self.dist is None else np.asarray(self.dist, dtype=np.float64)
        if dist.ndim != 1 or dist.size > 5 or not np.all(np.isfinite(dist)):
            raise ValueError(
                f"Camera: dist must hold at most 5 finite plumb_bob coefficients, got {dist}"
            )
        dist = np.concatenate([dist, np.zeros(5 - dist.size)])
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(
                f"Camera: width and height must be positive, got {self.width}x{self.height}"
            )
        K.setflags(write=False)
        dist.setflags(write=False)
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", dist)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    # ------------------------------------------------------------------ properties
    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.dist != 0))

    # ------------------------------------------------------------------ mapping
    def distort_normalized(self, xy: np.ndarray) -> np.ndarray:
        """Apply plumb_bob distortion to normalized image coordinates. (..., 2) -> (..., 2)."""
        xy = _as_points(xy, 2, "xy")
        k1, k2, p1, p2, k3 = self.dist
        x, y = xy[..., 0], xy[..., 1]
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return np.stack([xd, yd], axis=-1)

    def project(self, pts_cam: np.ndarray) -> np.ndarray:
        """Project points in the camera frame to pixels, with distortion.

        Args:
            pts_cam: (..., 3) points in metres; z must be > 0 for a meaningful result.
        Returns:
            uv: (..., 2) pixel coordinates.
        """
        pts = _as_points(pts_cam, 3, "pts_cam")
        xy = pts[..., :2] / pts[..., 2:3]
        if self.has_distortion:
            xy = self.distort_normalized(xy)
        u = self.K[0, 0] * xy[..., 0] + self.K[0, 1] * xy[..., 1] + self.K[0, 2]
        v = self.K[1, 1] * xy[..., 1] + self.K[1, 2]
        return np.stack([u, v], axis=-1)

    def undistort_points(self, uv: np.ndarray) -> np.ndarray:
        """Remove distortion from pixel coordinates, returning ideal pinhole pixels.

        Args:
            uv: (..., 2) distorted pixels.
        Returns:
            (..., 2) pixels that the same rays would hit in a camera with K and no distortion.
        """
        uv = _as_points(uv, 2, "uv")
        if not self.has_distortion:
            return uv.copy()
        flat = uv.reshape(-1, 1, 2)
        # OpenCV's iterative solver; enough iterations to converge for realistic lenses.
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
        if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4.x
            und = cv2.undistortPointsIter(flat, self.K, self.dist, None, self.K, criteria)
        else:  # OpenCV 5 folded the criteria into undistortPoints
            und = cv2.undistortPoints(flat, self.K, self.dist, None, self.K, criteria=criteria)
        return und.reshape(uv.shape)

    def back_project(self, uv: np.ndarray, depth: np.ndarray | float = 1.0) -> np.ndarray:
        """Pixels and depths (z, metres) to points in the camera frame.

        Args:
            uv: (..., 2) pixels (distorted, as seen in the image).
            depth: (...) or scalar z of each point.
        Returns:
            pts_cam: (..., 3); with depth 1 these are the viewing rays scaled to z = 1.
        """
        und = self.undistort_points(uv)
        x = und[..., 0] - self.K[0, 2] - self.K[0, 1] * (und[..., 1] - self.K[1, 2]) / self.K[1, 1]
        x = x / self.K[0, 0]
        y = (und[..., 1] - self.K[1, 2]) / self.K[1, 1]
        ray = np.stack([x, y, np.ones_like(x)], axis=-1)
        return ray * np.asarray(depth, dtype=np.float64)[..., None]

    def ray_directions(self, uv: np.ndarray) -> np.ndarray:
        """Unit viewing rays through pixels. (..., 2) -> (..., 3)."""
        ray = self.back_project(uv, 1.0)
        return ray / np.linalg.norm(ray, axis=-1, keepdims=True)

    def contains(self, uv: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Whether pixels lie inside the image shrunk by ``margin`` pixels. (..., 2) -> (...)."""
        uv = _as_points(uv, 2, "uv")
        return (
            (uv[..., 0] >= -0.5 + margin)
            & (uv[..., 0] <= self.width - 0.5 - margin)
            & (uv[..., 1] >= -0.5 + margin)
            & (uv[..., 1] <= self.height - 0.5 - margin)
        )

    def scaled(self, scale_x: float, scale_y: float | None = None) -> Camera:
        """The camera of the same image resized by (scale_x, scale_y).

        Pixel centres map as u' = (u + 0.5) * s - 0.5, so cx and cy shift with the half-pixel
        offset (what ``cv2.resize`` does). Distortion is unchanged (it lives in normalized
        coordinates).
        """
        sy = scale_x if scale_y is None else scale_y
        if not (scale_x > 0 and sy > 0):
            raise ValueError(f"Camera.scaled: scales must be positive, got {scale_x}, {sy}")
        K = self.K.copy()
        K[0, :] *= scale_x
        K[1, :] *= sy
        K[0, 2] = (self.K[0, 2] + 0.5) * scale_x - 0.5
        K[1, 2] = (self.K[1, 2] + 0.5) * sy - 0.5
        K[2] = [0, 0, 1]
        return Camera(K, round(self.width * scale_x), round(self.height * sy), self.dist.copy())

    def resized(self, width: int, height: int) -> Camera:
        """The camera of the same image resized to ``width`` x ``height`` pixels."""
        return self.scaled(width / self.width, height / self.height)

    @staticmethod
    def from_fov(width: int, height: int, fx: float, fy: float | None = None) -> Camera:
        """An ideal pinhole with the principal point at the image centre."""
        fy = fx if fy is None else fy
        K = np.array([[fx, 0, (width - 1) / 2], [0, fy, (height - 1) / 2], [0, 0, 1.0]])
        return Camera(K, width, height)
