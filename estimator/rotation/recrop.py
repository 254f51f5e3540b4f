"""The scale-aware re-crop (paper Section V-A): a view's region of interest around the part,
resampled so the part appears as at the templates' canonical distance.

From the track's translation ``t_cam_obj = [x_s, y_s, z_s]``: the object origin projects to
``u``; a square RoI of side ``l_s = (z_r / z_s) * (f / f_r) * l_r`` centred on ``u`` (padded at
the image border) is resized to ``l_r`` pixels, so the part appears at the templates' scale;
the front end's mask (dilated by a few pixels, to keep the silhouette's edges) removes the
clutter. Not to be confused with the front end's crops (:mod:`estimator.frontend.crops`), the
network's input at its second stage.
"""

from __future__ import annotations

import cv2
import numpy as np

from posefuse.estimator.rotation.templates import TemplateBank

__all__ = ["crop_roi"]


def crop_roi(
    image: np.ndarray,
    K: np.ndarray,
    t_cam_obj: np.ndarray,
    bank: TemplateBank,
    mask: np.ndarray | None = None,
    dilation_px: int = 3,
) -> tuple[np.ndarray, np.ndarray | None]:
    """The scale-normalised RoI and mask.

    Args:
        image: (H, W, 3) uint8 RGB. K: (3, 3). t_cam_obj: (3,) metres, z > 0.
        mask: (H, W) bool visible mask of the instance, or None.
    Returns:
        roi: (l_r, l_r, 3) uint8 BGR (cv2.linemod's order); roi_mask: (l_r, l_r) uint8 or None.
    """
    cfg = bank.config
    l_r = cfg.roi_size
    x, y, z = t_cam_obj
    u = K[0, 0] * x / z + K[0, 1] * y / z + K[0, 2]
    v = K[1, 1] * y / z + K[1, 2]
    f = 0.5 * (K[0, 0] + K[1, 1])
    s = (z / bank.z_r) * (cfg.focal / f)  # RoI pixels per image pixel
    c = (l_r - 1) / 2.0
    A = np.array([[s, 0.0, c - s * u], [0.0, s, c - s * v]])
    # warp, then swap channels: the same pixels as converting the whole image first, at the
    # cost of a RoI instead of a 1280x720 frame per object
    roi = cv2.cvtColor(
        cv2.warpAffine(
            image, A, (l_r, l_r), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
        ),
        cv2.COLOR_RGB2BGR,
    )
    if mask is None:
        return roi, None
    # warped as 0/1 and scaled on the RoI: nearest-neighbour sampling picks the same pixels
    mask01 = mask.view(np.uint8) if mask.dtype == bool else (mask != 0).astype(np.uint8)
    m = cv2.warpAffine(
        np.ascontiguousarray(mask01),
        A,
        (l_r, l_r),
        flags=cv2.INTER_NEAREST,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0,
    )
    m *= 255
    if dilation_px > 0:
        k = 2 * dilation_px + 1
        m = cv2.dilate(m, np.ones((k, k), np.uint8))
    return roi, m
