"""The two-stage front end's training data: bin views rendered once, kept on disk, cropped on
the fly.

A training set is a folder of numpy memory maps, rendered once per machine and reused by every
run and every resume (the rendering is deterministic in its seeds, so a set rendered again on
another machine is the same set):

- ``full_rgb.u8``: (N, 720, 1280, 3) uint8 views at the camera's resolution, sensor noise
  applied, exactly as test images and the service's frames are made;
- ``full_inst.u8``: (N, 720, 1280) uint8 instance map, 0 for background and the bin, k + 1 for
  the scene's instance k;
- ``small_rgb.u8``: (N, Hs, Ws, 3) the views resized by the detector's input scale with the
  front end's own ``cv2.resize``, padded to a multiple of 16;
- ``instances.npy``: (M, 11) float64, one row per visible instance: view index, instance
  index, class index (1..C), projected model origin (u, v), visible box (x0, y0, x1, y1) in
  image pixels (exclusive ends), visible fraction, visible pixel count;
- ``meta.json``: what was rendered, from which seeds.

Visible fractions come from silhouettes rendered at a quarter of the resolution (counts of the
visible mask against the unoccluded one at the same scale).
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from posefuse.estimator.core.objects import Catalog, load_catalog
from posefuse.estimator.rotation.render import Renderer
from posefuse.sim.materials import part_material, random_material
from posefuse.sim.scenes import PROFILES, REALSENSE_1280x720, make_scene
from posefuse.sim.sensor import SensorModel, apply_rgb
from posefuse.sim.synth import BIN_ID, scene_seed

FULL = REALSENSE_1280x720
INSTANCE_COLUMNS = (
    "view",
    "instance",
    "class",
    "u",
    "v",
    "x0",
    "y0",
    "x1",
    "y1",
    "visib_fract",
    "visible_px",
)


@dataclass(frozen=True)
class RenderSpec:
    """What a training set holds: ``n_scenes`` scenes of ``views`` views, scene seeds
    ``scene_seed(seed_base, 0..n_scenes - 1)``, ``robi_fraction`` of them in the robi profile
    (interleaved), the rest mixed."""

    n_scenes: int
    views: int
    seed_base: int
    robi_fraction: float = 0.5
    small_scale: float = 0.5
    # "catalog": each part as it will be seen (``part_material``); "random": a material drawn
    # per part type and scene (``random_material``), for the shape family's generalist
    materials: str = "catalog"
    # the share of scenes composed from parts rendered alone onto clutter (sim.composite),
    # interleaved; the rest rendered whole
    composite: float = 0.0

    def __post_init__(self):
        if self.materials not in ("catalog", "random"):
            raise ValueError(f"materials must be 'catalog' or 'random', got {self.materials!r}")
        if not 0.0 <= self.composite <= 1.0:
            raise ValueError(f"composite must be in [0, 1], got {self.composite}")

    def key(self) -> str:
        key = (
            f"s{self.n_scenes}_v{self.views}_b{self.seed_base}_r{self.robi_fraction:g}"
            f"_x{self.small_scale:g}"
        )
        if self.materials != "catalog":
            key += f"_m{self.materials}"
        return key if self.composite == 0 else key + f"_c{self.composite:g}"


def profile_of(scene_index: int, robi_fraction: float) -> str:
    """Which profile a training scene uses: ``robi_fraction`` of them, interleaved, are robi."""
    return "robi" if _interleaved(scene_index, robi_fraction) else "mixed"


def is_composed(scene_index: int, composite: float) -> bool:
    """Whether a training scene is composed (sim.composite): ``composite`` of them, interleaved
    by pairs of scenes, so that each kind has both profiles (which alternate scene by scene)."""
    return _interleaved(scene_index // 2, composite)


def _interleaved(k: int, share: float) -> bool:
    return int((k + 1) * share) > int(k * share)


def class_index(catalog: Catalog) -> dict[int, int]:
    """obj_id -> output class index 1..C (0 is background), in obj_id order."""
    return {obj_id: k + 1 for k, obj_id in enumerate(sorted(catalog))}


def small_size(scale: float) -> tuple[int, int]:
    """(width, height) of the detector's input for a 1280x720 view, padded to 16."""
    w, h = round(FULL.width * scale), round(FULL.height * scale)
    return w + (-w % 16), h + (-h % 16)


_CATALOGS: dict[str, Catalog] = {}


def _cached_catalog(catalog_dir: str) -> Catalog:
    if catalog_dir not in _CATALOGS:
        _CATALOGS[catalog_dir] = load_catalog(catalog_dir)
    return _CATALOGS[catalog_dir]


