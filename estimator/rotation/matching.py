"""Per-view rotation measurement with the translation known (paper Section V-A).

From the track's translation, the view is re-cropped at the templates' canonical distance
(:func:`estimator.rotation.recrop.crop_roi`: the part at the templates' scale, the front end's
mask removing the clutter); the LINE-2D templates are scored at the one position the translation
gives.

Scoring: ``cv2.linemod`` quantises the RoI's gradient orientations (8 bins, as in LINE-2D);
orientations are spread over T x T pixels and turned into 8 response maps (4 for the same
orientation, one less per bin of difference), and each template's similarity is the mean
response at its features, in percent. ``cv2.linemod.Detector.match`` would evaluate every
template at every position of the RoI; measured on 128 x 128 RoIs it costs 4.5-6 us per
template (``python -m posefuse.bench.rotation_measure``; a 3,000-template bank: ~15 ms), while the
position is already known here, so the templates are scored at that position only, in one
vectorised gather (1.3-1.9 ms per RoI with the whole re-crop).

Templates are rendered on the optical axis; a part off the axis is seen from a direction
rotated by the rotation that takes the optical axis onto the viewing ray of its center, so each
matched rotation is corrected by it: ``R_cam_obj = R_ray @ R_template``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from posefuse.estimator.core.geometry import rotation_angle, so3_exp
from posefuse.estimator.rotation.recrop import crop_roi
from posefuse.estimator.rotation.templates import TemplateBank

N_ORIENTATIONS = 8


def _similarity_lut() -> np.ndarray:
    """(8, 256) uint8: response of a feature with orientation l to a spread bit set."""
    lut = np.zeros((N_ORIENTATIONS, 256), np.uint8)
    for label in range(N_ORIENTATIONS):
        for bits in range(256):
            best = 0
            for b in range(N_ORIENTATIONS):
                if bits & (1 << b):
                    d = abs(b - label)
                    d = min(d, N_ORIENTATIONS - d)
                    best = max(best, 4 - d)
            lut[label, bits] = best
    return lut


SIMILARITY_LUT = _similarity_lut()


@dataclass(frozen=True, eq=False)
class RotationMeasurement:
    """One rotation hypothesis of one view: R_cam_obj (3, 3), confidence in [0, 1] (LINE-2D
    similarity), template index in the bank."""

    R_cam_obj: np.ndarray
    confidence: float
    template: int


@dataclass(frozen=True)
class RotationConfig:
    # hypotheses per view: on parts that look alike from opposite sides the flipped template
    # often scores best in one view; giving the mixture the next-best distinct templates too
    # lets the true mode collect evidence from every view. ADD(-S)-0.1d of the two-step
    # estimator on the scenes of `posefuse bench --dataset data/bench` (50 bins, oracle
    # detections) at 4 / 8 views: top 1 92.2% / 97.3%, top 2 96.4% / 98.9%, top 3 97.5% / 99.2%
    top_k: int = 3
    nms_deg: float = 15.0  # hypotheses closer than this to a better one are suppressed
    mask_dilation_px: int = 3
    min_confidence: float = 0.3  # below this a match says nothing


def ray_correction(t_cam_obj: np.ndarray) -> np.ndarray:
    """(3, 3) the rotation taking the optical axis [0, 0, 1] onto the ray through t_cam_obj."""
    d = np.asarray(t_cam_obj, dtype=np.float64)
    d = d / np.linalg.norm(d)
    axis = np.cross([0.0, 0.0, 1.0], d)
    s = np.linalg.norm(axis)
    if s < 1e-12:
        return np.eye(3)
    angle = np.arctan2(s, d[2])
    return so3_exp(axis / s * angle)


class RotationMatcher:
    """Scores one object's templates on scale-normalised RoIs."""

    def __init__(self, bank: TemplateBank, config: RotationConfig | None = None):
        self.bank = bank
        self.config = config or RotationConfig()
        cfg = bank.config
        self._modality = cv2.linemod.ColorGradient_create(
            cfg.weak_threshold, cfg.n_features, cfg.strong_threshold
        )
        L = cfg.roi_size
        self._index = (
            bank.feat_label.astype(np.intp) * L * L
            + bank.feat_y.astype(np.intp) * L
            + bank.feat_x.astype(np.intp)
        )  # (N, F) into the flattened (8, L, L) response maps
        self._weight = bank.feat_valid / np.maximum(bank.feat_valid.sum(1, keepdims=True), 1) / 4

    def response_maps(self, roi: np.ndarray, roi_mask: np.ndarray | None) -> np.ndarray:
        """(8, L, L) uint8 LINE-2D responses of a RoI."""
        quantized = self._modality.process(roi, roi_mask).quantize()  # (L, L) one bit per pixel
        T = self.bank.config.pyramid_T[0]
        # OR over a T x T window, one axis at a time (the same bits as the T^2 shifts)
        L = quantized.shape[0]
        lo = -(T // 2)
        padded = np.pad(quantized, T)
        rows = np.zeros((L + 2 * T, L), quantized.dtype)
        for dx in range(lo, lo + T):
            rows |= padded[:, T + dx : T + dx + L]
        spread = np.zeros_like(quantized)
        for dy in range(lo, lo + T):
            spread |= rows[T + dy : T + dy + L]
        return SIMILARITY_LUT[:, spread]

    def scores(self, roi: np.ndarray, roi_mask: np.ndarray | None) -> np.ndarray:
        """(N,) similarity in [0, 1] of every template at the RoI centre."""
        response = self.response_maps(roi, roi_mask).reshape(-1)
        return (np.take(response, self._index) * self._weight).sum(1)

    def measure(
        self,
        image: np.ndarray,
        K: np.ndarray,
        t_cam_obj: np.ndarray,
        mask: np.ndarray | None = None,
    ) -> list[RotationMeasurement]:
        """The top-k rotation hypotheses of one view, best first (empty when none is credible)."""
        if t_cam_obj[2] <= 0:
            return []
        roi, roi_mask = crop_roi(image, K, t_cam_obj, self.bank, mask, self.config.mask_dilation_px)
        scores = self.scores(roi, roi_mask)
        return select_hypotheses(
            scores, self.bank.R_cam_obj, ray_correction(t_cam_obj), self.config
        )


def select_hypotheses(
    scores: np.ndarray, R_templates: np.ndarray, R_ray: np.ndarray, config: RotationConfig
) -> list[RotationMeasurement]:
    """The best ``top_k`` templates by score, each at least ``nms_deg`` from a better one and
    above ``min_confidence``, as rotations corrected by R_ray (3, 3).

    scores: (N,) similarity per template; R_templates: (N, 3, 3) their R_cam_obj.
    """
    picked: list[int] = []
    for k in _best_first(scores, config.min_confidence):
        if scores[k] < config.min_confidence or len(picked) >= config.top_k:
            break
        R = R_templates[k]
        if picked:
            others = R_templates[picked]
            close = rotation_angle(np.einsum("nji,jk->nik", others, R))
            if np.any(close < np.deg2rad(config.nms_deg)):
                continue
        picked.append(int(k))
    return [RotationMeasurement(R_ray @ R_templates[k], float(scores[k]), k) for k in picked]


def _best_first(scores: np.ndarray, floor: float, head: int = 64):
    """Indices of ``scores`` (N,) at or above ``floor``, highest first, ties by index (the order
    of a stable sort of ``-scores``). Only the ``head`` best are sorted unless a caller reads
    past them: the full sort of every template was a tenth of the scoring time."""
    above = np.flatnonzero(scores >= floor)
    if len(above) > head:
        kth = -np.partition(-scores[above], head - 1)[head - 1]  # the head-th best score
        first = above[scores[above] > kth]  # every index above it: exact, whatever the ties
        rest = above[scores[above] <= kth]
    else:
        first, rest = above, above[:0]
    yield from first[np.lexsort((first, -scores[first]))]
    yield from rest[np.lexsort((rest, -scores[rest]))]
