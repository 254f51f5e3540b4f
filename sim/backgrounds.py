"""What lies around the parts in a real cell and not in a render: other things, drawn per training
sample (``posefuse train --backgrounds P``).

Every render puts the parts in the same grey bin on the same floor. A photograph holds a table,
a vise, cables, a marker board, printed boxes: edges and colours the network has never seen
beside a part, and which it reads as parts or lets hide them. With probability ``p`` a sample's
pixels that are no part are replaced by procedural clutter: a shaded base, then filled polygons,
ellipses, stripes and lines of random colours, some of them textured with noise, some blurred.
The parts keep their pixels, their outlines are feathered by half a pixel so the paste leaves no
seam to learn. A network trained across such backgrounds learns the parts' own shapes, not the
bin's (the cut-and-paste training of Dwibedi et al., ICCV 2017, with synthetic clutter instead of
photographs: no image collection to ship).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["Backgrounds", "clutter", "paste_on_clutter"]


@dataclass(frozen=True)
class Backgrounds:
    """How often a sample's background is replaced, and how busy the clutter is."""

    p: float = 0.5
    # clutter shapes in a 256 x 256 image; a larger one holds more, as the square root of its
    # area (the shapes grow with the image too)
    shapes: tuple[int, int] = (4, 40)
    noise_std: tuple[float, float] = (0.0, 25.0)  # grey levels of texture on a textured shape
    feather_px: float = 0.5  # Gaussian sigma of the parts' outline in the composite

    def __post_init__(self) -> None:
        if not 0.0 <= self.p <= 1.0:
            raise ValueError(f"Backgrounds: p must be in [0, 1], got {self.p}")
        if not 0 <= self.shapes[0] <= self.shapes[1]:
            raise ValueError(f"Backgrounds: shapes must be 0 <= min <= max, got {self.shapes}")


def _muted_colour(rng: np.random.Generator) -> np.ndarray:
    """(3,) an RGB colour of a random brightness, mostly greyish (a workshop's, not a poster's):
    saturation ``U(0, 1) ** 2``."""
    grey = rng.uniform(15, 240)
    hue = rng.uniform(-grey, 255 - grey, 3)
    return grey + rng.uniform(0, 1) ** 2 * hue


