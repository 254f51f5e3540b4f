"""Multi-view detection sequences straight from scene geometry, without rendering.

For measuring the back end quickly on many scenes: the bin scenes of :mod:`sim.scenes`, and per
view the oracle's detections (true projected model origin + Gaussian noise, the box of the
projected model points, seeded drops and false positives). Occlusion is ignored: every part
whose center projects into the image is detectable. For detections with occlusion use
:class:`evaluation.oracle.OracleFrontend` on a rendered dataset.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from posefuse.estimator.core.camera import Camera
from posefuse.estimator.core.objects import Catalog
from posefuse.estimator.frontend.detection import Detection
from posefuse.estimator.tracker import Frame
from posefuse.sim.scenes import REALSENSE_1280x720, SceneSpec, make_scene


@dataclass(frozen=True, eq=False)
class SequenceView:
    """One view: the frame, its detections, and per detection the instance index (-1 false)."""

    frame: Frame
    detections: list[Detection]
    instance_of: list[int]


@dataclass(frozen=True, eq=False)
class Sequence:
    """A scene's instances (obj_id, T_world_obj (4, 4)) and its views in order."""

    instances: tuple[tuple[int, np.ndarray], ...]
    views: tuple[SequenceView, ...]


def make_sequence(
    catalog: Catalog,
    seed: int,
    spec: SceneSpec | None = None,
    camera: Camera = REALSENSE_1280x720,
    center_sigma_px: float = 2.0,
    drop_rate: float = 0.1,
    false_positive_rate: float = 0.05,
) -> Sequence:
    """A bin scene and its oracle detections in every view, all from ``seed``."""
    spec = spec or SceneSpec()
    scene = make_scene(catalog, spec, seed=seed, camera=camera)
    rng = np.random.default_rng([seed, 1])
    cov = np.eye(2) * center_sigma_px**2
    views = []
    for k, T_world_cam in enumerate(scene.T_world_cams):
        T_cam_world = np.linalg.inv(T_world_cam)
        dets, owners, sizes = [], [], []
        for i, inst in enumerate(scene.instances):
            noise = rng.normal(0.0, center_sigma_px, 2)
            dropped = rng.random() < drop_rate
            T_cam_obj = T_cam_world @ inst.T_world_obj
            if dropped or T_cam_obj[2, 3] <= 0:
                continue
            uv = camera.project(T_cam_obj[:3, 3])
            if not camera.contains(uv[None])[0]:
                continue
            pts = catalog[inst.obj_id].points @ T_cam_obj[:3, :3].T + T_cam_obj[:3, 3]
            q = camera.project(pts)
            lo = np.clip(q.min(0), 0, [camera.width - 1, camera.height - 1])
            hi = np.clip(q.max(0), 0, [camera.width - 1, camera.height - 1])
            box = np.array([lo[0], lo[1], max(hi[0] - lo[0], 1.0), max(hi[1] - lo[1], 1.0)])
            sizes.append(box[2:])
            dets.append(Detection(inst.obj_id, box, uv + noise, cov, None, 1.0))
            owners.append(i)
        n_false = rng.binomial(len(dets), false_positive_rate) if dets else 0
        for _ in range(n_false):
            wh = sizes[rng.integers(len(sizes))]
            uv = rng.uniform(wh, [camera.width - wh[0], camera.height - wh[1]])
            box = np.array([uv[0] - wh[0] / 2, uv[1] - wh[1] / 2, wh[0], wh[1]])
            obj_id = int(scene.instances[rng.integers(len(scene.instances))].obj_id)
            dets.append(Detection(obj_id, box, uv, cov, None, 0.5))
            owners.append(-1)
        frame = Frame(stamp_ns=(k + 1) * 100_000_000, camera=camera, T_world_cam=T_world_cam)
        views.append(SequenceView(frame, dets, owners))
    instances = tuple((inst.obj_id, inst.T_world_obj) for inst in scene.instances)
    return Sequence(instances, tuple(views))
