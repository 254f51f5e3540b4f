"""Writes BOP-format datasets: ``camera.json``, the catalog under ``models/``, and per scene
``rgb/``, ``depth/``, ``mask_visib/``, ``scene_camera.json``, ``scene_gt.json`` and
``scene_gt_info.json``.

Files are written byte-for-byte deterministically: JSON with sorted integer keys and fixed float
formatting, PNGs with a fixed compression level.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from posefuse.estimator.core.camera import Camera
from posefuse.estimator.core.objects import Catalog, write_catalog
from posefuse.evaluation.eval_points import with_eval_points

DEPTH_SCALE = 0.1  # BOP: depth_mm = png_value * depth_scale
# lossless as every PNG; the rows predicted from the row above, and zlib's fast run-length
# matching: a rendered view's sensor noise leaves its long matches nothing to find. On a 2-core
# CPU a 1280x720 view's RGB took 39 instead of 170 ms, its depth 19 instead of 67 and a mask 7
# instead of 15, the files no larger (against level 3 with every filter tried per row, as
# written until 2026-12-07). The level comes first: OpenCV resets the strategy when it is set.
# The row filter needs OpenCV 4.12.
PNG_PARAMS = [
    cv2.IMWRITE_PNG_COMPRESSION,
    1,
    cv2.IMWRITE_PNG_FILTER,
    cv2.IMWRITE_PNG_FILTER_UP,
    cv2.IMWRITE_PNG_STRATEGY,
    cv2.IMWRITE_PNG_STRATEGY_RLE,
]


def _round(values, ndigits: int) -> list[float]:
    return [round(float(v), ndigits) + 0.0 for v in np.asarray(values).reshape(-1)]


def bbox_xywh(mask: np.ndarray) -> list[int]:
    """BOP box [x, y, w, h] of a (H, W) bool mask; [-1, -1, -1, -1] when empty."""
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return [-1, -1, -1, -1]
    return [
        int(xs.min()),
        int(ys.min()),
        int(xs.max() - xs.min() + 1),
        int(ys.max() - ys.min() + 1),
    ]


def write_dataset_header(root: str | Path, camera: Camera, catalog: Catalog) -> Path:
    """``camera.json`` and ``models/`` of a dataset."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    cam = {
        "cx": camera.cx,
        "cy": camera.cy,
        "depth_scale": DEPTH_SCALE,
        "fx": camera.fx,
        "fy": camera.fy,
        "height": camera.height,
        "width": camera.width,
    }
    (root / "camera.json").write_text(json.dumps(cam, indent=2) + "\n")
    write_catalog(root / "models", with_eval_points(catalog))
    return root


class SceneWriter:
    """Collects the views of one scene and writes its files; JSON files are written on close."""

    def __init__(self, split_dir: str | Path, scene_id: int):
        self.dir = Path(split_dir) / f"{scene_id:06d}"
        for sub in ("rgb", "depth", "mask_visib"):
            (self.dir / sub).mkdir(parents=True, exist_ok=True)
        self.scene_camera: dict[int, dict] = {}
        self.scene_gt: dict[int, list] = {}
        self.scene_gt_info: dict[int, list] = {}

    def add_view(
        self,
        im_id: int,
        camera: Camera,
        T_cam_world: np.ndarray,
        rgb: np.ndarray,
        depth_m: np.ndarray,
        gts: list[tuple[int, np.ndarray]],
        masks_visib: list[np.ndarray],
        masks_full: list[np.ndarray],
    ) -> None:
        """One image with its ground truth.

        Args:
            T_cam_world: (4, 4) metres.
            rgb: (H, W, 3) uint8 RGB.
            depth_m: (H, W) float metres, 0 = no depth.
            gts: per instance (obj_id, T_cam_obj (4, 4) metres), in the scene's instance order.
            masks_visib, masks_full: per instance (H, W) bool visible and unoccluded silhouettes.
        """
        cv2.imwrite(
            str(self.dir / "rgb" / f"{im_id:06d}.png"),
            cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR),
            PNG_PARAMS,
        )
        depth_units = np.round(depth_m * 1000.0 / DEPTH_SCALE)
        depth_png = np.clip(depth_units, 0, 65535).astype(np.uint16)
        cv2.imwrite(str(self.dir / "depth" / f"{im_id:06d}.png"), depth_png, PNG_PARAMS)
        self.scene_camera[im_id] = {
            "cam_K": _round(camera.K, 6),
            "cam_R_w2c": _round(T_cam_world[:3, :3], 12),
            "cam_t_w2c": _round(T_cam_world[:3, 3] * 1000.0, 9),
            "depth_scale": DEPTH_SCALE,
        }
        gt_list, info_list = [], []
        valid_depth = depth_png > 0
        for gt_idx, ((obj_id, T_cam_obj), visib, full) in enumerate(
            zip(gts, masks_visib, masks_full, strict=True)
        ):
            cv2.imwrite(
                str(self.dir / "mask_visib" / f"{im_id:06d}_{gt_idx:06d}.png"),
                visib.astype(np.uint8) * 255,
                PNG_PARAMS,
            )
            gt_list.append(
                {
                    "cam_R_m2c": _round(T_cam_obj[:3, :3], 12),
                    "cam_t_m2c": _round(T_cam_obj[:3, 3] * 1000.0, 9),
                    "obj_id": int(obj_id),
                }
            )
            n_all = int(full.sum())
            n_visib = int((visib & full).sum()) if n_all else int(visib.sum())
            info_list.append(
                {
                    "bbox_obj": bbox_xywh(full),
                    "bbox_visib": bbox_xywh(visib),
                    "px_count_all": n_all,
                    "px_count_valid": int((full & valid_depth).sum()),
                    "px_count_visib": n_visib,
                    "visib_fract": round(n_visib / n_all, 9) if n_all else 0.0,
                }
            )
        self.scene_gt[im_id] = gt_list
        self.scene_gt_info[im_id] = info_list

    def close(self) -> None:
        for name, data in (
            ("scene_camera.json", self.scene_camera),
            ("scene_gt.json", self.scene_gt),
            ("scene_gt_info.json", self.scene_gt_info),
        ):
            ordered = {str(k): data[k] for k in sorted(data)}
            (self.dir / name).write_text(json.dumps(ordered, indent=2, sort_keys=True) + "\n")
