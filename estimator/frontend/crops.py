"""Square crops of an image resized to a fixed size: the scale normalisation of stage two.

A crop of side ``side`` image pixels centred at ``center`` is resampled to ``size`` x ``size``
pixels. With pixel-center coordinates on both sides (pixel (0, 0) covers [-0.5, 0.5)), a crop
pixel p maps to the image pixel

    image = a * p + b,   a = side / size,   b = center - a * (size / 2 - 0.5)

so the crop's own center lands on ``center``. Training cuts its crops with these same two
functions, which is what makes the network's output mean the same thing at inference.
"""

from __future__ import annotations

import math

import cv2
import numpy as np


def crop_transform(center: np.ndarray, side: float, size: int) -> tuple[float, np.ndarray]:
    """(a, b) of the crop (see the module docstring).

    Args:
        center: (2,) image pixel (x, y) the crop is centred on.
        side: the crop's side in image pixels.
        size: the crop's side in crop pixels.
    Returns:
        a: image pixels per crop pixel; b: (2,) image position of crop pixel (0, 0).
    """
    if not side > 0 or size <= 0:
        raise ValueError(f"crop_transform: side and size must be positive, got {side}, {size}")
    a = float(side) / size
    return a, np.asarray(center, np.float64) - a * (size / 2 - 0.5)


def warp_crop(
    image: np.ndarray, a: float, b: np.ndarray, size: int, interpolation: int
) -> np.ndarray:
    """The (size, size[, 3]) crop of ``image`` (H, W[, 3]) under image = a * crop + b; pixels
    outside the image repeat its border. Only the region the crop covers is read (the image
    may be a memory map)."""
    H, W = image.shape[:2]
    bx, by, a = float(b[0]), float(b[1]), float(a)
    if not (math.isfinite(bx) and math.isfinite(by) and math.isfinite(a)):
        raise ValueError(f"warp_crop: the crop's transform must be finite, got a={a}, b={b}")
    x0 = min(max(math.floor(bx) - 1, 0), W - 1)
    y0 = min(max(math.floor(by) - 1, 0), H - 1)
    x1 = min(max(math.ceil(bx + a * size) + 2, x0 + 1), W)
    y1 = min(max(math.ceil(by + a * size) + 2, y0 + 1), H)
    region = image[y0:y1, x0:x1]  # a view: OpenCV reads its rows by their stride
    M = np.array([[a, 0.0, bx - x0], [0.0, a, by - y0]])
    return cv2.warpAffine(
        region,
        M,
        (size, size),
        flags=interpolation | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_REPLICATE,
    )


def box_mask(
    center: np.ndarray, size: np.ndarray, a: float, b: np.ndarray, crop_size: int
) -> np.ndarray:
    """The (crop_size, crop_size) uint8 mask, 1 where a crop pixel's center lies in the box.

    Stage two's fourth input channel: the crop is square, so without it the network cannot
    tell a wide box from a tall one, nor which of two touching parts the box is of.

    Args:
        center: (2,) the box's center, image pixels (x, y).
        size: (2,) its width and height, image pixels.
        a, b: the crop's transform (image = a * crop + b).
    """
    half = 0.5 * np.asarray(size, np.float64)
    lo = (np.asarray(center, np.float64) - half - b) / a
    hi = (np.asarray(center, np.float64) + half - b) / a
    p = np.arange(crop_size, dtype=np.float64)
    inside_x = (p >= lo[0]) & (p <= hi[0])
    inside_y = (p >= lo[1]) & (p <= hi[1])
    return (inside_y[:, None] & inside_x[None, :]).astype(np.uint8)
