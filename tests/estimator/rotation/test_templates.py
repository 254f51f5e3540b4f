"""Template banks: in-plane turns as image rotations equal rendering the turned camera; banks
built in parallel equal banks built one by one."""

import numpy as np
import pytest

from posefuse.estimator.rotation.render import Renderer
from posefuse.estimator.rotation.templates import (
    TEMPLATE_MATERIAL,
    TemplateConfig,
    _render_template_view,
    build_template_bank,
    build_template_banks,
    icosphere_directions,
    look_at_rotation,
)


@pytest.mark.parametrize("inplane_deg", [10.0, 130.0, 250.0])
def test_an_image_rotation_is_the_turned_camera(robi_catalog, inplane_deg):
    import cv2

    model = robi_catalog[1]
    config = TemplateConfig()
    camera = config.camera()
    z_r = config.canonical_depth(model.diameter)
    renderer = Renderer([model.mesh], materials=[TEMPLATE_MATERIAL])
    direction = icosphere_directions(config.subdivisions)[11]
    _, mask = _render_template_view(renderer, camera, direction, z_r)
    a = np.deg2rad(inplane_deg)
    Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])
    T_cam_obj = np.eye(4)
    T_cam_obj[:3, :3] = Rz @ look_at_rotation(direction)
    T_cam_obj[2, 3] = z_r
    direct = renderer.render(camera, np.linalg.inv(T_cam_obj), shadows=False).instance >= 0
    M = cv2.getRotationMatrix2D((camera.K[0, 2], camera.K[1, 2]), -inplane_deg, 1.0)
    turned = cv2.warpAffine(mask, M, (camera.width, camera.height), flags=cv2.INTER_NEAREST) > 0
    iou = (direct & turned).sum() / (direct | turned).sum()
    assert iou > 0.93  # only the silhouette's boundary pixels differ


def test_parallel_banks_equal_sequential_ones(robi_catalog, tmp_path):
    models = [robi_catalog[k] for k in sorted(robi_catalog)[:3]]  # 3 parts on 2 workers
    parallel = build_template_banks(models, cache_dir=tmp_path / "p", workers=2)
    for model in models:
        one = build_template_bank(model, cache_dir=tmp_path / "s", show_progress=False)
        np.testing.assert_array_equal(parallel[model.obj_id].feat_x, one.feat_x)
        np.testing.assert_array_equal(parallel[model.obj_id].feat_label, one.feat_label)
        np.testing.assert_allclose(parallel[model.obj_id].R_cam_obj, one.R_cam_obj)
    seen = []
    build_template_banks(models, cache_dir=tmp_path / "p", progress=lambda *a: seen.append(a))
    assert [name for name, _, cached in seen if cached] == [m.name for m in models]
