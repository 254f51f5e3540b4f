"""A BOP dataset's rendered twin: the same cameras, the same object poses, posefuse's renderer.

What separates a real photograph from posefuse's own renders is then the only difference
between a dataset and its twin: the estimator's accuracy on both, side by side
(``bench.real``), says what a real camera costs each step.

Each scene's objects are placed where its first view's ground truth puts them in the world
(``T_world_cam @ T_cam_obj``: a multi-view scene's objects are at rest); nothing else is
rendered (no table, no clutter). Parts are in ``sim.materials.part_material`` (plastic of a
mesh's own colour); two lights follow each camera (one from above it, one
beside it), so a world frame whose z is not up still gets lit from the front.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from tqdm import tqdm

from posefuse.estimator.rotation.render import (
    DirectionalLight,
    Lighting,
    Renderer,
    make_environment,
)
from posefuse.sim.bop_writer import SceneWriter, write_dataset_header
from posefuse.sim.materials import part_material
from posefuse.sim.sensor import SensorModel, apply_rgb

# camera frame: x right, y down, z forward; directions point towards the light
_LIGHTS_CAM = ((0.25, -0.7, -0.65, 1.0), (-0.8, -0.1, -0.6, 0.45))


def camera_lighting(T_world_cam: np.ndarray, environment: np.ndarray) -> Lighting:
    """Two lights fixed to the camera (``_LIGHTS_CAM``), expressed in the world frame."""
    lights = []
    for x, y, z, strength in _LIGHTS_CAM:
        d = T_world_cam[:3, :3] @ (np.array([x, y, z]) / np.linalg.norm([x, y, z]))
        lights.append(DirectionalLight(tuple(d), (strength,) * 3))
    return Lighting(lights=tuple(lights), ambient=(0.1, 0.1, 0.1), environment=environment)


def render_twin(
    dataset, out: str | Path, seed: int = 0, sensor: SensorModel | None = None, progress=True
) -> Path:
    """Render the twin of every scene of ``dataset`` (a BopDataset) into ``out`` (BOP, same
    scene and image ids, same split). Returns ``out``."""
    out = Path(out)
    sensor = sensor or SensorModel()
    first = dataset.scene(dataset.scene_ids[0])
    write_dataset_header(out, first.intrinsics(first.im_ids[0]), dataset.catalog)
    environment = make_environment(seed)
    total = sum(len(dataset.scene(s).im_ids) for s in dataset.scene_ids)
    with tqdm(total=total, desc="twin", unit="view", disable=not progress) as bar:
        for scene_id in dataset.scene_ids:
            scene = dataset.scene(scene_id)
            anchor_view = scene.view(scene.im_ids[0])
            instances = [(g.obj_id, anchor_view.T_world_cam @ g.T_cam_obj) for g in anchor_view.gts]
            models = [dataset.catalog[obj_id] for obj_id, _ in instances]
            renderer = Renderer(
                [m.mesh for m in models],
                [T for _, T in instances],
                materials=[part_material(m) for m in models],
            )
            rng = np.random.default_rng([seed, scene_id])
            writer = SceneWriter(out / dataset.split, scene_id)
            for im_id in scene.im_ids:
                view = scene.view(im_id)
                lighting = camera_lighting(view.T_world_cam, environment)
                res = renderer.render(view.camera, view.T_world_cam, lighting)
                T_cam_world = view.T_cam_world
                gts = [(obj_id, T_cam_world @ T) for obj_id, T in instances]
                visib = [res.instance == k for k in range(len(instances))]
                full = [
                    renderer.render_mask(view.camera, view.T_world_cam, k)
                    for k in range(len(instances))
                ]
                rgb = apply_rgb(res.image, sensor, rng)
                writer.add_view(im_id, view.camera, T_cam_world, rgb, res.depth, gts, visib, full)
                bar.update(1)
            writer.close()
    return out
