"""The ray-cast renderer against analytic geometry."""

import numpy as np
import trimesh

from posefuse.estimator.core.camera import Camera
from posefuse.estimator.core.geometry import invert
from posefuse.estimator.rotation.render import BACKGROUND, MATTE, Renderer

CAMERA = Camera(np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]]), 320, 240)


def _cam_looking_down(height):
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])  # z forward = world -z
    T[:3, 3] = [0, 0, height]
    return T


def test_depth_of_a_plane_is_exact():
    plane = trimesh.creation.box([2.0, 2.0, 0.01])
    plane.apply_translation([0, 0, -0.005])  # top at z = 0
    res = Renderer([plane], materials=[MATTE]).render(CAMERA, _cam_looking_down(0.8), shadows=False)
    assert np.all(res.instance == 0)
    np.testing.assert_allclose(res.depth, 0.8, atol=1e-5)
    np.testing.assert_allclose(res.normals[..., 2], -1.0, atol=1e-5)  # facing the camera


def test_sphere_silhouette_depth_and_normals():
    r, z = 0.05, 0.6
    sphere = trimesh.creation.icosphere(5, r)
    T_world_cam = np.eye(4)
    T_world_cam[:3, 3] = [0, 0, -z]  # camera at -z looking along +z at the origin
    res = Renderer([sphere]).render(CAMERA, T_world_cam, shadows=False)
    mask = res.instance == 0
    # apparent radius of a sphere: f * r / sqrt(z^2 - r^2)
    expected_area = np.pi * (300.0 * r / np.sqrt(z**2 - r**2)) ** 2
    assert abs(mask.sum() - expected_area) / expected_area < 0.02
    assert abs(res.depth[120, 160] - (z - r)) < 2e-4
    n_centre = res.normals[120, 160]
    np.testing.assert_allclose(n_centre, [0, 0, -1], atol=0.03)  # pixel centre is 0.5 px off
    assert np.all(res.instance[~mask] == BACKGROUND)
    assert np.all(res.depth[~mask] == 0)
    assert res.image.dtype == np.uint8 and res.image.shape == (240, 320, 3)


def test_occlusion_and_unoccluded_mask():
    front = trimesh.creation.box([0.04, 0.04, 0.01])
    back = trimesh.creation.box([0.1, 0.1, 0.01])
    poses = [np.eye(4), np.eye(4)]
    poses[0][:3, 3] = [0, 0, 0.1]  # nearer to a camera above
    renderer = Renderer([front, back], poses, ids=[7, 3])
    T_world_cam = _cam_looking_down(0.7)
    res = renderer.render(CAMERA, T_world_cam, shadows=True)
    visible_back = res.instance == 3
    full_back = renderer.render_mask(CAMERA, T_world_cam, 1)
    full_front = renderer.render_mask(CAMERA, T_world_cam, 0)
    assert np.array_equal(full_front, res.instance == 7)
    assert np.all(full_back >= visible_back)
    np.testing.assert_array_equal(full_back & ~visible_back, full_front & full_back)


def test_projected_origin_is_the_silhouette_centre():
    sphere = trimesh.creation.icosphere(4, 0.03)
    T_world_obj = np.eye(4)
    T_world_obj[:3, 3] = [0.05, -0.03, 0.0]
    T_world_cam = np.eye(4)
    T_world_cam[:3, 3] = [0, 0, -0.5]
    res = Renderer([sphere], [T_world_obj]).render(CAMERA, T_world_cam, shadows=False)
    ys, xs = np.nonzero(res.instance == 0)
    uv = CAMERA.project((invert(T_world_cam) @ T_world_obj)[:3, 3])
    # a sphere's silhouette centre is its projected centre up to the perspective bulge
    assert np.hypot(xs.mean() - uv[0], ys.mean() - uv[1]) < 0.5
