"""What a real camera varies and a render does not: exposure, white balance, tone curve, focus,
sensor noise and JPEG compression, drawn per training sample (``posefuse train --photometric``).

The renders already carry a fixed sensor model (``sim.sensor``: 2.5 grey levels of noise, 0.6 px
of blur). A real camera's differ from shot to shot and from camera to camera: auto exposure and
white balance shift the colours, the lens may be a little out of focus, a compressed stream
blocks the edges. A front end trained on one sensor model reads these as new; trained across
them it learns what stays, the parts' shapes.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["Photometric", "photometric"]


@dataclass(frozen=True)
class Photometric:
    """Ranges of the draws; each effect is applied to a sample with probability ``p``."""

    p: float = 0.5
    gain_log: float = 0.35  # exposure: a gain exp(U(-g, g))
    white_balance_log: float = 0.1  # per channel, on top of the gain
    gamma_log: float = 0.25  # tone curve: x ** exp(U(-g, g)), x in [0, 1]
    blur_sigma: tuple[float, float] = (0.3, 1.5)  # pixels of Gaussian blur (focus, motion)
    noise_std: tuple[float, float] = (1.0, 8.0)  # grey levels of Gaussian noise
    jpeg_quality: tuple[int, int] = (35, 95)

    def __post_init__(self) -> None:
        if not 0.0 <= self.p <= 1.0:
            raise ValueError(f"Photometric: p must be in [0, 1], got {self.p}")
        if not 1 <= self.jpeg_quality[0] <= self.jpeg_quality[1] <= 100:
            raise ValueError(
                f"Photometric: jpeg_quality must be in [1, 100], got {self.jpeg_quality}"
            )


def photometric(image: np.ndarray, rng: np.random.Generator, config: Photometric) -> np.ndarray:
    """One draw of the camera's effects on an (H, W, 3) uint8 RGB image; returns a new (H, W, 3)
    uint8 image. The draws come from ``rng`` alone, a fixed number per call (every effect's
    coin and its parameters are drawn whether or not it applies), so a seeded stream repeats."""
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"photometric: expected (H, W, 3) uint8, got {image.shape} {image.dtype}")
    coins = rng.random(5) < config.p
    gain = np.exp(rng.uniform(-config.gain_log, config.gain_log))
    balance = np.exp(rng.uniform(-config.white_balance_log, config.white_balance_log, 3))
    gamma = np.exp(rng.uniform(-config.gamma_log, config.gamma_log))
    sigma = rng.uniform(*config.blur_sigma)
    noise = rng.uniform(*config.noise_std)
    quality = int(rng.integers(config.jpeg_quality[0], config.jpeg_quality[1] + 1))
    noise_seed = int(rng.integers(2**31))
    x = image.astype(np.float32) / 255.0
    if coins[0]:
        x = x * np.float32(gain) * balance.astype(np.float32)
    if coins[1]:
        x = np.clip(x, 0.0, 1.0) ** np.float32(gamma)
    if coins[2]:
        x = cv2.GaussianBlur(x, (0, 0), sigma)
    if coins[3]:
        noisy = np.random.default_rng(noise_seed).normal(0.0, noise / 255.0, x.shape)
        x = x + noisy.astype(np.float32)
    out = np.clip(x * 255.0 + 0.5, 0, 255).astype(np.uint8)
    if coins[4]:
        ok, data = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, quality])
        if ok:
            out = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    return out
