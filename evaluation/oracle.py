"""An oracle front end: detections made from a BOP dataset's ground truth, with controlled noise.

It stands in for the network while the back end is measured: each annotated instance that is
visible enough gives a detection whose center is the true projected model origin plus Gaussian
noise of ``center_sigma_px`` (reported as its covariance), the visible box and mask (the
ground-truth silhouette, or with ``masks="box"`` the filled visible box, so that the rotation
step must find the part's outline in the image's own edges, as behind a detector that gives
boxes); a fraction
``drop_rate`` of them is dropped, and false positives of random classes are added at a rate of
``false_positive_rate`` per true detection. The randomness of one view depends only on
``(seed, scene_id, im_id)``, so any order of views gives the same detections.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from posefuse.estimator.frontend.detection import Detection


@dataclass(frozen=True)
class OracleConfig:
    center_sigma_px: float = 2.0
    drop_rate: float = 0.0
    false_positive_rate: float = 0.0
    min_visib: float = 0.1  # instances less visible than this are not detected
    with_masks: bool = True  # give masks (the rotation step needs them)
    masks: str = "silhouette"  # "silhouette" (mask_visib PNGs) or "box" (the filled bbox_visib)
    seed: int = 0

    def __post_init__(self) -> None:
        if self.masks not in ("silhouette", "box"):
            raise ValueError(f"masks must be 'silhouette' or 'box', got {self.masks!r}")
        if not self.center_sigma_px > 0:
            raise ValueError(f"center_sigma_px must be positive, got {self.center_sigma_px}")
        for name in ("drop_rate", "false_positive_rate", "min_visib"):
            value = getattr(self, name)
            if not 0 <= value <= 1:
                raise ValueError(f"{name} must be in [0, 1], got {value}")


class OracleFrontend:
    """Noisy detections from ground truth (see the module docstring)."""

    def __init__(self, dataset, config: OracleConfig | None = None):
        self.dataset = dataset
        self.config = config or OracleConfig()
        self._obj_ids = tuple(dataset.catalog)

    def detect(self, view) -> list[Detection]:
        """Detections of one BopView, in a fixed order."""
        return [d for d, _ in self.detect_with_truth(view)]

    def detect_with_truth(self, view) -> list[tuple[Detection, int]]:
        """Detections with the ground-truth index each came from (-1 for false positives)."""
        cfg = self.config
        rng = np.random.default_rng([cfg.seed, view.scene_id, view.im_id])
        scene = self.dataset.scene(view.scene_id)
        camera = view.camera
        cov = np.eye(2) * cfg.center_sigma_px**2
        out: list[tuple[Detection, int]] = []
        sizes = []
        for gt in view.gts:
            noise = rng.normal(0.0, cfg.center_sigma_px, 2)  # drawn for every gt: stable streams
            dropped = rng.random() < cfg.drop_rate
            if gt.visib_fract < cfg.min_visib or gt.bbox_visib[2] <= 0 or dropped:
                continue
            t = gt.T_cam_obj[:3, 3]
            if t[2] <= 0:
                continue
            uv = camera.project(t)
            if not camera.contains(uv[None])[0]:
                continue
            bbox = np.asarray(gt.bbox_visib, dtype=np.float64)
            mask = None
            if cfg.with_masks and cfg.masks == "box":
                mask = np.zeros((camera.height, camera.width), bool)
                x, y, w, h = gt.bbox_visib
                mask[y : y + h, x : x + w] = True
            elif cfg.with_masks:
                mask = scene.load_mask_visib(view.im_id, gt.gt_idx)
            sizes.append(bbox[2:])
            kind = "box" if cfg.masks == "box" else "silhouette"
            det = Detection(gt.obj_id, bbox, uv + noise, cov, mask, 1.0, kind)
            out.append((det, gt.gt_idx))
        n_false = rng.binomial(len(out), cfg.false_positive_rate) if out else 0
        for _ in range(n_false):
            # the size of a random true detection, at most half the image, so the box fits
            wh = np.minimum(sizes[rng.integers(len(sizes))], [camera.width / 2, camera.height / 2])
            uv = rng.uniform([wh[0], wh[1]], [camera.width - wh[0], camera.height - wh[1]])
            bbox = np.array([uv[0] - wh[0] / 2, uv[1] - wh[1] / 2, wh[0], wh[1]])
            mask = None
            if cfg.with_masks:
                mask = np.zeros((camera.height, camera.width), bool)
                x0, y0 = int(bbox[0]), int(bbox[1])
                mask[y0 : y0 + int(wh[1]), x0 : x0 + int(wh[0])] = True
            obj_id = self._obj_ids[rng.integers(len(self._obj_ids))]
            # a false detection's mask is its box; in the silhouette mode it poses as a
            # silhouette, as it always has (the figures measured with it stay comparable)
            kind = "box" if cfg.masks == "box" else "silhouette"
            out.append((Detection(obj_id, bbox, uv, cov, mask, 0.5, kind), -1))
        return out
