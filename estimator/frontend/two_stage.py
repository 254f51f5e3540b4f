"""The paper's two stages: boxes and classes on the downscaled frame, then a center per box.

Stage one (``BoxDetectorNet`` in training, an ONNX model here) gives, on a grid of stride
``det_stride`` over the detector's input, per class the probability that a visible box is
centred at that cell, plus the box's log size and sub-cell offset. Peaks (3x3 local maxima
above ``min_score``) are the boxes.

Stage two (``CropVotingNet``) gets each box cropped square (``box_scale`` x its longer side)
and resized to ``crop_size``: cropping normalises scale, and two touching parts of one type
no longer compete for the same pixels, since each crop asks only for the part it is centred
on. Its output labels the part's pixels and points each at the projected model origin;
RANSAC voting (:mod:`estimator.frontend.voting`) on the labelled pixels gives the center and
its covariance, mapped back to image pixels with the crop's transform.

All functions take and return image pixels (pixel-center coordinates).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from posefuse.estimator.frontend.crops import box_mask, crop_transform, warp_crop
from posefuse.estimator.frontend.detection import Detection
from posefuse.estimator.frontend.voting import VotingConfig, labelled_pixels, vote_instances


@dataclass(frozen=True)
class TwoStageConfig:
    det_stride: int = 4
    crop_size: int = 96
    crop_stride: int = 4
    box_scale: float = 1.2
    min_score: float = 0.3  # heatmap peak probability
    max_boxes: int = 100
    min_crop_side: float = 16.0  # image pixels
    min_votes: int = 10  # object pixels (crop output cells) a center needs
    duplicate_factor: float = 0.3  # same-class centers closer than this x box side: one part
    refine_passes: int = 0  # stage two again on crops centred on its own centers
    # ... except for a vote within this share of its crop's side from the crop's center: its
    # crop is already centred on it (0: every vote is cropped again)
    refine_min_offset: float = 0.0
    box_channel: bool = False  # stage two takes the box as a fourth input channel

    def __post_init__(self) -> None:
        if self.refine_passes < 0 or not (
            math.isfinite(self.refine_min_offset) and self.refine_min_offset >= 0
        ):
            raise ValueError(
                "TwoStageConfig: refine_passes and refine_min_offset must be at least 0 (and "
                f"finite), got {self.refine_passes}, {self.refine_min_offset}"
            )


@dataclass(frozen=True, eq=False)
class Box:
    """A stage-one box: class index (0-based, output order), center (2,) and size (2,)
    (w, h) in image pixels, and its peak probability."""

    class_index: int
    center: np.ndarray
    size: np.ndarray
    score: float


def decode_boxes(out: np.ndarray, input_scale: float, config: TwoStageConfig) -> list[Box]:
    """Boxes from the detector's output.

    Args:
        out: (C + 4, h, w) heatmap probabilities, log w, log h (input pixels), offsets (cells).
        input_scale: detector input pixels per image pixel.
    Returns:
        boxes, best first (at most ``config.max_boxes``).
    """
    n_classes = out.shape[0] - 4
    heat = np.ascontiguousarray(out[:n_classes], np.float32)
    peaks = []
    for c in range(n_classes):
        local_max = cv2.dilate(heat[c], np.ones((3, 3), np.uint8))
        ys, xs = np.nonzero((heat[c] >= local_max) & (heat[c] >= config.min_score))
        peaks.extend((float(heat[c, y, x]), c, y, x) for y, x in zip(ys, xs, strict=True))
    peaks.sort(key=lambda p: -p[0])
    s = config.det_stride
    boxes = []
    for score, c, y, x in peaks[: config.max_boxes]:
        lw, lh, ox, oy = out[n_classes:, y, x]
        gx, gy = x + float(ox), y + float(oy)
        center_in = np.array([gx, gy]) * s + 0.5 * (s - 1)  # detector input pixels
        center = (center_in + 0.5) / input_scale - 0.5
        size = np.exp(np.clip([lw, lh], -2.0, 8.0)) / input_scale
        boxes.append(Box(c, center, size, score))
    return boxes


def crop_side(box: Box, config: TwoStageConfig) -> float:
    """The side, in image pixels, of the square crop stage two cuts around ``box``."""
    return max(config.box_scale * float(box.size.max()), config.min_crop_side)


def crop_boxes(image: np.ndarray, boxes: list[Box], config: TwoStageConfig):
    """(crops (N, S, S, 3) uint8, transforms [(a, b)]) of the boxes, each square and centred."""
    S = config.crop_size
    crops, transforms = [], []
    for box in boxes:
        a, b = crop_transform(box.center, crop_side(box, config), S)
        crops.append(warp_crop(image, a, b, S, cv2.INTER_LINEAR))
        transforms.append((a, b))
    return (np.stack(crops) if crops else np.zeros((0, S, S, 3), np.uint8)), transforms


def box_masks(boxes: list[Box], transforms: list, config: TwoStageConfig) -> np.ndarray:
    """(N, S, S) uint8: each box drawn in its own crop (stage two's box channel)."""
    S = config.crop_size
    if not boxes:
        return np.zeros((0, S, S), np.uint8)
    return np.stack(
        [
            box_mask(box.center, box.size, a, b, S)
            for box, (a, b) in zip(boxes, transforms, strict=True)
        ]
    )


@dataclass(frozen=True, eq=False)
class CropVote:
    """What one crop's vote found, before its mask is drawn: center (2,) and cov (2, 2) in
    image pixels; cells (n, 2) int, the output cells (x, y) of the part's pixels; score; the
    crop's output-cell transform (image = a_out * cell + b_out) and grid side g."""

    center: np.ndarray
    cov: np.ndarray
    cells: np.ndarray
    score: float
    a_out: float
    b_out: np.ndarray
    g: int


def vote_center(
    crop_out: np.ndarray,
    a: float,
    b: np.ndarray,
    box_score: float,
    voting: VotingConfig,
    config: TwoStageConfig,
    rng: np.random.Generator,
) -> CropVote | None:
    """The center one crop's output gives, or None when it holds no part (the refinement pass
    needs no more than this; :func:`detection_of` draws the mask).

    Args:
        crop_out: (3, g, g) object logit and unit vectors on the crop's output grid.
        a, b: the crop's transform (image = a * crop + b).
    """
    logit, vectors = crop_out[0], crop_out[1:]
    g = logit.shape[0]
    pix, vec = labelled_pixels(logit, vectors)
    if len(pix) < config.min_votes:
        return None
    instances = [i for i in vote_instances(pix, vec, voting, rng) if i.n_votes >= config.min_votes]
    if not instances:
        return None
    # the part the crop is centred on: in a pile the crop also holds pieces of its
    # neighbours, and a neighbour's piece may gather more votes than the part itself
    middle = 0.5 * (g - 1)
    offsets = np.array([i.center for i in instances]) - middle
    inst = instances[int(np.argmin(np.hypot(offsets[:, 0], offsets[:, 1])))]
    # output cell -> crop pixel -> image pixel
    a_out = a * config.crop_stride
    b_out = b + a * 0.5 * (config.crop_stride - 1)
    members = pix[inst.pixels].astype(int)
    fg = 1.0 / (1.0 + np.exp(-logit[members[:, 1], members[:, 0]].astype(np.float64)))
    return CropVote(
        a_out * inst.center + b_out,
        inst.cov * a_out**2,
        members,
        float(box_score * fg.mean()),
        float(a_out),
        np.asarray(b_out, float),
        g,
    )


def detection_of(vote: CropVote, image_hw: tuple[int, int], obj_id: int) -> Detection | None:
    """The detection of a crop's vote, with its mask in image pixels (each output cell covers
    a_out x a_out image pixels around its center), or None when the mask leaves the image."""
    a_out, b_out, g = vote.a_out, vote.b_out, vote.g
    H, W = image_hw
    cell = np.zeros((g, g), np.uint8)
    cell[vote.cells[:, 1], vote.cells[:, 0]] = 1
    x0 = max(int(np.floor(b_out[0] - a_out / 2)), 0)
    y0 = max(int(np.floor(b_out[1] - a_out / 2)), 0)
    x1 = min(int(np.ceil(b_out[0] + a_out * (g - 0.5))), W)
    y1 = min(int(np.ceil(b_out[1] + a_out * (g - 0.5))), H)
    if x1 <= x0 or y1 <= y0:
        return None
    M = np.array([[1 / a_out, 0, (x0 - b_out[0]) / a_out], [0, 1 / a_out, (y0 - b_out[1]) / a_out]])
    local = cv2.warpAffine(
        cell, M, (x1 - x0, y1 - y0), flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP
    )
    if not local.any():
        return None
    mask = np.zeros((H, W), bool)
    mask[y0:y1, x0:x1] = local.view(bool)  # 0 or 1
    cols, rows = np.flatnonzero(local.any(0)), np.flatnonzero(local.any(1))
    bbox = np.array(
        [x0 + cols[0], y0 + rows[0], cols[-1] - cols[0] + 1, rows[-1] - rows[0] + 1], float
    )
    return Detection(obj_id, bbox, vote.center, vote.cov, mask, vote.score)


def vote_in_crop(
    crop_out: np.ndarray,
    a: float,
    b: np.ndarray,
    image_hw: tuple[int, int],
    obj_id: int,
    box_score: float,
    voting: VotingConfig,
    config: TwoStageConfig,
    rng: np.random.Generator,
) -> Detection | None:
    """The detection one crop's output gives, or None when it holds no part:
    :func:`vote_center`, then :func:`detection_of`.

    Args:
        crop_out: (3, g, g) object logit and unit vectors on the crop's output grid.
        a, b: the crop's transform (image = a * crop + b).
    """
    vote = vote_center(crop_out, a, b, box_score, voting, config, rng)
    return None if vote is None else detection_of(vote, image_hw, obj_id)


def suppress_duplicates(dets: list[Detection], factor: float) -> list[Detection]:
    """Of same-class detections whose centers lie closer than ``factor`` x the smaller box's
    longer side, the best scored (two peaks of one part)."""
    kept: list[Detection] = []
    for d in sorted(dets, key=lambda d: -d.score):
        side = d.bbox_xywh[2:].max()
        if any(
            k.obj_id == d.obj_id
            and np.linalg.norm(k.center_uv - d.center_uv)
            < factor * min(side, k.bbox_xywh[2:].max())
            for k in kept
        ):
            continue
        kept.append(d)
    return kept
