"""BOP's single-image test scenes made multi-view.

A BOP test image stands alone: its ground truth gives each object's pose in that camera
(``T_cam_obj``) and no camera pose. Where the objects of a group of images stayed put relative
to each other, one of them (the anchor) can stand for the world: in each image
``T_cam_world = T_cam_anchor``, so every other object's world pose
``T_world_obj = T_world_cam @ T_cam_obj`` is fixed across the group, checked here to within
``max_spread_mm`` and ``max_spread_deg``. That is how ``../shared/realdata/lmo_mv`` was cut from
LM-O (its README): :func:`multiview_scene` builds one such scene's files from a BOP scene,
:func:`write_multiview_scene` writes them.

Each image keeps its own annotations (of the group's objects only, in their stored order), its
``cam_K`` and ``depth_scale``; ``cam_R_w2c`` / ``cam_t_w2c`` are the anchor's pose (mm).
Rotations stored orthonormal only to 1e-2 are projected as ``evaluation.dataset`` reads them.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from posefuse.estimator.core.errors import DatasetError
from posefuse.estimator.core.geometry import invert
from posefuse.evaluation.dataset import BopScene


@dataclass(frozen=True)
class MultiviewGroup:
    """Images of one BOP scene in which the objects ``obj_ids`` stayed put; ``anchor`` (one of
    them) is the world."""

    im_ids: tuple[int, ...]
    obj_ids: tuple[int, ...]
    anchor: int

    def __post_init__(self) -> None:
        if self.anchor not in self.obj_ids:
            raise ValueError(f"the anchor {self.anchor} is not one of the objects {self.obj_ids}")
        if len(set(self.im_ids)) != len(self.im_ids) or not self.im_ids:
            raise ValueError(f"im_ids must be distinct and not empty, got {self.im_ids}")


@dataclass(frozen=True)
class MultiviewScene:
    """The files of one multi-view scene (BOP JSON, ready to dump) and how far each object's
    world pose moved across its images: spread[obj_id] = (mm, degrees), the largest distance
    of one image's world pose from the group's mean."""

    scene_camera: dict
    scene_gt: dict
    scene_gt_info: dict
    spread: dict[int, tuple[float, float]]


def _world_spread(T_world_obj: np.ndarray) -> tuple[float, float]:
    """T_world_obj: (N, 4, 4) metres. (mm, degrees) from their mean."""
    t = T_world_obj[:, :3, 3]
    mm = 1000.0 * float(np.linalg.norm(t - t.mean(axis=0), axis=1).max())
    R = Rotation.from_matrix(T_world_obj[:, :3, :3])
    deg = float(np.degrees((R.mean().inv() * R).magnitude()).max())
    return mm, deg


def multiview_scene(
    scene: BopScene,
    group: MultiviewGroup,
    max_spread_mm: float = 3.0,
    max_spread_deg: float = 1.0,
) -> MultiviewScene:
    """The multi-view scene of ``group`` cut from ``scene``; DatasetError naming the image and
    the object where one is missing or moved beyond the spread allowed."""
    gt_path = scene.path / "scene_gt.json"
    cameras, gts, infos = {}, {}, {}
    world: dict[int, list[np.ndarray]] = {o: [] for o in group.obj_ids}
    for im_id in group.im_ids:
        annotated = scene.ground_truth(im_id)
        by_obj = {g.obj_id: g for g in annotated}
        missing = [o for o in group.obj_ids if o not in by_obj]
        if missing:
            raise DatasetError(gt_path, f"image {im_id}: no ground truth of object {missing[0]}")
        if len(by_obj) != len(annotated):
            raise DatasetError(gt_path, f"image {im_id}: an object annotated twice")
        T_cam_world = by_obj[group.anchor].T_cam_obj
        T_world_cam = invert(T_cam_world)
        camera = scene.intrinsics(im_id)
        entry = {
            "cam_K": camera.K.reshape(-1).tolist(),
            "cam_R_w2c": T_cam_world[:3, :3].reshape(-1).tolist(),
            "cam_t_w2c": (1000.0 * T_cam_world[:3, 3]).tolist(),
        }
        stored = scene.stored_camera(im_id)
        if "depth_scale" in stored:
            entry["depth_scale"] = stored["depth_scale"]
        cameras[str(im_id)] = entry
        kept = [g for g in annotated if g.obj_id in world]
        gts[str(im_id)] = [
            {
                "cam_R_m2c": g.T_cam_obj[:3, :3].reshape(-1).tolist(),
                "cam_t_m2c": (1000.0 * g.T_cam_obj[:3, 3]).tolist(),
                "obj_id": g.obj_id,
            }
            for g in kept
        ]
        stored_infos = scene.stored_gt_info(im_id)
        if stored_infos:
            infos[str(im_id)] = [stored_infos[g.gt_idx] for g in kept]
        for g in kept:
            world[g.obj_id].append(T_world_cam @ g.T_cam_obj)
    spread = {o: _world_spread(np.stack(Ts)) for o, Ts in world.items()}
    for obj_id, (mm, deg) in spread.items():
        if mm > max_spread_mm or deg > max_spread_deg:
            raise DatasetError(
                gt_path,
                f"object {obj_id} moved {mm:.1f} mm / {deg:.2f} deg relative to the anchor "
                f"{group.anchor} across images {group.im_ids} (allowed {max_spread_mm:g} mm / "
                f"{max_spread_deg:g} deg): these images are not one multi-view scene",
            )
    return MultiviewScene(cameras, gts, infos, spread)


def write_multiview_scene(built: MultiviewScene, out_dir: str | Path) -> Path:
    """Write ``built`` as a BOP scene folder (its JSON files; images are the caller's)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = {"scene_camera.json": built.scene_camera, "scene_gt.json": built.scene_gt}
    if built.scene_gt_info:
        files["scene_gt_info.json"] = built.scene_gt_info
    for name, content in files.items():
        (out / name).write_text(json.dumps(content, indent=1))
    return out