def _scene_renderer(
    catalog_dir: str,
    scene_index: int,
    views: int,
    seed_base: int,
    profile: str,
    materials_kind: str = "catalog",
):
    catalog = _cached_catalog(catalog_dir)
    seed = scene_seed(seed_base, scene_index)
    spec = dataclasses.replace(PROFILES[profile], n_views=views)
    scene = make_scene(catalog, spec, seed, FULL)
    if len(scene.instances) > 254:
        raise ValueError(f"scene {scene_index}: {len(scene.instances)} instances exceed uint8")
    if materials_kind == "random":  # one draw per part type in this scene, from its own stream
        mat_rng = np.random.default_rng([seed, 2])
        drawn = {k: random_material(mat_rng) for k in sorted({i.obj_id for i in scene.instances})}
        materials = [drawn[i.obj_id] for i in scene.instances]
    else:
        materials = [part_material(catalog[i.obj_id]) for i in scene.instances]
    meshes = [catalog[i.obj_id].mesh for i in scene.instances] + [scene.bin_mesh]
    poses = [i.T_world_obj for i in scene.instances] + [np.eye(4)]
    ids = list(range(len(scene.instances))) + [BIN_ID]
    renderer = Renderer(meshes, poses, ids, materials + [scene.bin_material])
    return catalog, scene, renderer, seed


def instance_rows(
    catalog, scene, renderer, T_world_cam: np.ndarray, inst: np.ndarray
) -> np.ndarray:
    """(K, 10) the rows of ``INSTANCE_COLUMNS`` but the view, of one view's visible instances.

    Args:
        inst: (720, 1280) uint8 instance map of the view (k + 1 for instance k).
    """
    classes = class_index(catalog)
    quarter = FULL.scaled(0.25)
    inst_q = cv2.resize(inst, (quarter.width, quarter.height), interpolation=cv2.INTER_NEAREST)
    T_cam_world = np.linalg.inv(T_world_cam)
    rows = []
    for k, inst_k in enumerate(scene.instances):
        ys, xs = np.nonzero(inst == k + 1)
        if len(xs) == 0:
            continue
        t_cam = T_cam_world[:3, :3] @ inst_k.T_world_obj[:3, 3] + T_cam_world[:3, 3]
        if t_cam[2] <= 0:
            continue
        u, v = FULL.project(t_cam)
        full_q = renderer.render_mask(quarter, T_world_cam, k).sum()
        visib = float(min((inst_q == k + 1).sum() / full_q, 1.0)) if full_q else 0.0
        rows.append(
            (
                k,
                classes[inst_k.obj_id],
                u,
                v,
                xs.min(),
                ys.min(),
                xs.max() + 1,
                ys.max() + 1,
                visib,
                len(xs),
            )
        )
    return np.array(rows, np.float64).reshape(-1, 10)


def render_scene(args: tuple) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """One scene's views as (rgb (720, 1280, 3) uint8, instance map (720, 1280) uint8, small
    rgb (Hs, Ws, 3) uint8, instance rows (K, 10): the columns of ``INSTANCE_COLUMNS`` but the
    view). The picklable unit of parallel rendering."""
    catalog_dir, scene_index, views, seed_base, profile, small_scale = args[:6]
    materials_kind = args[6] if len(args) > 6 else "catalog"
    if len(args) > 7 and args[7]:
        return compose_scene(
            catalog_dir, scene_index, views, seed_base, profile, small_scale, materials_kind
        )
    prepared = _scene_renderer(catalog_dir, scene_index, views, seed_base, profile, materials_kind)
    return render_views(*prepared, small_scale)


def compose_scene(
    catalog_dir: str,
    scene_index: int,
    views: int,
    seed_base: int,
    profile: str,
    small_scale: float,
    materials_kind: str = "catalog",
) -> list:
    """A composed scene's views (``sim.composite``), as :func:`render_scene` returns them: its
    cut-outs, parts of the catalog drawn evenly (or one part for a pile, as the robi profile
    heaps one type), then its views composed from them."""
    from posefuse.sim.composite import ComposeSpec, compose_view, part_cutout

    catalog = _cached_catalog(catalog_dir)
    classes = class_index(catalog)
    rng = np.random.default_rng([scene_seed(seed_base, scene_index), 3])
    spec = ComposeSpec()
    ids = sorted(catalog)
    pile = profile == "robi"
    drawn = (
        [ids[int(rng.integers(len(ids)))]] * spec.cutouts
        if pile
        else [ids[int(k)] for k in rng.integers(len(ids), size=spec.cutouts)]
    )
    materials = {}
    cutouts = []
    for obj_id in drawn:
        if obj_id not in materials:
            materials[obj_id] = (
                random_material(rng)
                if materials_kind == "random"
                else part_material(catalog[obj_id])
            )
        model = catalog[obj_id]
        cutouts.append(
            part_cutout(model.mesh, materials[obj_id], classes[obj_id], FULL.K[0, 0], rng, spec)
        )
    sw, sh = round(FULL.width * small_scale), round(FULL.height * small_scale)
    out = []
    for _ in range(views):
        rgb, inst, rows = compose_view(cutouts, pile, FULL.height, FULL.width, rng, spec)
        small = cv2.resize(rgb, (sw, sh), interpolation=cv2.INTER_AREA)
        ph, pw = -sh % 16, -sw % 16
        small = cv2.copyMakeBorder(small, 0, ph, 0, pw, cv2.BORDER_REPLICATE)
        out.append((rgb, inst, small, rows))
    return out


