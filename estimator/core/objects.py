"""Object models and the BOP object catalog (``models/obj_XXXXXX.ply`` + ``models_info.json``,
and ``models_eval/obj_XXXXXX.ply`` when the catalog stores the points pose errors are evaluated
on: ``posefuse.evaluation.eval_points`` derives them; the estimator never reads them).

In memory everything is in metres; the catalog on disk is in millimetres, as BOP has it.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial.distance import pdist

from posefuse.estimator.core.errors import CatalogError, MeshError
from posefuse.estimator.core.symmetry import (
    ContinuousSymmetry,
    SymmetryAxis,
    describe_symmetries,
    detect_symmetries,
    symmetry_transforms,
)

EVAL_DIR = "models_eval"
UNITS_TO_METRES = {"m": 1.0, "cm": 1e-2, "mm": 1e-3}
PLAUSIBLE_DIAMETER_M = (0.005, 2.0)
N_MODEL_POINTS = 2000
MODEL_POINTS_SEED = 0


@dataclass(frozen=True, eq=False)
class ObjectModel:
    """One rigid object class.

    Attributes:
        obj_id: BOP object id (>= 1).
        name: human name, e.g. ``"gear"``.
        mesh: the surface in metres, in the object frame.
        diameter: largest distance between two mesh vertices, metres (BOP's definition).
        points: (N, 3) seeded uniform surface samples in metres, used by the estimator (box
            sizes, overlays, baselines); never by the pose errors.
        symmetries_discrete: (D, 4, 4) discrete symmetries without the identity, metres.
        symmetries_continuous: continuous symmetry axes (offset in metres).
        stored_eval_points: (M, 3) the catalog's ``models_eval`` points, metres, when stored
            (``posefuse.evaluation.eval_points.eval_points`` derives them otherwise).
        near_symmetries: groups the symmetry detection found almost, not quite, exact and did
            not claim (``SymmetryReport.alternatives``, the flags of the contact sheet: a gear's
            teeth beside the hub that breaks them). Their turns the views are not asked about
            are published as the pose's alternatives.
    """

    obj_id: int
    name: str
    mesh: trimesh.Trimesh
    diameter: float
    points: np.ndarray  # (N, 3)
    symmetries_discrete: np.ndarray  # (D, 4, 4)
    symmetries_continuous: tuple[ContinuousSymmetry, ...] = ()
    stored_eval_points: np.ndarray | None = None  # (M, 3)
    near_symmetries: tuple[SymmetryAxis, ...] = ()

    @property
    def is_symmetric(self) -> bool:
        """True when the model has any symmetry."""
        return len(self.symmetries_discrete) > 0 or len(self.symmetries_continuous) > 0

    def symmetry_transforms(self, max_step_rad: float = np.deg2rad(1.0)) -> np.ndarray:
        """(S, 4, 4) all symmetries with the identity first, continuous axes discretised."""
        return symmetry_transforms(
            self.symmetries_discrete, self.symmetries_continuous, max_step_rad
        )

    def describe_symmetries(self) -> str:
        return describe_symmetries(self.symmetries_discrete, self.symmetries_continuous)


def load_mesh(path: str | Path, units: str = "mm", check_size: bool = True) -> trimesh.Trimesh:
    """Read an STL, PLY or OBJ surface and convert it to metres.

    ``check_size`` refuses a part whose diameter, read in ``units``, lies outside 5 mm .. 2 m:
    almost always a unit mistake (a millimetre mesh read as metres is a 100 m part).

    Raises:
        MeshError: the file is missing, not a mesh, empty, or has non-finite vertices.
    """
    path = Path(path)
    if units not in UNITS_TO_METRES:
        raise MeshError(path, f"unknown units {units!r}; use one of {sorted(UNITS_TO_METRES)}")
    if not path.is_file():
        raise MeshError(path, "no such mesh file")
    if path.suffix.lower() not in (".stl", ".ply", ".obj"):
        raise MeshError(path, f"unsupported mesh format {path.suffix!r}; use .stl, .ply or .obj")
    try:
        loaded = trimesh.load(path, force="mesh", process=True)
    except Exception as exc:  # trimesh raises many types for corrupt files
        raise MeshError(path, f"cannot read mesh: {exc}") from None
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise MeshError(path, "file holds no triangles")
    if not np.all(np.isfinite(loaded.vertices)):
        raise MeshError(path, "mesh has non-finite vertex coordinates")
    if len(loaded.faces) < 4:
        raise MeshError(path, f"mesh has {len(loaded.faces)} triangles; a part needs a surface")
    mesh = loaded.copy()
    mesh.apply_scale(UNITS_TO_METRES[units])
    if mesh.area <= 0:
        raise MeshError(path, "mesh has zero surface area")
    if check_size:
        diameter = mesh_diameter(mesh)
        if not PLAUSIBLE_DIAMETER_M[0] <= diameter <= PLAUSIBLE_DIAMETER_M[1]:
            # the units that make it most like a typical part (10 cm, in log scale)
            sizes = {u: diameter / UNITS_TO_METRES[units] * f for u, f in UNITS_TO_METRES.items()}
            best = min(sizes, key=lambda u: abs(np.log(sizes[u] / 0.1)))
            hint = (
                f"; did you mean --units {best} ({_length(sizes[best])})?" if best != units else ""
            )
            raise MeshError(
                path,
                f"diameter {_length(diameter)} read in {units} is implausible for a part "
                f"(between 5 mm and 2 m expected){hint}",
            )
    return mesh


def _length(metres: float) -> str:
    return f"{metres * 1000:.3g} mm" if metres < 1 else f"{metres:.4g} m"


def mesh_diameter(mesh: trimesh.Trimesh) -> float:
    """Largest distance between two vertices (on the convex hull, as BOP computes it)."""
    try:
        pts = np.asarray(mesh.convex_hull.vertices)
    except Exception:  # flat or degenerate meshes have no 3D hull
        pts = np.asarray(mesh.vertices)
    if len(pts) > 4000:
        pts = pts[:: int(np.ceil(len(pts) / 4000))]
    return float(pdist(pts).max())


def sample_model_points(
    mesh: trimesh.Trimesh, n: int = N_MODEL_POINTS, seed: int = 0
) -> np.ndarray:
    """(n, 3) uniform surface samples with a fixed seed."""
    pts, _ = trimesh.sample.sample_surface(mesh, n, seed=seed)
    return np.asarray(pts, dtype=np.float64)


def make_model(
    obj_id: int,
    name: str,
    mesh: trimesh.Trimesh,
    symmetries_discrete: np.ndarray | None = None,
    symmetries_continuous: tuple[ContinuousSymmetry, ...] | None = None,
    detect: bool = True,
    near_symmetries: tuple[SymmetryAxis, ...] | None = None,
) -> ObjectModel:
    """Build an ObjectModel from a mesh in metres.

    Symmetries given by the caller (e.g. from ``models_info.json``) are used as they are; when
    none are given and ``detect`` is True they are detected from the mesh, and the groups the
    detection did not claim become its near-symmetries (unless the caller gives those too).
    """
    diameter = mesh_diameter(mesh)
    if symmetries_discrete is None and symmetries_continuous is None and detect:
        report = detect_symmetries(mesh, diameter)
        symmetries_discrete, symmetries_continuous = report.discrete, report.continuous
        if near_symmetries is None:
            near_symmetries = report.alternatives
    disc = np.zeros((0, 4, 4)) if symmetries_discrete is None else np.asarray(symmetries_discrete)
    cont = tuple(symmetries_continuous or ())
    return ObjectModel(
        obj_id=int(obj_id),
        name=name,
        mesh=mesh,
        diameter=diameter,
        points=sample_model_points(mesh, seed=MODEL_POINTS_SEED),
        symmetries_discrete=disc.reshape(-1, 4, 4),
        symmetries_continuous=cont,
        near_symmetries=tuple(near_symmetries or ()),
    )


class Catalog(Mapping[int, ObjectModel]):
    """The objects of one BOP catalog, by obj_id."""

    def __init__(
        self, models: Mapping[int, ObjectModel] | list[ObjectModel], root: Path | None = None
    ):
        items = models.values() if isinstance(models, Mapping) else models
        self._models = {m.obj_id: m for m in sorted(items, key=lambda m: m.obj_id)}
        self.root = root

    def __getitem__(self, obj_id: int) -> ObjectModel:
        try:
            return self._models[obj_id]
        except KeyError:
            where = f" in {self.root}" if self.root else ""
            raise CatalogError(
                self.root or "catalog", f"no object with obj_id {obj_id}{where}"
            ) from None

    def __contains__(self, obj_id: object) -> bool:
        return obj_id in self._models

    def __iter__(self) -> Iterator[int]:
        return iter(self._models)

    def __len__(self) -> int:
        return len(self._models)

    def by_name(self, name: str) -> ObjectModel:
        for m in self._models.values():
            if m.name == name:
                return m
        raise CatalogError(self.root or "catalog", f"no object named {name!r}")


def model_path(models_dir: Path, obj_id: int) -> Path:
    return Path(models_dir) / f"obj_{obj_id:06d}.ply"


def _info_entry(model: ObjectModel) -> dict:
    mm = 1000.0
    lo, hi = model.mesh.bounds * mm
    entry: dict = {
        "diameter": round(model.diameter * mm, 6),
        "min_x": round(float(lo[0]), 6),
        "min_y": round(float(lo[1]), 6),
        "min_z": round(float(lo[2]), 6),
        "size_x": round(float(hi[0] - lo[0]), 6),
        "size_y": round(float(hi[1] - lo[1]), 6),
        "size_z": round(float(hi[2] - lo[2]), 6),
        "name": model.name,
    }
    if len(model.symmetries_discrete):
        syms = []
        for T in model.symmetries_discrete:
            T_mm = np.array(T, dtype=np.float64)
            T_mm[:3, 3] *= mm
            syms.append([round(float(x), 9) for x in T_mm.reshape(-1)])
        entry["symmetries_discrete"] = syms
    if model.symmetries_continuous:
        entry["symmetries_continuous"] = [
            {
                "axis": [round(float(a), 9) for a in s.axis],
                "offset": [round(float(o) * mm, 6) for o in s.offset],
            }
            for s in model.symmetries_continuous
        ]
    if model.near_symmetries:
        # not BOP's: the groups almost found (ObjectModel.near_symmetries)
        entry["near_symmetries"] = [
            {
                "axis": [round(float(a), 9) for a in s.axis],
                "order": int(s.order),
                "residual": round(float(s.residual), 6),
            }
            for s in model.near_symmetries
        ]
    return entry


def _parse_near_symmetries(entry: dict, where: str, info_path: Path) -> tuple[SymmetryAxis, ...]:
    """The entry's ``near_symmetries`` (posefuse's key; absent: none)."""
    out = []
    for i, near in enumerate(entry.get("near_symmetries", [])):
        try:
            axis = np.asarray(near["axis"], dtype=np.float64).reshape(3)
            order = int(near["order"])
            residual = float(near.get("residual", 0.0))
        except (KeyError, TypeError, ValueError):
            raise CatalogError(
                info_path, f"{where}: near_symmetries[{i}] needs axis[3] and an integer order"
            ) from None
        n = np.linalg.norm(axis)
        if not np.isfinite(n) or n < 1e-9 or order < 2 or not np.isfinite(residual):
            raise CatalogError(
                info_path, f"{where}: near_symmetries[{i}] needs a unit axis and an order >= 2"
            )
        out.append(SymmetryAxis(tuple(float(a) for a in axis / n), order, residual))
    return tuple(out)


def eval_points_path(models_dir: str | Path, obj_id: int) -> Path:
    """``models_eval/obj_XXXXXX.ply`` inside a catalog folder."""
    return Path(models_dir) / EVAL_DIR / f"obj_{obj_id:06d}.ply"


def write_eval_points(path: str | Path, pts_m: np.ndarray) -> Path:
    """A binary PLY point cloud in millimetres (BOP's unit)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    cloud = trimesh.PointCloud(np.asarray(pts_m, dtype=np.float64) * 1000.0)
    path.write_bytes(trimesh.exchange.ply.export_ply(cloud, encoding="binary"))
    return path


def read_eval_points(path: str | Path) -> np.ndarray:
    """(N, 3) metres from a PLY written by :func:`write_eval_points` (or any PLY's vertices).

    Raises:
        ValueError: the file holds no finite 3D points.
    """
    loaded = trimesh.load(Path(path), process=False)
    pts = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0 or not np.all(np.isfinite(pts)):
        raise ValueError("holds no finite 3D points")
    return pts / 1000.0


def write_catalog(models_dir: str | Path, models: Catalog | list[ObjectModel]) -> Path:
    """Write a BOP catalog: ``obj_XXXXXX.ply`` (binary, mm), ``models_info.json``, and the
    ``models_eval`` points of the models that carry them (``stored_eval_points``;
    ``posefuse.evaluation.eval_points.with_eval_points`` derives them first)."""
    models_dir = Path(models_dir)
    models_dir.mkdir(parents=True, exist_ok=True)
    items = list(models.values()) if isinstance(models, Catalog) else list(models)
    info = {}
    for model in sorted(items, key=lambda m: m.obj_id):
        mesh_mm = model.mesh.copy()
        mesh_mm.apply_scale(1000.0)
        model_path(models_dir, model.obj_id).write_bytes(
            trimesh.exchange.ply.export_ply(mesh_mm, encoding="binary", include_attributes=False)
        )
        info[str(model.obj_id)] = _info_entry(model)
        if model.stored_eval_points is not None:
            write_eval_points(eval_points_path(models_dir, model.obj_id), model.stored_eval_points)
    (models_dir / "models_info.json").write_text(json.dumps(info, indent=2) + "\n")
    return models_dir


def _parse_symmetries(entry: dict, where: str, info_path: Path):
    disc = []
    for i, sym in enumerate(entry.get("symmetries_discrete", [])):
        arr = np.asarray(sym, dtype=np.float64)
        if arr.size != 16 or not np.all(np.isfinite(arr)):
            raise CatalogError(
                info_path, f"{where}: symmetries_discrete[{i}] is not 16 finite numbers"
            )
        T = arr.reshape(4, 4).copy()
        R = T[:3, :3]
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0:
            raise CatalogError(info_path, f"{where}: symmetries_discrete[{i}] is not a rotation")
        T[:3, 3] /= 1000.0
        disc.append(T)
    cont = []
    for i, sym in enumerate(entry.get("symmetries_continuous", [])):
        try:
            axis = np.asarray(sym["axis"], dtype=np.float64).reshape(3)
            offset = np.asarray(sym.get("offset", [0, 0, 0]), dtype=np.float64).reshape(3) / 1000.0
        except (KeyError, TypeError, ValueError):
            raise CatalogError(
                info_path, f"{where}: symmetries_continuous[{i}] needs axis[3] and offset[3]"
            ) from None
        n = np.linalg.norm(axis)
        if not np.isfinite(n) or n < 1e-9 or not np.all(np.isfinite(offset)):
            raise CatalogError(info_path, f"{where}: symmetries_continuous[{i}] has a bad axis")
        cont.append(ContinuousSymmetry(tuple(axis / n), tuple(offset)))
    return np.array(disc).reshape(-1, 4, 4), tuple(cont)


def load_catalog(models_dir: str | Path, detect_symmetries_if_missing: bool = False) -> Catalog:
    """Read a BOP catalog folder.

    Symmetries come from ``models_info.json`` (BOP semantics: absent keys mean no symmetry),
    unless ``detect_symmetries_if_missing`` asks to detect them for entries that have neither key.

    Raises:
        CatalogError: the folder or ``models_info.json`` is missing or malformed.
        MeshError: a listed model file is missing or corrupt.
    """
    models_dir = Path(models_dir)
    info_path = models_dir / "models_info.json"
    if not models_dir.is_dir():
        raise CatalogError(models_dir, "no such catalog folder")
    if not info_path.is_file():
        raise CatalogError(info_path, "missing; a BOP catalog needs models_info.json")
    try:
        info = json.loads(info_path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise CatalogError(info_path, f"not valid JSON: {exc}") from None
    if not isinstance(info, dict) or not info:
        raise CatalogError(info_path, "must be a non-empty object keyed by obj_id")
    models = []
    for key, entry in info.items():
        where = f"obj_id {key}"
        if not key.isdigit() or int(key) < 1:
            raise CatalogError(info_path, f"key {key!r} is not a positive integer obj_id")
        if not isinstance(entry, dict):
            raise CatalogError(info_path, f"{where}: entry must be an object")
        obj_id = int(key)
        mesh = load_mesh(model_path(models_dir, obj_id), units="mm", check_size=False)
        has_syms = "symmetries_discrete" in entry or "symmetries_continuous" in entry
        disc, cont = _parse_symmetries(entry, where, info_path)
        name = str(entry.get("name", f"obj_{obj_id:06d}"))
        if has_syms or not detect_symmetries_if_missing:
            near = _parse_near_symmetries(entry, where, info_path)
            model = make_model(obj_id, name, mesh, disc, cont, detect=False, near_symmetries=near)
        else:
            model = make_model(obj_id, name, mesh, detect=True)
        eval_path = eval_points_path(models_dir, obj_id)
        if eval_path.is_file():
            try:
                stored = read_eval_points(eval_path)
            except Exception as exc:  # trimesh raises many types for corrupt files
                raise CatalogError(eval_path, f"evaluation points: {exc}") from None
            model = dataclasses.replace(model, stored_eval_points=stored)
        models.append(model)
    return Catalog(models, root=models_dir)
