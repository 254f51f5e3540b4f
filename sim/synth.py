"""``posefuse synth``: render multi-view bin scenes of a catalog into a BOP dataset."""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from posefuse.estimator.core.bin_region import BinRegion
from posefuse.estimator.core.camera import Camera
from posefuse.estimator.core.geometry import invert
from posefuse.estimator.core.objects import Catalog
from posefuse.estimator.rotation.render import Renderer
from posefuse.sim.bop_writer import SceneWriter, write_dataset_header
from posefuse.sim.scenes import REALSENSE_1280x720, Scene, SceneSpec, make_scene
from posefuse.sim.sensor import SensorModel, apply_depth, apply_rgb

BIN_ID = 10_000  # instance id of the bin in renders (parts are 0..n-1)


@dataclass(frozen=True)
class SynthConfig:
    n_scenes: int = 2
    seed: int = 0
    split: str = "test"
    first_scene_id: int = 0
    camera: Camera = REALSENSE_1280x720
    scene: SceneSpec = SceneSpec()
    sensor: SensorModel = SensorModel()
    obj_ids: tuple[int, ...] | None = None
    profile: str = "mixed"  # the name of ``scene``'s profile, recorded in synth.json


def scene_seed(seed: int, scene_id: int) -> int:
    """The seed of one scene: independent of how many scenes are generated."""
    return int(np.random.SeedSequence([seed, scene_id]).generate_state(1)[0])


def render_scene_views(
    catalog: Catalog,
    scene: Scene,
    writer: SceneWriter,
    sensor: SensorModel,
    seed: int,
    progress: Callable[[], None] | None = None,
) -> None:
    """Render every view of ``scene`` and hand it to ``writer``."""
    materials = [_part_material(catalog, inst.obj_id) for inst in scene.instances]
    meshes = [catalog[inst.obj_id].mesh for inst in scene.instances] + [scene.bin_mesh]
    poses = [inst.T_world_obj for inst in scene.instances] + [np.eye(4)]
    ids = list(range(len(scene.instances))) + [BIN_ID]
    renderer = Renderer(meshes, poses, ids, materials + [scene.bin_material])
    rng = np.random.default_rng(seed)
    for im_id, T_world_cam in enumerate(scene.T_world_cams):
        res = renderer.render(scene.camera, T_world_cam, scene.lighting)
        metal = (res.instance >= 0) & (res.instance != BIN_ID)
        rgb = apply_rgb(res.image, sensor, rng)
        depth = apply_depth(res.depth, res.image, res.normals, metal, sensor, rng)
        T_cam_world = invert(T_world_cam)
        gts, visib, full = [], [], []
        for k, inst in enumerate(scene.instances):
            gts.append((inst.obj_id, T_cam_world @ inst.T_world_obj))
            visib.append(res.instance == k)
            full.append(renderer.render_mask(scene.camera, T_world_cam, k))
        writer.add_view(im_id, scene.camera, T_cam_world, rgb, depth, gts, visib, full)
        if progress:
            progress()


def _part_material(catalog: Catalog, obj_id: int):
    from posefuse.sim.materials import part_material

    return part_material(catalog[obj_id])


def generate_dataset(
    catalog: Catalog,
    out: str | Path,
    config: SynthConfig,
    show_progress: bool = True,
    workers: int = 1,
) -> Path:
    """Write ``config.n_scenes`` scenes of ``config.scene.n_views`` views to ``out`` (BOP).

    ``workers`` > 1 renders scenes in that many processes, one scene each; every scene is a
    function of its own seed, so the files are the same as one process writes."""
    if workers < 1:
        raise ValueError(f"workers must be at least 1, got {workers}")
    out = Path(out)
    write_dataset_header(out, config.camera, catalog)
    write_synth_json(out, config)
    scene_ids = [config.first_scene_id + k for k in range(config.n_scenes)]
    total = config.n_scenes * config.scene.n_views
    with tqdm(total=total, desc="synth", unit="view", disable=not show_progress) as bar:
        if workers == 1 or len(scene_ids) == 1:
            for scene_id in scene_ids:
                render_dataset_scene(catalog, out, config, scene_id, bar.update)
            return out
        from concurrent.futures import ProcessPoolExecutor
        from multiprocessing import get_context

        # spawned, not forked: the caller may hold onnxruntime's or torch's threads
        with ProcessPoolExecutor(min(workers, len(scene_ids)), get_context("spawn")) as pool:
            jobs = [pool.submit(render_dataset_scene, catalog, out, config, s) for s in scene_ids]
            for job in jobs:
                job.result()
                bar.update(config.scene.n_views)
    return out


def write_synth_json(out: Path, config: SynthConfig) -> None:
    """``synth.json``: how a dataset was rendered (its profile, seed, scenes and bin)."""
    spec = config.scene
    (Path(out) / "synth.json").write_text(
        json.dumps(
            {
                "profile": config.profile,
                "seed": config.seed,
                "first_scene_id": config.first_scene_id,
                "n_scenes": config.n_scenes,
                "n_views": spec.n_views,
                "instances": list(spec.n_instances),
                "parts_per_scene": list(spec.parts_per_scene),
                "view_pattern": spec.view_pattern,
                "obj_ids": list(config.obj_ids) if config.obj_ids else None,
                # the bin the parts were dropped into, as a cell that knows its bin would
                # give it (run-dataset --bin dataset hands it to the estimator)
                "bin": BinRegion(spec.bin.size, spec.bin.wall_height).to_json(),
            },
            indent=1,
        )
        + "\n"
    )


def render_dataset_scene(
    catalog: Catalog,
    out: Path,
    config: SynthConfig,
    scene_id: int,
    progress: Callable[[], None] | None = None,
) -> None:
    """Render and write one scene of a dataset (``generate_dataset``): its layout and its views
    from ``scene_seed(config.seed, scene_id)`` alone."""
    seed = scene_seed(config.seed, scene_id)
    obj_ids = list(config.obj_ids) if config.obj_ids else None
    scene = make_scene(catalog, config.scene, seed, config.camera, obj_ids)
    writer = SceneWriter(out / config.split, scene_id)
    render_scene_views(catalog, scene, writer, config.sensor, seed + 1, progress)
    writer.close()