def clutter(height: int, width: int, rng: np.random.Generator, config: Backgrounds) -> np.ndarray:
    """(height, width, 3) uint8 RGB procedural clutter, drawn from ``rng`` alone: a shaded base,
    shapes drawn straight into it with OpenCV, then texture and focus over the whole."""
    base = _muted_colour(rng)
    slope = rng.uniform(-60, 60, (2, 3))  # a linear shade across the image, per channel
    ys = np.linspace(-0.5, 0.5, height, dtype=np.float32)[:, None, None]
    xs = np.linspace(-0.5, 0.5, width, dtype=np.float32)[None, :, None]
    shade = np.clip(base + ys * slope[0] + xs * slope[1], 0, 255)
    image = np.ascontiguousarray(np.broadcast_to(shade, (height, width, 3)).astype(np.uint8))
    area = height * width / (256.0 * 256.0)
    n = int(rng.integers(config.shapes[0], config.shapes[1] + 1) * max(np.sqrt(area), 0.5))
    scale = float(max(height, width))
    lo, hi = np.array([0.0, 0.0]), np.array([width, height], float)
    for _ in range(n):
        colour = tuple(float(c) for c in _muted_colour(rng))
        kind = rng.integers(4)
        if kind == 0:  # a filled polygon
            k = int(rng.integers(3, 8))
            centre = rng.uniform(lo, hi)
            angles = np.sort(rng.uniform(0, 2 * np.pi, k))
            radii = rng.uniform(0.03, 0.3) * scale * rng.uniform(0.4, 1.0, k)
            pts = centre + np.stack([np.cos(angles), np.sin(angles)], 1) * radii[:, None]
            cv2.fillPoly(image, [np.round(pts).astype(np.int32)], colour, cv2.LINE_AA)
        elif kind == 1:  # an ellipse, filled or a ring
            centre = tuple(int(v) for v in rng.uniform(lo, hi))
            axes = tuple(max(int(v), 1) for v in rng.uniform(0.01, 0.2, 2) * scale)
            thickness = -1 if rng.random() < 0.6 else int(rng.integers(1, 6))
            angle = float(rng.uniform(0, 180))
            cv2.ellipse(image, centre, axes, angle, 0, 360, colour, thickness, cv2.LINE_AA)
        elif kind == 2:  # parallel strokes (a grille, a printed pattern, a ruler)
            centre = rng.uniform(lo, hi)
            along = rng.uniform(0, np.pi)
            u = np.array([np.cos(along), np.sin(along)])
            v = np.array([-u[1], u[0]])
            length = rng.uniform(0.05, 0.4) * scale
            period = rng.uniform(4, 30)
            thickness = int(rng.integers(1, max(2, int(period / 2))))
            for j in range(int(rng.integers(3, 12))):
                mid = centre + v * period * j
                p0, p1 = mid - u * length / 2, mid + u * length / 2
                cv2.line(
                    image,
                    tuple(int(c) for c in p0),
                    tuple(int(c) for c in p1),
                    colour,
                    thickness,
                    cv2.LINE_AA,
                )
        else:  # a line (a cable, an edge of a fixture)
            p0 = tuple(int(c) for c in rng.uniform(lo, hi))
            p1 = tuple(int(c) for c in rng.uniform(lo, hi))
            cv2.line(image, p0, p1, colour, int(rng.integers(1, 8)), cv2.LINE_AA)
    out = image.astype(np.float32)
    # texture: a smooth brightness field (shading, stains) and fine noise (grain, print)
    coarse = rng.normal(1.0, 0.15, (4, 4)).astype(np.float32)
    out *= cv2.resize(coarse, (width, height), interpolation=cv2.INTER_CUBIC)[..., None]
    std = rng.uniform(*config.noise_std)
    noise_seed = int(rng.integers(2**31))
    out += np.random.default_rng(noise_seed).normal(0.0, std, (height, width, 1)).astype(np.float32)
    sigma = float(rng.uniform(0.5, 2.5))
    if rng.random() < 0.5:  # out of focus behind the parts
        out = cv2.GaussianBlur(out, (0, 0), sigma)
    return np.clip(out, 0, 255).astype(np.uint8)


def paste_on_clutter(
    image: np.ndarray, part_alpha: np.ndarray, rng: np.random.Generator, config: Backgrounds
) -> np.ndarray:
    """With probability ``config.p``: ``image`` (H, W, 3) uint8 over :func:`clutter`, where
    ``part_alpha`` (H, W), bool or float in [0, 1], is how much of each pixel is part (0: none,
    replaced by clutter); else the image as it is. One coin is drawn per call and the clutter's
    own draws from a seed drawn from ``rng`` whether or not it applies, so a seeded stream
    advances the same either way."""
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"paste_on_clutter: expected (H, W, 3) uint8, got {image.shape}")
    if part_alpha.shape != image.shape[:2]:
        raise ValueError(
            f"paste_on_clutter: alpha {part_alpha.shape} does not match image {image.shape[:2]}"
        )
    apply = rng.random() < config.p
    seed = int(rng.integers(2**31))
    if not apply:
        return image
    background = clutter(*image.shape[:2], np.random.default_rng(seed), config)
    alpha = np.clip(part_alpha.astype(np.float32), 0.0, 1.0)
    if config.feather_px > 0:
        alpha = cv2.GaussianBlur(alpha, (0, 0), config.feather_px)
    alpha = alpha[..., None]
    out = image.astype(np.float32) * alpha + background.astype(np.float32) * (1 - alpha)
    return np.clip(out + 0.5, 0, 255).astype(np.uint8)