def render_views(catalog, scene, renderer, seed: int, small_scale: float) -> list:
    """The views of a prepared scene (``_scene_renderer``), as :func:`render_scene` returns
    them."""
    rng = np.random.default_rng(seed + 1)
    sw, sh = round(FULL.width * small_scale), round(FULL.height * small_scale)
    out = []
    for T_world_cam in scene.T_world_cams:
        res = renderer.render(FULL, T_world_cam, scene.lighting)
        rgb = apply_rgb(res.image, SensorModel(), rng)
        inst = np.where((res.instance >= 0) & (res.instance != BIN_ID), res.instance + 1, 0)
        inst = inst.astype(np.uint8)
        small = cv2.resize(rgb, (sw, sh), interpolation=cv2.INTER_AREA)
        ph, pw = -sh % 16, -sw % 16
        small = cv2.copyMakeBorder(small, 0, ph, 0, pw, cv2.BORDER_REPLICATE)
        rows = instance_rows(catalog, scene, renderer, T_world_cam, inst)
        out.append((rgb, inst, small, rows))
    return out


@dataclass
class TrainingSet:
    """A rendered training set, opened read-only (see the module docstring)."""

    folder: Path
    full_rgb: np.ndarray  # (N, 720, 1280, 3) uint8 memmap
    full_inst: np.ndarray  # (N, 720, 1280) uint8 memmap
    small_rgb: np.ndarray  # (N, Hs, Ws, 3) uint8 memmap
    instances: np.ndarray  # (M, 11) float64
    meta: dict

    @property
    def n_views(self) -> int:
        return len(self.full_rgb)

    def view_instances(self) -> list[np.ndarray]:
        """Per view, (K, 11) its instance rows."""
        order = self.instances[:, 0].astype(int)
        return [self.instances[order == k] for k in range(self.n_views)]


def open_training_set(folder: str | Path) -> TrainingSet:
    folder = Path(folder)
    meta_path = folder / "meta.json"
    if not meta_path.is_file():
        raise FileNotFoundError(f"{folder}: not a rendered training set (no meta.json)")
    meta = json.loads(meta_path.read_text())
    n = meta["n_views"]
    sw, sh = meta["small_size"]
    return TrainingSet(
        folder,
        np.memmap(folder / "full_rgb.u8", np.uint8, "r", shape=(n, FULL.height, FULL.width, 3)),
        np.memmap(folder / "full_inst.u8", np.uint8, "r", shape=(n, FULL.height, FULL.width)),
        np.memmap(folder / "small_rgb.u8", np.uint8, "r", shape=(n, sh, sw, 3)),
        np.load(folder / "instances.npy"),
        meta,
    )


def _same_views_at_another_scale(folder: Path, spec: RenderSpec) -> Path | None:
    """A complete set beside ``folder`` rendered from the same spec but for another detector
    input scale, or None."""
    want = {k: v for k, v in dataclasses.asdict(spec).items() if k != "small_scale"}
    prefix = folder.name.split("_", 1)[0]
    for candidate in sorted(folder.parent.glob(f"{prefix}_*")):
        meta_path = candidate / "meta.json"
        if candidate == folder or not meta_path.is_file():
            continue
        stored = dict(json.loads(meta_path.read_text())["spec"])
        stored.pop("small_scale", None)
        if stored == want:
            return candidate
    return None


