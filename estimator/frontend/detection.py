"""The per-frame measurement every front end produces: one detected object instance."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

MASK_KINDS = ("silhouette", "box")  # what a Detection's mask outlines
# the obj_id of "a part" of no particular class: a generalist front end's detections, named by
# the tracker from the catalog's templates (estimator.rotation.naming)
ANY_PART = 0


@dataclass(frozen=True, eq=False)
class Detection:
    """One object instance detected in one image.

    Attributes:
        obj_id: BOP object id of the detected class.
        bbox_xywh: (4,) float, the instance's box in pixels: x, y of the top-left corner, width,
            height (BOP's ``bbox_visib`` convention).
        center_uv: (2,) float, pixel coordinates of the projected model origin ``u_k``.
        center_cov: (2, 2) float, covariance of ``center_uv`` in pixels^2, symmetric positive
            definite.
        mask: (H, W) bool visible mask of the instance, or None when the front end has none.
        score: confidence of the detection in [0, 1].
        mask_kind: ``"silhouette"`` when ``mask`` follows the part's visible outline (the
            learned front end's, the ground truth's), ``"box"`` when it only fills the box
            around it. Both bound the rotation step's RoI; only a silhouette's outline is
            compared with the model's by the verification across views, since a box's edges
            are not the part's.
    """

    obj_id: int
    bbox_xywh: np.ndarray  # (4,)
    center_uv: np.ndarray  # (2,)
    center_cov: np.ndarray  # (2, 2)
    mask: np.ndarray | None  # (H, W) bool
    score: float = 1.0
    mask_kind: str = "silhouette"

    def __post_init__(self) -> None:
        if self.mask_kind not in MASK_KINDS:
            raise ValueError(
                f"Detection: mask_kind must be one of {MASK_KINDS}, got {self.mask_kind!r}"
            )
        bbox = np.asarray(self.bbox_xywh, dtype=np.float64).reshape(4)
        uv = np.asarray(self.center_uv, dtype=np.float64).reshape(2)
        cov = np.asarray(self.center_cov, dtype=np.float64).reshape(2, 2)
        # scalar checks: a frame's detections are made and copied by the dozen, and numpy's
        # isfinite / allclose / eigvalsh on arrays of 2 to 4 values were a fifth of a
        # detection's cost in the front end
        values = [*bbox.tolist(), *uv.tolist(), *cov.ravel().tolist()]
        if not all(math.isfinite(x) for x in values):
            raise ValueError("Detection: bbox_xywh, center_uv and center_cov must be finite")
        if bbox[2] <= 0 or bbox[3] <= 0:
            raise ValueError(f"Detection: bbox width and height must be positive, got {bbox}")
        a, b, c, d = values[6:]
        atol = 1e-9 * max(1.0, abs(a), abs(b), abs(c), abs(d))
        # np.allclose(cov, cov.T) tests b against c and c against b, each relative to the other
        if abs(b - c) > atol + 1e-5 * min(abs(b), abs(c)):
            raise ValueError("Detection: center_cov must be symmetric")
        # of its lower triangle, as eigvalsh reads it, scaled so that no product overflows
        scale = max(abs(a), abs(c), abs(d))
        a, c, d = (a / scale, c / scale, d / scale) if scale > 0 else (0.0, 0.0, 0.0)
        if not (a > 0 and a * d - c * c > 0):
            raise ValueError("Detection: center_cov must be positive definite")
        if self.mask is not None and (self.mask.ndim != 2 or self.mask.dtype != bool):
            raise ValueError("Detection: mask must be a 2D bool array")
        object.__setattr__(self, "bbox_xywh", bbox)
        object.__setattr__(self, "center_uv", uv)
        object.__setattr__(self, "center_cov", cov)

    @property
    def silhouette(self) -> np.ndarray | None:
        """The mask when it is the part's outline (``mask_kind == "silhouette"``), else None."""
        return self.mask if self.mask_kind == "silhouette" else None

    @property
    def bbox_diagonal(self) -> float:
        """Length of the bbox diagonal in pixels."""
        return float(np.hypot(self.bbox_xywh[2], self.bbox_xywh[3]))


@dataclass(frozen=True, eq=False)
class ExpectedPart:
    """Where a known part should show in an image: a track's translation projected into it.

    Attributes:
        object_id: the track's.
        obj_id: BOP object id of its class.
        center_uv: (2,) pixel coordinates of its projected model origin.
        side_px: the side, in pixels, of the square box its silhouette is expected to fill.
    """

    object_id: str
    obj_id: int
    center_uv: np.ndarray  # (2,)
    side_px: float
