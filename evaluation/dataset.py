"""Reads BOP datasets: ``models/`` (the catalog), ``camera.json`` and ``{split}/{scene_id:06d}/``
with ``scene_camera.json``, ``scene_gt.json``, ``scene_gt_info.json``, ``rgb/``, ``depth/`` and
``mask_visib/``.

Poses come out in metres (BOP stores millimetres). ``cam_R_w2c``/``cam_t_w2c`` of
``scene_camera.json`` are ``T_cam_world``; a view without them has no known camera pose, which a
multi-view estimator cannot use, so it is refused with the file and key named (its ground truth
alone is still read by :meth:`BopScene.ground_truth`: that is how BOP's single-image test sets
become multi-view scenes, see ``evaluation.multiview``).

Rotations must be rotations. BOP's real datasets store them orthonormal only to about 1e-2
(LM-O: ``max |R R^T - I|`` up to 9.4e-3): a rotation within ``ORTHONORMAL_REPAIR`` of
orthonormal is replaced by the nearest rotation (in the Frobenius norm, scipy's
``Rotation.from_matrix``) and counted, one
:class:`~posefuse.estimator.core.errors.DatasetWarning` per file naming it and how many; beyond
that, or with a determinant below zero, the file is refused.
"""

from __future__ import annotations

import json
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from posefuse.estimator.core.bin_region import BinRegion
from posefuse.estimator.core.camera import Camera
from posefuse.estimator.core.errors import DatasetError, DatasetWarning
from posefuse.estimator.core.geometry import invert
from posefuse.estimator.core.objects import Catalog, load_catalog


@dataclass(frozen=True, eq=False)
class GroundTruth:
    """One annotated instance in one view.

    T_cam_obj: (4, 4) metres. bbox_visib, bbox_obj: [x, y, w, h] pixels ([-1]*4 when empty).
    """

    obj_id: int
    gt_idx: int
    T_cam_obj: np.ndarray
    visib_fract: float
    bbox_visib: tuple[int, int, int, int]
    bbox_obj: tuple[int, int, int, int]
    px_count_visib: int


@dataclass(frozen=True, eq=False)
class BopView:
    """One image of a scene: camera, its pose T_world_cam (4, 4) metres, the annotations."""

    scene_id: int
    im_id: int
    camera: Camera
    T_world_cam: np.ndarray
    gts: tuple[GroundTruth, ...]

    @property
    def T_cam_world(self) -> np.ndarray:
        return invert(self.T_world_cam)


def _read_json(path: Path) -> dict:
    if not path.is_file():
        raise DatasetError(path, "file not found")
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DatasetError(path, f"not valid JSON ({exc})") from None


def _matrix(entry: dict, key: str, shape: tuple[int, ...], path: Path, where: str) -> np.ndarray:
    if key not in entry:
        raise DatasetError(path, f"{where}: missing {key!r}")
    try:
        values = np.asarray(entry[key], dtype=np.float64)
    except (TypeError, ValueError):
        raise DatasetError(path, f"{where}: {key!r} is not a list of numbers") from None
    if values.size != int(np.prod(shape)) or not np.all(np.isfinite(values)):
        raise DatasetError(path, f"{where}: {key!r} needs {np.prod(shape)} finite numbers")
    return values.reshape(shape)


ORTHONORMAL_EXACT = 1e-5  # max |R R^T - I| of a rotation used as stored
ORTHONORMAL_REPAIR = 1e-2  # up to this, projected to the nearest rotation and counted


def _repair_rotations(path: Path, entries: dict, key: str) -> dict:
    """Replace, in a parsed scene file, each rotation ``key`` stored orthonormal only to within
    ``ORTHONORMAL_REPAIR`` by the nearest rotation; one DatasetWarning for the file. Malformed
    entries and rotations further off are left for the view that reads them to refuse."""
    count, worst = 0, 0.0
    for value in entries.values():
        for entry in value if isinstance(value, list) else [value]:
            try:
                R = np.asarray(entry[key], dtype=np.float64).reshape(3, 3)
            except (KeyError, TypeError, ValueError):
                continue
            if not np.all(np.isfinite(R)) or np.linalg.det(R) <= 0:
                continue
            off = float(np.abs(R @ R.T - np.eye(3)).max())
            if ORTHONORMAL_EXACT < off <= ORTHONORMAL_REPAIR:
                entry[key] = Rotation.from_matrix(R).as_matrix().reshape(-1).tolist()  # the nearest
                count, worst = count + 1, max(worst, off)
    if count:
        reason = (
            f"{count} rotations ({key}) orthonormal only to {worst:.1e} (up to "
            f"{ORTHONORMAL_REPAIR:g} accepted) were replaced by the nearest rotation"
        )
        warnings.warn(DatasetWarning(path, count, reason), stacklevel=2)
    return entries


