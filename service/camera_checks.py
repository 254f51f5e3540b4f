"""Camera intrinsics that no real camera has, refused before they reach the estimator.

A CameraInfo can be well formed and still describe no camera: a focal length of 1e-300 or
1e300 pixels, a skew of 1e300, a distortion coefficient of 1e12. Used, such numbers overflow
the estimator's arithmetic (a ray of infinite length, a center at infinity) or quietly give
every pose of that camera wrong. The bounds below are far outside every lens a robot cell
mounts, from a 170 degree fisheye (as plumb_bob can model it at all) to a 1 degree telephoto:

- the field of view along each image axis between ``MIN_FOV_DEG`` and ``MAX_FOV_DEG``;
- pixels at most ``MAX_ASPECT`` times taller than wide or wider than tall (fy / fx);
- a skew at most ``MAX_SKEW_FRAC`` of fx (digital cameras have none);
- the principal point inside the image;
- each plumb_bob coefficient at most ``MAX_DISTORTION`` in magnitude.

:func:`implausible_intrinsics` says why a camera fails, or None; the codec refuses such an info
with the code ``implausible``, counted like every refused message.
"""

from __future__ import annotations

import math

import numpy as np

MIN_FOV_DEG = 1.0
MAX_FOV_DEG = 170.0
MAX_ASPECT = 4.0
MAX_SKEW_FRAC = 0.1
MAX_DISTORTION = 100.0


def focal_range_px(side_px: int) -> tuple[float, float]:
    """(least, largest) focal length in pixels that gives an image side of ``side_px`` a
    field of view between ``MAX_FOV_DEG`` and ``MIN_FOV_DEG``."""
    half = 0.5 * side_px
    return (
        half / math.tan(math.radians(0.5 * MAX_FOV_DEG)),
        half / math.tan(math.radians(0.5 * MIN_FOV_DEG)),
    )


def implausible_intrinsics(K: np.ndarray, width: int, height: int, D: np.ndarray) -> str | None:
    """Why a camera (K (3, 3) pixels, image width x height, plumb_bob D (<= 5,)) is one no
    real camera is, or None when it is plausible (see the module docstring)."""
    fx, fy, skew, cx, cy = K[0, 0], K[1, 1], K[0, 1], K[0, 2], K[1, 2]
    for name, f, side in (("fx", fx, width), ("fy", fy, height)):
        low, high = focal_range_px(side)
        if not low <= f <= high:
            return (
                f"{name} = {f:.6g} px gives the {side} px side a field of view outside "
                f"{MIN_FOV_DEG:g} to {MAX_FOV_DEG:g} degrees ({low:.4g} to {high:.4g} px)"
            )
    if not 1.0 / MAX_ASPECT <= fy / fx <= MAX_ASPECT:
        return f"fy / fx = {fy / fx:.6g} is outside 1/{MAX_ASPECT:g} to {MAX_ASPECT:g}"
    if abs(skew) > MAX_SKEW_FRAC * fx:
        return f"skew {skew:.6g} px exceeds {MAX_SKEW_FRAC:g} of fx"
    if not (0.0 <= cx <= width and 0.0 <= cy <= height):
        return f"principal point ({cx:.6g}, {cy:.6g}) lies outside the {width}x{height} image"
    D = np.asarray(D, dtype=np.float64).reshape(-1)
    if D.size and np.max(np.abs(D)) > MAX_DISTORTION:
        worst = D[np.argmax(np.abs(D))]
        return f"a distortion coefficient is {worst:.6g} (at most {MAX_DISTORTION:g} in magnitude)"
    return None
