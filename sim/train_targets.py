"""Training batches of the two-stage front end, drawn from a rendered training set.

Every batch is a function of (seed, step) alone (``np.random.default_rng([seed, step, k])``),
so a resumed run sees exactly the stream an uninterrupted one would have.

- Detector batches: crops of the downscaled views (most of them holding a part), with
  CenterNet targets on the output grid: per class a Gaussian peak at each visible box's
  center, the box's log size and sub-cell offset at the peak, and a weight map that ignores
  the peaks of barely visible parts (finding them is neither required nor wrong).
- Crop batches: one visible instance per sample, its box jittered as stage one's boxes are,
  cut out of the full-resolution view and resized to the crop size (the same warp as the
  front end's), with the instance's own pixels as the object label and unit vectors towards
  its projected model origin.
- Detector batches with ``class_scale_factors`` (the scale normalisation of SNIP, Singh and
  Davis 2018): each class is detected at the input scale where its parts look the size the
  network knows (a part set's large parts at half the scale, say). A sample is drawn at one of
  the factors, the view resized by it, and only that factor's classes are taught there: the
  others' heatmaps are ignored in the sample, neither targets nor negatives.
- Both, with ``photometric``: a real camera's exposure, white balance, tone curve, blur, noise
  and JPEG drawn per sample (``sim.photometric``).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from posefuse.estimator.frontend.crops import box_mask, crop_transform, warp_crop
from posefuse.sim.backgrounds import Backgrounds, paste_on_clutter
from posefuse.sim.photometric import Photometric, photometric

DET_STRIDE = 4
CROP_STRIDE = 4
MIN_POSITIVE_VISIB = 0.3  # less visible parts are neither targets nor negatives
MIN_TARGET_VISIB = 0.1


@dataclass(frozen=True)
class BatchConfig:
    det_batch: int = 16
    det_crop: tuple[int, int] = (256, 320)  # input pixels (height, width), multiples of 16
    crop_batch: int = 48
    crop_size: int = 96
    box_scale: float = 1.2  # crop side = box_scale x the box's longer side
    center_jitter: float = 0.12  # x the box's longer side
    scale_jitter: float = 0.2  # log scale
    background_crops: float = 0.1  # share of crop samples centred on no part
    box_channel: bool = False  # stage two also gets the box (jittered in aspect as well)
    aspect_jitter: float = 0.1  # log scale of the box's width and height apart
    on_part: float = 0.85  # share of detector crops that hold a part's center
    # also flip upside down (both stages) and transpose (stage two's square crops), each half
    # the time: a bin seen with the camera rolled by 90 or 180 degrees is as plausible a bin
    dihedral: bool = False
    # a real camera's effects drawn per sample (sim.photometric), None: the renders as they are
    photometric: Photometric | None = None
    # what is no part replaced by clutter per sample (sim.backgrounds), None: the bin as rendered
    backgrounds: Backgrounds | None = None
    # per class (output order) the factor of stage one's input scale it is detected at (see the
    # module's docstring); empty: every class at the one scale
    class_scale_factors: tuple[float, ...] = ()
    # per class (output order) the weight of its parts when a detector crop's centre part and
    # a stage-two crop's part are drawn (class-balanced sampling: the inverse of each class's
    # share of the training set's parts); empty: every part alike
    class_weights: tuple[float, ...] = ()


def det_targets(
    rows: np.ndarray,
    scale: float,
    origin_xy: tuple[int, int],
    grid_hw: tuple[int, int],
    n_classes: int,
    taught: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """CenterNet targets of one detector crop.

    Args:
        rows: (K, 11) the view's instance rows (see ``sim.train_data``), image pixels.
        scale: detector input pixels per image pixel.
        origin_xy: top-left of the crop in detector input pixels.
        grid_hw: (h, w) output cells of the crop.
        taught: (C,) bool, the classes taught in this crop (None: all); the others' heatmaps
            are weighted 0 everywhere and their parts give no box target.
    Returns:
        heat: (C, h, w) float32 target in [0, 1]; weight: (C, h, w) float32 (0: ignored);
        box: (4, h, w) float32 log width, log height (input pixels), offset x, y (cells);
        box_mask: (h, w) float32, 1 at the positive peaks.
    """
    h, w = grid_hw
    heat = np.zeros((n_classes, h, w), np.float32)
    weight = np.ones((n_classes, h, w), np.float32)
    box = np.zeros((4, h, w), np.float32)
    box_mask = np.zeros((h, w), np.float32)
    ox, oy = origin_xy
    if taught is not None:
        weight[~np.asarray(taught, bool)] = 0.0
    for r in rows:
        cls = int(r[2])
        if taught is not None and not taught[cls - 1]:
            continue
        x0, y0, x1, y1 = r[5:9] * scale  # box edges in input pixels
        bw, bh = max(x1 - x0, 1.0), max(y1 - y0, 1.0)
        # box center (pixel-center coordinates) -> output cell coordinates of the crop
        gx = ((x0 + x1) / 2 - 0.5 - ox - 0.5 * (DET_STRIDE - 1)) / DET_STRIDE
        gy = ((y0 + y1) / 2 - 0.5 - oy - 0.5 * (DET_STRIDE - 1)) / DET_STRIDE
        cx, cy = int(round(gx)), int(round(gy))
        if not (0 <= cx < w and 0 <= cy < h):
            continue
        if r[9] < MIN_POSITIVE_VISIB:
            weight[:, max(cy - 1, 0) : cy + 2, max(cx - 1, 0) : cx + 2] = 0.0
            continue
        sigma = max(0.6, min(bw, bh) / DET_STRIDE / 6.0)
        rad = int(np.ceil(3 * sigma))
        ya, yb = max(cy - rad, 0), min(cy + rad + 1, h)
        xa, xb = max(cx - rad, 0), min(cx + rad + 1, w)
        yy, xx = np.mgrid[ya:yb, xa:xb]
        g = np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * sigma**2)).astype(np.float32)
        np.maximum(heat[cls - 1, ya:yb, xa:xb], g, out=heat[cls - 1, ya:yb, xa:xb])
        box[:, cy, cx] = (np.log(bw), np.log(bh), gx - cx, gy - cy)
        box_mask[cy, cx] = 1.0
    return heat, weight, box, box_mask


def flip_detector_sample(image, heat, weight, box, box_mask, axis: int):
    """One detector crop and its targets flipped left-right (``axis`` 1) or upside down (0).

    Args:
        image: (H, W, 3); heat: (C, h, w); weight: (C, h, w); box: (4, h, w) log width, log
            height, offset x, y; box_mask: (h, w).
    Returns:
        the five, flipped alike. A flip moves each cell's center by the stride's odd half,
        exactly as it moves the pixels, so the sub-cell offset along the axis flips sign.
    """
    image = np.flip(image, axis)
    heat, weight = np.flip(heat, axis + 1), np.flip(weight, axis + 1)
    box_mask = np.flip(box_mask, axis)
    box = np.flip(box, axis + 1).copy()
    box[3 - axis] = -box[3 - axis]
    return image, heat, weight, box, box_mask


def small_part_alpha(ts, view: int) -> np.ndarray:
    """(Hs, Ws) float32 in [0, 1]: the share of each pixel of a view's stage-one input
    (``ts.small_rgb``) that shows a part, from its full-resolution instance map, resized and
    padded as the renderer makes the input."""
    Hs, Ws = ts.small_rgb.shape[1:3]
    scale = ts.meta["spec"]["small_scale"]
    H, W = ts.full_inst.shape[1:3]
    sw, sh = round(W * scale), round(H * scale)
    parts = (np.asarray(ts.full_inst[view]) > 0).astype(np.float32)
    small = cv2.resize(parts, (sw, sh), interpolation=cv2.INTER_AREA)
    return cv2.copyMakeBorder(small, 0, Hs - sh, 0, Ws - sw, cv2.BORDER_REPLICATE)


def draw_parts(
    classes: np.ndarray, weights: tuple[float, ...], rng: np.random.Generator, size=None
):
    """Indices into ``classes`` (the class column, 1..C, of the parts that may be drawn): each
    part drawn with its class's weight, or uniformly when ``weights`` is empty."""
    if not weights:
        return rng.integers(len(classes), size=size)
    p = np.asarray(weights, float)[np.asarray(classes).astype(int) - 1]
    return rng.choice(len(classes), size=size, p=p / p.sum())