def _rigid(R: np.ndarray, t_mm: np.ndarray, path: Path, where: str) -> np.ndarray:
    off = float(np.abs(R @ R.T - np.eye(3)).max())
    if off > ORTHONORMAL_EXACT or np.linalg.det(R) < 0:
        raise DatasetError(
            path, f"{where}: rotation is not a rotation matrix (max |R R^T - I| = {off:.1e})"
        )
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t_mm / 1000.0
    return T


class BopScene:
    """One scene folder; JSON files are parsed when first needed, images read on demand."""

    def __init__(self, dataset: BopDataset, scene_id: int, path: Path):
        self.dataset = dataset
        self.scene_id = scene_id
        self.path = path

    @cached_property
    def _camera_json(self) -> dict:
        path = self.path / "scene_camera.json"
        return _repair_rotations(path, _read_json(path), "cam_R_w2c")

    @cached_property
    def _gt_json(self) -> dict:
        path = self.path / "scene_gt.json"
        return _repair_rotations(path, _read_json(path), "cam_R_m2c")

    @cached_property
    def _gt_info_json(self) -> dict:
        path = self.path / "scene_gt_info.json"
        return _read_json(path) if path.is_file() else {}

    @cached_property
    def im_ids(self) -> tuple[int, ...]:
        try:
            return tuple(sorted(int(k) for k in self._camera_json))
        except ValueError:
            raise DatasetError(self.path / "scene_camera.json", "keys must be image ids") from None

    def stored_camera(self, im_id: int) -> dict:
        """One image's entry of ``scene_camera.json`` as stored (rotations repaired)."""
        entry = self._camera_json.get(str(im_id))
        if entry is None:
            raise DatasetError(
                self.path / "scene_camera.json", f"no image {im_id} in scene {self.scene_id}"
            )
        return entry

    def stored_gt_info(self, im_id: int) -> list[dict]:
        """One image's entries of ``scene_gt_info.json`` as stored ([] where it has none)."""
        return list(self._gt_info_json.get(str(im_id), []))

    def intrinsics(self, im_id: int) -> Camera:
        """The camera of one image (``cam_K`` and the dataset's image size)."""
        cam_path = self.path / "scene_camera.json"
        entry = self.stored_camera(im_id)
        K = _matrix(entry, "cam_K", (3, 3), cam_path, f"image {im_id}")
        width, height = self.dataset.image_size
        try:
            return Camera(K, width, height)
        except ValueError as exc:
            raise DatasetError(cam_path, f"image {im_id}: {exc}") from None

    def view(self, im_id: int) -> BopView:
        camera = self.intrinsics(im_id)
        cam_path = self.path / "scene_camera.json"
        entry = self._camera_json[str(im_id)]
        where = f"image {im_id}"
        R = _matrix(entry, "cam_R_w2c", (3, 3), cam_path, where)
        t = _matrix(entry, "cam_t_w2c", (3,), cam_path, where)
        T_cam_world = _rigid(R, t, cam_path, where)
        T_world_cam = invert(T_cam_world)
        return BopView(self.scene_id, im_id, camera, T_world_cam, self.ground_truth(im_id))

    def ground_truth(self, im_id: int) -> tuple[GroundTruth, ...]:
        """The annotated instances of one image (T_cam_obj), whether or not its camera pose is
        known (BOP's single-image test sets store none)."""
        gt_path = self.path / "scene_gt.json"
        gts_raw = self._gt_json.get(str(im_id), [])
        infos = self._gt_info_json.get(str(im_id), [])
        if infos and len(infos) != len(gts_raw):
            raise DatasetError(
                self.path / "scene_gt_info.json",
                f"image {im_id}: {len(infos)} entries but scene_gt.json has {len(gts_raw)}",
            )
        gts = []
        for gt_idx, g in enumerate(gts_raw):
            where = f"image {im_id} instance {gt_idx}"
            if "obj_id" not in g:
                raise DatasetError(gt_path, f"{where}: missing 'obj_id'")
            T = _rigid(
                _matrix(g, "cam_R_m2c", (3, 3), gt_path, where),
                _matrix(g, "cam_t_m2c", (3,), gt_path, where),
                gt_path,
                where,
            )
            info = infos[gt_idx] if infos else {}
            gts.append(
                GroundTruth(
                    obj_id=int(g["obj_id"]),
                    gt_idx=gt_idx,
                    T_cam_obj=T,
                    visib_fract=float(info.get("visib_fract", 1.0)),
                    bbox_visib=tuple(int(v) for v in info.get("bbox_visib", [-1] * 4)),
                    bbox_obj=tuple(int(v) for v in info.get("bbox_obj", [-1] * 4)),
                    px_count_visib=int(info.get("px_count_visib", -1)),
                )
            )
        return tuple(gts)

    def views(self) -> Iterator[BopView]:
        for im_id in self.im_ids:
            yield self.view(im_id)

    def _image_path(self, sub: str, name: str) -> Path:
        for ext in (".png", ".jpg", ".tif"):
            path = self.path / sub / f"{name}{ext}"
            if path.is_file():
                return path
        raise DatasetError(self.path / sub / f"{name}.png", "image not found")

    def load_rgb(self, im_id: int) -> np.ndarray:
        """(H, W, 3) uint8 RGB."""
        path = self._image_path("rgb", f"{im_id:06d}")
        image = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if image is None:
            raise DatasetError(path, "unreadable image")
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)

    def load_depth(self, im_id: int) -> np.ndarray:
        """(H, W) float64 metres, 0 where there is no depth."""
        path = self._image_path("depth", f"{im_id:06d}")
        depth = cv2.imread(str(path), cv2.IMREAD_ANYDEPTH)
        if depth is None:
            raise DatasetError(path, "unreadable depth image")
        scale = float(self._camera_json.get(str(im_id), {}).get("depth_scale", 1.0))
        return depth.astype(np.float64) * scale / 1000.0

    def load_mask_visib(self, im_id: int, gt_idx: int) -> np.ndarray:
        """(H, W) bool visible mask of one annotated instance."""
        path = self._image_path("mask_visib", f"{im_id:06d}_{gt_idx:06d}")
        mask = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if mask is None:
            raise DatasetError(path, "unreadable mask")
        return mask > 127


