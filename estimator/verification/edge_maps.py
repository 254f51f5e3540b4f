"""Edges of an image, for verifying and refining a pose across views (D2CO): the image side.

Image side (:func:`edge_view`): the view's region of interest is warped to a fixed size at a
scale that makes the part's diameter span a fixed number of pixels (so the costs of a near and a
far view compare), Canny edges are split into orientation bins, and each bin gets a distance
transform. The *directional chamfer distance transform* of Liu et al. (2010), as D2CO uses it,
is then the minimum over bins of the bin's distance plus a penalty per bin of orientation
difference. A point of the model's projected edges (:mod:`estimator.verification.model_edges`),
with its projected direction, reads its cost there (:func:`sample_maps`). The front end's mask
gives a second map: the distance to the mask's boundary, which the model's occluding contour
should follow; and points inside it, which a pose's silhouette should cover.

:func:`edge_view` is two steps: :func:`edge_roi` warps the RoI (cheap), :func:`edge_maps` makes
its maps (the cost). A daemon that verifies between frames keeps the first on the frame's path
and runs the second when the check comes.

Everything is stored per view in ``uint8`` (tenths of the truncation), ``bins * L * L`` bytes
plus ``L * L`` for the mask, and the mask's points in ``int16``: 83 kB a view at the defaults.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = [
    "EdgeConfig",
    "EdgeRoi",
    "EdgeView",
    "edge_maps",
    "edge_roi",
    "edge_view",
    "sample_maps",
]


@dataclass(frozen=True)
class EdgeConfig:
    roi_size: int = 96  # L: RoI side in pixels
    diameter_px: float = 60.0  # the part's diameter in RoI pixels
    bins: int = 8  # orientation bins over [0, pi)
    bin_penalty_px: float = 2.5  # directional chamfer: cost of one bin of orientation difference
    truncate_px: float = 10.0  # distances are clipped here (RoI pixels)
    canny_low: int = 40
    canny_high: int = 100
    crease_deg: float = 35.0  # faces meeting at a sharper angle make a crease
    max_faces: int = 2000  # the mesh is decimated to this many faces first...
    # ...or to twice as many, and so on, until its surface lies within this share of the
    # diameter of the mesh's (95% of samples, both ways; model_edges.decimated)
    max_deviation_frac: float = 0.01
    # edge samples of a model, at most: 1000 cut the step's cost by 30% and lost two chrome
    # screws on the tuning set (docs/lab/2026-12-03-verification-changed-mixture-fewer-samples.md)
    max_points: int = 2000
    # self-occlusion is looked up per viewpoint (OcclusionTable): the camera's direction from the
    # part snapped to one of this many directions (about 3 degrees apart at 4096), its distance
    # to a shell of radii in this ratio, in (1, 4]; 0 casts the rays of every pose instead
    occlusion_directions: int = 4096
    occlusion_shell_ratio: float = 1.25
    # points kept inside the front end's mask, for the silhouette's coverage of it (at most)
    coverage_points: int = 64

    def __post_init__(self) -> None:
        if (
            self.roi_size < 16
            or self.bins < 2
            or self.truncate_px <= 0
            or self.max_points < 1
            or self.bins > 64
            or self.occlusion_directions < 0
            or not 1.0 < self.occlusion_shell_ratio <= 4.0
            or self.coverage_points < 0
        ):
            raise ValueError(f"invalid edge config: {self}")


@dataclass(frozen=True, eq=False)
class EdgeView:
    """What scoring a pose in one view needs, at RoI scale.

    T_cam_world: (4, 4); K_roi: (3, 3) intrinsics of the RoI (the image's, scaled and shifted);
    dcdt: (bins, L, L) uint8 directional chamfer distance, 255 = ``truncate_px``;
    mask_dt: (L, L) uint8 distance to the mask's boundary, same scale, or None without a mask;
    stamp_ns: the view's capture time; mask_points: (Q, 2) int16 RoI pixels (x, y) inside the
    mask (a pixel in from its boundary), spread evenly over it, or None without a mask.
    """

    T_cam_world: np.ndarray
    K_roi: np.ndarray
    dcdt: np.ndarray
    mask_dt: np.ndarray | None
    stamp_ns: int
    mask_points: np.ndarray | None = None

    @property
    def nbytes(self) -> int:
        return (
            self.dcdt.nbytes
            + (0 if self.mask_dt is None else self.mask_dt.nbytes)
            + (0 if self.mask_points is None else self.mask_points.nbytes)
        )


def _roi_affine(K: np.ndarray, t_cam_obj: np.ndarray, diameter: float, config: EdgeConfig):
    """(2, 3) image -> RoI affine map centred on the projected origin, and the RoI's K."""
    x, y, z = t_cam_obj
    u = K[0, 0] * x / z + K[0, 1] * y / z + K[0, 2]
    v = K[1, 1] * y / z + K[1, 2]
    f = 0.5 * (K[0, 0] + K[1, 1])
    s = config.diameter_px / (f * diameter / z)  # RoI pixels per image pixel
    c = (config.roi_size - 1) / 2.0
    A = np.array([[s, 0.0, c - s * u], [0.0, s, c - s * v]])
    K_roi = np.vstack([A, [0.0, 0.0, 1.0]]) @ K
    return A, K_roi


def _covered(image: np.ndarray, A: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """The part of ``image`` that the (2, 3) scale-and-shift map ``A`` (image -> RoI) reads for
    a ``size`` x ``size`` RoI, and the map from that part to the RoI."""
    H, W = image.shape[:2]
    s = A[0, 0]
    lo = (-A[:, 2]) / s  # image (x, y) of RoI pixel (0, 0)
    hi = (size - 1 - A[:, 2]) / s
    # at least one pixel, even where the RoI lies off the image: the map stays exact, and RoI
    # pixels that fall outside the part read the border value
    x0, y0 = (int(np.clip(np.floor(v) - 1, 0, n - 1)) for v, n in zip(lo, (W, H), strict=True))
    x1, y1 = (int(np.clip(np.ceil(v) + 2, 0, n)) for v, n in zip(hi, (W, H), strict=True))
    A_sub = A.copy()
    A_sub[:, 2] += s * np.array([x0, y0])
    return image[y0 : max(y1, y0 + 1), x0 : max(x1, x0 + 1)], A_sub


def _to_u8(d: np.ndarray, truncate: float) -> np.ndarray:
    return np.round(np.minimum(d, truncate) * (255.0 / truncate)).astype(np.uint8)


@dataclass(frozen=True, eq=False)
class EdgeRoi:
    """One view's region of interest around a part, warped, before its maps are made: what
    :func:`edge_maps` needs, kept while a deferred check waits (18 kB a view at the defaults).

    T_cam_world: (4, 4); K_roi: (3, 3); gray: (L, L) uint8; mask: (L, L) uint8 0/1 of the
    front end's mask, or None; stamp_ns: the view's capture time.
    """

    T_cam_world: np.ndarray
    K_roi: np.ndarray
    gray: np.ndarray
    mask: np.ndarray | None
    stamp_ns: int


def edge_roi(
    image: np.ndarray,
    K: np.ndarray,
    T_cam_world: np.ndarray,
    t_cam_obj: np.ndarray,
    diameter: float,
    config: EdgeConfig,
    mask: np.ndarray | None = None,
    stamp_ns: int = 0,
) -> EdgeRoi:
    """The RoI of one view around the part at ``t_cam_obj``, warped to ``roi_size`` pixels
    (the cheap first half of :func:`edge_view`).

    Args:
        image: (H, W, 3) uint8 RGB or (H, W) gray. K: (3, 3). T_cam_world: (4, 4). t_cam_obj:
        (3,) metres, z > 0. mask: (H, W) bool visible mask of the instance, or None.
    """
    # OpenCV's warp crashes the process on a map with NaN or inf in it: refuse them here
    if not (np.all(np.isfinite(t_cam_obj)) and np.all(np.isfinite(K)) and np.isfinite(diameter)):
        raise ValueError("edge_view: K, t_cam_obj and diameter must be finite")
    if t_cam_obj[2] <= 0:
        raise ValueError(f"edge_view: the part is behind the camera (z = {t_cam_obj[2]:.3f} m)")
    L = config.roi_size
    A, K_roi = _roi_affine(K, t_cam_obj, diameter, config)
    # warp first, then convert: only the RoI's pixels are read, not the whole frame's
    roi = cv2.warpAffine(image, A, (L, L), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    if roi.ndim == 3:
        roi = cv2.cvtColor(roi, cv2.COLOR_RGB2GRAY)
    m = None
    if mask is not None:
        sub, A_sub = _covered(np.asarray(mask), A, L)
        m = cv2.warpAffine(
            (sub != 0).astype(np.uint8),
            A_sub,
            (L, L),
            flags=cv2.INTER_NEAREST,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=0,
        )
    return EdgeRoi(np.asarray(T_cam_world, float).copy(), K_roi, roi, m, int(stamp_ns))


def edge_maps(roi: EdgeRoi, config: EdgeConfig) -> EdgeView:
    """The directional chamfer maps of a warped RoI (the costly second half of
    :func:`edge_view`), and those of the mask's boundary."""
    L = config.roi_size
    edges = cv2.Canny(roi.gray, config.canny_low, config.canny_high, L2gradient=True) > 0
    gx = cv2.Sobel(roi.gray, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(roi.gray, cv2.CV_32F, 0, 1, ksize=3)
    # each edge pixel's orientation bin, the rest in no bin (config.bins); the edge runs across
    # the gradient
    b = np.full((L, L), config.bins, np.uint8)
    tangent = np.mod(np.arctan2(gy[edges], gx[edges]) + np.pi / 2, np.pi)
    b[edges] = np.floor(tangent / (np.pi / config.bins) + 0.5).astype(np.uint8) % config.bins
    dt = np.empty((config.bins, L, L), np.float32)
    for k in range(config.bins):
        # the 5x5 mask's distance is within 0.2 px of the exact one where read, and cheaper
        # (docs/lab/2026-12-03-verification-self-occlusion-table.md)
        dt[k] = cv2.distanceTransform((b != k).view(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_5)
    # orientation term: min over bins of distance + penalty * circular bin difference
    lam = np.float32(config.bin_penalty_px)
    for _ in range(2):
        for k in range(config.bins):
            np.minimum(dt[k], dt[k - 1] + lam, out=dt[k])
        for k in reversed(range(config.bins)):
            np.minimum(dt[k], dt[(k + 1) % config.bins] + lam, out=dt[k])
    mask_dt = mask_points = None
    if roi.mask is not None:
        m = roi.mask
        inner = cv2.erode(m, np.ones((3, 3), np.uint8))
        boundary = m & ~inner.astype(bool)
        src = np.where(boundary.astype(bool), 0, 255).astype(np.uint8)
        mask_dt = _to_u8(
            cv2.distanceTransform(src, cv2.DIST_L2, cv2.DIST_MASK_5), config.truncate_px
        )
        mask_points = _spread_points(inner, config.coverage_points)
    return EdgeView(
        roi.T_cam_world,
        roi.K_roi,
        _to_u8(dt, config.truncate_px),
        mask_dt,
        roi.stamp_ns,
        mask_points,
    )


def edge_view(
    image: np.ndarray,
    K: np.ndarray,
    T_cam_world: np.ndarray,
    t_cam_obj: np.ndarray,
    diameter: float,
    config: EdgeConfig,
    mask: np.ndarray | None = None,
    stamp_ns: int = 0,
) -> EdgeView:
    """The directional chamfer maps of one view's RoI around the part at ``t_cam_obj``:
    :func:`edge_maps` of :func:`edge_roi`.

    Args:
        image: (H, W, 3) uint8 RGB. K: (3, 3). T_cam_world: (4, 4). t_cam_obj: (3,) metres,
        z > 0. mask: (H, W) bool visible mask of the instance, or None.
    """
    return edge_maps(
        edge_roi(image, K, T_cam_world, t_cam_obj, diameter, config, mask, stamp_ns), config
    )


def _spread_points(region: np.ndarray, count: int) -> np.ndarray:
    """(Q, 2) int16 (x, y) of at most ``count`` pixels of ``region`` (L, L) nonzero, evenly
    spaced in raster order (every pixel when it has no more)."""
    flat = np.flatnonzero(region)
    if len(flat) > count:
        flat = flat[np.round(np.linspace(0, len(flat) - 1, count)).astype(np.intp)]
    L = region.shape[1]
    return np.stack([flat % L, flat // L], axis=1).astype(np.int16)


def sample_maps(
    maps: np.ndarray,
    channel: np.ndarray | None,
    uv: np.ndarray,
    truncate: float,
    with_gradient: bool = True,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Bilinear samples of uint8 distance maps, in pixels, and their gradients.

    Args:
        maps: (C, L, L) uint8 (255 = ``truncate``) or (L, L). channel: (...) int per sample, or
        None for a single map. uv: (..., 2) pixel coordinates; outside the map reads
        ``truncate`` with a zero gradient.
    Returns:
        value: (...) pixels; grad: (..., 2) d value / d (u, v), None without ``with_gradient``.
    """
    if maps.ndim == 2:
        maps = maps[None]
        channel = None
    L_y, L_x = maps.shape[1:]
    u, v = uv[..., 0], uv[..., 1]
    inside = (u >= 0) & (v >= 0) & (u <= L_x - 1.001) & (v <= L_y - 1.001)
    u = np.where(inside, u, 0.0)
    v = np.where(inside, v, 0.0)
    x0 = np.floor(u).astype(np.intp)
    y0 = np.floor(v).astype(np.intp)
    fx, fy = u - x0, v - y0
    c = np.zeros_like(x0) if channel is None else channel
    flat = maps.reshape(-1)
    base = (c * L_y + y0) * L_x + x0
    # as floats: differences of uint8 reads would wrap around below zero
    v00 = flat[base].astype(np.float64)
    v01 = flat[base + 1].astype(np.float64)
    v10 = flat[base + L_x].astype(np.float64)
    v11 = flat[base + L_x + 1].astype(np.float64)
    top = v00 + fx * (v01 - v00)
    bottom = v10 + fx * (v11 - v10)
    scale = truncate / 255.0
    value = np.where(inside, (top + fy * (bottom - top)) * scale, truncate)
    if not with_gradient:
        return value, None
    grad = np.empty(u.shape + (2,))
    grad[..., 0] = ((1 - fy) * (v01 - v00) + fy * (v11 - v10)) * scale
    grad[..., 1] = (bottom - top) * scale
    grad[~inside] = 0.0
    return value, grad
