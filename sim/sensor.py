"""Sensor effects applied to clean renders: RGB noise and blur, depth noise and holes.

The depth model follows what stereo sensors do on shiny parts: noise growing with the square of
the distance, quantisation, missing depth on strong specular highlights and at grazing angles on
metal, and dropouts along depth discontinuities.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class SensorModel:
    rgb_noise_std: float = 2.5  # grey levels, per pixel and channel
    rgb_blur_sigma: float = 0.6  # pixels, optics
    depth_noise_at_1m: float = 0.0015  # metres of std at 1 m, scales with z^2
    depth_hole_saturation: int = 245  # grey level above which a metal pixel has no depth
    depth_grazing_cos: float = 0.25  # metal pixels viewed more obliquely lose depth...
    depth_grazing_drop: float = 0.6  # ...with this probability
    depth_edge_px: int = 1  # dropout band along depth discontinuities
    depth_edge_jump: float = 0.01  # metres: a discontinuity


def apply_rgb(image: np.ndarray, model: SensorModel, rng: np.random.Generator) -> np.ndarray:
    """Blur and noise on a (H, W, 3) uint8 image."""
    out = image.astype(np.float32)
    if model.rgb_blur_sigma > 0:
        out = cv2.GaussianBlur(out, (0, 0), model.rgb_blur_sigma)
    out += rng.normal(0.0, model.rgb_noise_std, size=out.shape).astype(np.float32)
    return np.clip(out + 0.5, 0, 255).astype(np.uint8)


def apply_depth(
    depth: np.ndarray,
    image: np.ndarray,
    normals_cam: np.ndarray,
    metal: np.ndarray,
    model: SensorModel,
    rng: np.random.Generator,
) -> np.ndarray:
    """Noisy depth with holes.

    Args:
        depth: (H, W) float32 clean z in metres, 0 = no surface.
        image: (H, W, 3) uint8 clean render (to find saturated highlights).
        normals_cam: (H, W, 3) unit normals in the camera frame.
        metal: (H, W) bool, pixels on metal parts.
    Returns:
        (H, W) float32 metres, 0 where the sensor has no depth.
    """
    valid = depth > 0
    z = depth.astype(np.float64)
    noisy = z + rng.normal(size=z.shape) * model.depth_noise_at_1m * z**2
    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w]
    rays = np.stack([u - w / 2, v - h / 2, np.full_like(u, max(h, w), dtype=np.float64)], axis=-1)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    cos_view = np.abs(np.einsum("hwc,hwc->hw", normals_cam.astype(np.float64), rays))
    bright = image.max(axis=2) >= model.depth_hole_saturation
    holes = metal & bright
    grazing = metal & (cos_view < model.depth_grazing_cos)
    holes |= grazing & (rng.random(z.shape) < model.depth_grazing_drop)
    if model.depth_edge_px > 0:
        zmax = cv2.dilate(z.astype(np.float32), np.ones((3, 3), np.uint8))
        zmin = -cv2.dilate(-z.astype(np.float32), np.ones((3, 3), np.uint8))
        edge = (zmax - zmin) > model.depth_edge_jump
        if model.depth_edge_px > 1:
            edge = (
                cv2.dilate(edge.astype(np.uint8), np.ones((model.depth_edge_px,) * 2, np.uint8)) > 0
            )
        holes |= edge
    out = np.where(valid & ~holes, noisy, 0.0)
    return out.astype(np.float32)