def _resized_view(view: np.ndarray, factor: float, min_hw: tuple[int, int]) -> np.ndarray:
    """(H', W', ...) a stage-one view resized by ``factor`` (as the front end resizes a frame),
    then padded at the bottom and right by repeating its edge to at least ``min_hw``, and to
    multiples of 16."""
    h, w = view.shape[:2]
    if factor != 1.0:
        size = (max(round(w * factor), 1), max(round(h * factor), 1))
        view = cv2.resize(view, size, interpolation=cv2.INTER_AREA)
    h, w = view.shape[:2]
    ph, pw = max(min_hw[0] - h, -h % 16), max(min_hw[1] - w, -w % 16)
    if ph or pw:
        view = cv2.copyMakeBorder(view, 0, ph, 0, pw, cv2.BORDER_REPLICATE)
    return view


def detector_batch(ts, view_rows, n_classes: int, config: BatchConfig, rng: np.random.Generator):
    """(images (B, H, W, 3) uint8, heat (B, C, h, w), weight (B, C, h, w), box (B, 4, h, w),
    box_mask (B, h, w))."""
    ch, cw = config.det_crop
    scale = ts.meta["spec"]["small_scale"]
    factors = np.asarray(config.class_scale_factors or [1.0] * n_classes, float)
    if len(factors) != n_classes:
        raise ValueError(f"class_scale_factors: {len(factors)} factors for {n_classes} classes")
    levels = np.unique(factors)[::-1]  # the full scale first
    views = rng.integers(ts.n_views, size=config.det_batch)
    out = [], [], [], [], []
    for i in views:
        rows = view_rows[i]
        taught = None
        factor = 1.0
        if len(levels) > 1:
            factor = float(levels[rng.integers(len(levels))])
            taught = factors == factor
            source = _resized_view(np.asarray(ts.small_rgb[i]), factor, (ch, cw))
            candidates = rows[taught[rows[:, 2].astype(int) - 1]] if len(rows) else rows
        else:
            source = ts.small_rgb[i]
            candidates = rows
        H, W = source.shape[:2]
        ny, nx = (H - ch) // 16 + 1, (W - cw) // 16 + 1
        s = scale * factor
        y0, x0 = int(rng.integers(ny)) * 16, int(rng.integers(nx)) * 16
        if len(candidates) and rng.random() < config.on_part:
            r = candidates[draw_parts(candidates[:, 2], config.class_weights, rng)]
            px, py = (r[5] + r[7]) / 2 * s, (r[6] + r[8]) / 2 * s
            lo_x, hi_x = int(np.ceil((px + 32 - cw) / 16)), int(np.floor((px - 32) / 16))
            lo_y, hi_y = int(np.ceil((py + 32 - ch) / 16)), int(np.floor((py - 32) / 16))
            lo_x, hi_x, lo_y, hi_y = (
                max(lo_x, 0),
                min(hi_x, nx - 1),
                max(lo_y, 0),
                min(hi_y, ny - 1),
            )
            if lo_x <= hi_x:
                x0 = int(rng.integers(lo_x, hi_x + 1)) * 16
            if lo_y <= hi_y:
                y0 = int(rng.integers(lo_y, hi_y + 1)) * 16
        image = np.asarray(source[y0 : y0 + ch, x0 : x0 + cw])
        if config.backgrounds is not None:
            alpha = small_part_alpha(ts, int(i))
            if taught is not None:
                alpha = _resized_view(alpha, factor, (ch, cw))
            alpha = alpha[y0 : y0 + ch, x0 : x0 + cw]
            image = paste_on_clutter(np.ascontiguousarray(image), alpha, rng, config.backgrounds)
        heat, weight, box, box_mask = det_targets(
            rows, s, (x0, y0), (ch // DET_STRIDE, cw // DET_STRIDE), n_classes, taught
        )
        sample = (image, heat, weight, box, box_mask)
        if rng.random() < 0.5:  # a mirrored bin is as plausible a bin
            sample = flip_detector_sample(*sample, axis=1)
        if config.dihedral and rng.random() < 0.5:  # and so is one upside down
            sample = flip_detector_sample(*sample, axis=0)
        image, heat, weight, box, box_mask = sample
        if config.photometric is not None:
            image = photometric(np.ascontiguousarray(image), rng, config.photometric)
        for lst, a in zip(out, (image, heat, weight, box, box_mask), strict=True):
            lst.append(np.ascontiguousarray(a))
    return tuple(np.stack(a) for a in out)


def crop_targets(
    inst_map: np.ndarray, k: int, uv: np.ndarray, a: float, b: np.ndarray, size: int
) -> tuple[np.ndarray, np.ndarray]:
    """Object label and unit vectors of one crop on its output grid.

    Args:
        inst_map: (H, W) uint8 instance map of the view (k + 1 for instance k).
        uv: (2,) the instance's projected model origin, image pixels; k < 0: no target.
        a, b: the crop's transform, image = a * crop + b (pixel-center coordinates).
    Returns:
        label: (g, g) float32 in {0, 1}; vec: (2, g, g) float32 unit vectors (0 off the part).
    """
    g = size // CROP_STRIDE
    a_out = a * CROP_STRIDE
    b_out = b + a * 0.5 * (CROP_STRIDE - 1)
    lab = warp_crop(inst_map, a_out, b_out, g, cv2.INTER_NEAREST)
    label = (lab == k + 1).astype(np.float32) if k >= 0 else np.zeros((g, g), np.float32)
    j = np.arange(g, dtype=np.float64)
    px = a_out * j[None, :] + b_out[0]
    py = a_out * j[:, None] + b_out[1]
    dx, dy = uv[0] - px, uv[1] - py
    n = np.maximum(np.hypot(dx, dy), 1e-6)
    vec = np.stack([dx / n, dy / n]).astype(np.float32) * label[None]
    return label, vec


def dihedral_crop(crop, mask, label, vec, rng: np.random.Generator):
    """One square crop and its targets flipped upside down, then transposed, each half the
    time (the mirror is drawn before): with it, all eight turns and flips of the square.

    Args:
        crop: (S, S, 3); mask: (S, S); label: (g, g); vec: (2, g, g) unit vectors (x, y).
    Returns:
        the four, transformed alike (a flipped vector field still points at the center).
    """
    if rng.random() < 0.5:
        crop, mask, label = crop[::-1], mask[::-1], label[::-1]
        vec = vec[:, ::-1] * np.array([1, -1], np.float32)[:, None, None]
    if rng.random() < 0.5:
        crop, mask, label = crop.transpose(1, 0, 2), mask.T, label.T
        vec = vec[::-1].transpose(0, 2, 1)
    return crop, mask, label, vec


def crop_batch(ts, config: BatchConfig, rng: np.random.Generator, candidates: np.ndarray):
    """(crops (B, S, S, 3) uint8, boxes (B, S, S) uint8, label (B, g, g), vec (B, 2, g, g)).

    ``boxes`` is the jittered box each crop was cut around (``box_mask``): stage two's fourth
    input channel when ``config.box_channel``; zeros otherwise.

    Args:
        candidates: indices of the instance rows that may be drawn (visible enough).
    """
    drawn = draw_parts(ts.instances[candidates, 2], config.class_weights, rng, config.crop_batch)
    rows = ts.instances[candidates[drawn]]
    S = config.crop_size
    H, W = ts.full_rgb.shape[1:3]
    crops, masks, labels, vecs = [], [], [], []
    for r in rows:
        view = int(r[0])
        x0, y0, x1, y1 = r[5:9]
        side = max(x1 - x0, y1 - y0)
        center = np.array([(x0 + x1) / 2 - 0.5, (y0 + y1) / 2 - 0.5])
        k = int(r[1])
        if rng.random() < config.background_crops:
            center = np.array([rng.uniform(0, W), rng.uniform(0, H)])
            k = -1
        center = center + rng.uniform(-1, 1, 2) * config.center_jitter * side
        scale = np.exp(rng.uniform(-1, 1) * config.scale_jitter)
        if config.box_channel:
            # the box as stage one would give it: its width and height err apart
            box_size = np.array([x1 - x0, y1 - y0], np.float64) * scale
            box_size *= np.exp(rng.uniform(-1, 1, 2) * config.aspect_jitter)
            crop_side = max(config.box_scale * float(box_size.max()), 16.0)
        else:
            crop_side = max(config.box_scale * side * scale, 16.0)
        a, b = crop_transform(center, crop_side, S)
        crop = warp_crop(ts.full_rgb[view], a, b, S, cv2.INTER_LINEAR)
        if config.backgrounds is not None:
            parts = (np.asarray(ts.full_inst[view]) > 0).astype(np.float32)
            alpha = warp_crop(parts, a, b, S, cv2.INTER_LINEAR)
            crop = paste_on_clutter(np.ascontiguousarray(crop), alpha, rng, config.backgrounds)
        mask = (
            box_mask(center, box_size, a, b, S)
            if config.box_channel
            else np.zeros((S, S), np.uint8)
        )
        label, vec = crop_targets(ts.full_inst[view], k, r[3:5], a, b, S)
        if k >= 0 and label.sum() == 0:
            k = -1
        if rng.random() < 0.5:
            crop, mask, label, vec = (
                crop[:, ::-1],
                mask[:, ::-1],
                label[:, ::-1],
                vec[:, :, ::-1] * np.array([-1, 1], np.float32)[:, None, None],
            )
        if config.dihedral:
            crop, mask, label, vec = dihedral_crop(crop, mask, label, vec, rng)
        if config.photometric is not None:
            crop = photometric(np.ascontiguousarray(crop), rng, config.photometric)
        crops.append(np.ascontiguousarray(crop))
        masks.append(np.ascontiguousarray(mask))
        labels.append(np.ascontiguousarray(label))
        vecs.append(np.ascontiguousarray(vec))
    return np.stack(crops), np.stack(masks), np.stack(labels), np.stack(vecs)