class BopDataset:
    """A BOP dataset folder and one of its splits."""

    def __init__(self, root: Path, split: str, catalog: Catalog):
        self.root = root
        self.split = split
        self.catalog = catalog
        self.split_dir = root / split
        cam = _read_json(root / "camera.json")
        try:
            self.image_size = (int(cam["width"]), int(cam["height"]))
        except (KeyError, TypeError, ValueError):
            raise DatasetError(root / "camera.json", "needs integer 'width' and 'height'") from None
        self.scene_ids = tuple(
            sorted(int(p.name) for p in self.split_dir.iterdir() if p.is_dir() and p.name.isdigit())
        )
        self._scenes: dict[int, BopScene] = {}

    @property
    def profile(self) -> str:
        """The scene profile ``posefuse synth`` rendered it with (``synth.json``), else
        ``"unknown"`` (a dataset made elsewhere)."""
        path = self.root / "synth.json"
        try:
            return str(json.loads(path.read_text()).get("profile", "unknown"))
        except (OSError, ValueError, AttributeError):
            return "unknown"

    @property
    def bin(self) -> BinRegion | None:
        """The bin the parts lie in, as ``posefuse synth`` recorded it (``synth.json``'s
        ``bin``), else None (a dataset made elsewhere, or before synth recorded it). Raises
        DatasetError naming the file when the record is malformed."""
        path = self.root / "synth.json"
        try:
            record = json.loads(path.read_text())
        except OSError:
            return None
        except ValueError as exc:
            raise DatasetError(path, f"not JSON ({exc})") from None
        if not isinstance(record, dict) or record.get("bin") is None:
            return None
        try:
            return BinRegion.from_json(record["bin"])
        except ValueError as exc:
            raise DatasetError(path, f"'bin': {exc}") from None

    def scene(self, scene_id: int) -> BopScene:
        if scene_id not in self.scene_ids:
            raise DatasetError(self.split_dir, f"no scene {scene_id}; scenes are {self.scene_ids}")
        if scene_id not in self._scenes:
            self._scenes[scene_id] = BopScene(self, scene_id, self.split_dir / f"{scene_id:06d}")
        return self._scenes[scene_id]

    def views(self) -> Iterator[BopView]:
        """Every view of every scene, in (scene_id, im_id) order."""
        for scene_id in self.scene_ids:
            yield from self.scene(scene_id).views()


def load_dataset(
    root: str | Path, split: str = "test", catalog: Catalog | None = None
) -> BopDataset:
    """Open a BOP dataset; the catalog defaults to its ``models/`` folder."""
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(root, "dataset folder not found")
    if not (root / split).is_dir():
        raise DatasetError(root / split, f"split {split!r} not found")
    if catalog is None:
        catalog = load_catalog(root / "models")
    return BopDataset(root, split, catalog)