def rescaled_training_set(
    source: str | Path, folder: str | Path, small_scale: float, desc: str = "rescale"
) -> TrainingSet:
    """The training set of ``source`` for another detector input scale, in ``folder``: the same
    full-resolution views, instance maps and rows (linked, not copied, where the file system
    allows), and the detector's input resized from the full views as ``render_scene`` resizes
    them, so the set is the one a rendering at that scale writes."""
    src = open_training_set(source)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for name in ("full_rgb.u8", "full_inst.u8"):
        target = folder / name
        if not target.exists():
            try:
                os.link(src.folder / name, target)
            except OSError:
                shutil.copyfile(src.folder / name, target)
    sw, sh = small_size(small_scale)
    small_rgb = np.memmap(folder / "small_rgb.u8", np.uint8, "w+", shape=(src.n_views, sh, sw, 3))
    w, h = round(FULL.width * small_scale), round(FULL.height * small_scale)
    for k in tqdm(range(src.n_views), desc=desc, unit="view"):
        small = cv2.resize(np.asarray(src.full_rgb[k]), (w, h), interpolation=cv2.INTER_AREA)
        small_rgb[k] = cv2.copyMakeBorder(small, 0, sh - h, 0, sw - w, cv2.BORDER_REPLICATE)
    small_rgb.flush()
    np.save(folder / "instances.npy", src.instances)
    meta = dict(src.meta)
    meta["small_size"] = [sw, sh]
    meta["spec"] = {**src.meta["spec"], "small_scale": small_scale}
    meta["rescaled_from"] = str(src.folder)
    (folder / "meta.json").write_text(json.dumps(meta, indent=2) + "\n")
    return open_training_set(folder)


def render_training_set(
    catalog_dir: str | Path, spec: RenderSpec, root: str | Path, workers: int = 2, desc="render"
) -> TrainingSet:
    """The training set of ``spec`` under ``root``, rendered unless it is there already
    (complete sets only: ``meta.json`` is written last)."""
    from posefuse.estimator.frontend.network import catalog_hash

    # a set belongs to its catalog: the same spec of another catalog is another set
    folder = Path(root) / f"{catalog_hash(_cached_catalog(str(catalog_dir)))[:8]}_{spec.key()}"
    if (folder / "meta.json").is_file():
        return open_training_set(folder)
    other = _same_views_at_another_scale(folder, spec)
    if other is not None:
        return rescaled_training_set(other, folder, spec.small_scale, desc)
    folder.mkdir(parents=True, exist_ok=True)
    n = spec.n_scenes * spec.views
    sw, sh = small_size(spec.small_scale)

    def open_map(name, shape):
        mode = "r+" if (folder / name).is_file() else "w+"
        return np.memmap(folder / name, np.uint8, mode, shape=shape)

    full_rgb = open_map("full_rgb.u8", (n, FULL.height, FULL.width, 3))
    full_inst = open_map("full_inst.u8", (n, FULL.height, FULL.width))
    small_rgb = open_map("small_rgb.u8", (n, sh, sw, 3))
    # a scene is done when its rows are on disk (written after its views): an interrupted
    # rendering goes on where it stopped
    done_dir = folder / "scenes"
    done_dir.mkdir(exist_ok=True)
    todo = [k for k in range(spec.n_scenes) if not (done_dir / f"{k:06d}.npy").is_file()]
    jobs = [
        (
            str(catalog_dir),
            k,
            spec.views,
            spec.seed_base,
            profile_of(k, spec.robi_fraction),
            spec.small_scale,
            spec.materials,
            is_composed(k, spec.composite),
        )
        for k in todo
    ]
    pool = get_context("spawn").Pool(workers) if workers > 1 and jobs else None
    try:
        results = pool.imap(render_scene, jobs) if pool else map(render_scene, jobs)
        with tqdm(
            total=spec.n_scenes, initial=spec.n_scenes - len(todo), desc=desc, unit="scene"
        ) as bar:
            for k, views in zip(todo, results, strict=True):
                scene_rows = []
                for j, (rgb, inst, small, inst_rows) in enumerate(views):
                    index = k * spec.views + j
                    full_rgb[index] = rgb
                    full_inst[index] = inst
                    small_rgb[index] = small
                    scene_rows.append(
                        np.concatenate([np.full((len(inst_rows), 1), index), inst_rows], 1)
                    )
                for m in (full_rgb, full_inst, small_rgb):
                    m.flush()
                np.save(done_dir / f"{k:06d}.npy", np.concatenate(scene_rows, 0))
                bar.update(1)
    finally:
        if pool:
            pool.close()
            pool.join()
    rows = [np.load(done_dir / f"{k:06d}.npy") for k in range(spec.n_scenes)]
    np.save(folder / "instances.npy", np.concatenate(rows, 0) if rows else np.zeros((0, 11)))
    meta = {
        "n_views": n,
        "small_size": [sw, sh],
        "spec": dataclasses.asdict(spec),
        "catalog": str(catalog_dir),
        "instance_columns": list(INSTANCE_COLUMNS),
    }
    (folder / "meta.json").write_text(json.dumps(meta, indent=2) + "\n")
    return open_training_set(folder)
