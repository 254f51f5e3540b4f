"""A dataset's rendered twin: the same cameras and poses, every instance rendered where the
ground truth puts it."""

import numpy as np

from posefuse.evaluation.dataset import load_dataset
from posefuse.sim.materials import part_material, plastic_of
from posefuse.sim.twin import render_twin


def test_the_twin_has_the_same_cameras_poses_and_visible_parts(small_dataset_root, tmp_path):
    source = load_dataset(small_dataset_root)
    twin = load_dataset(render_twin(source, tmp_path / "twin", progress=False))
    assert twin.scene_ids == source.scene_ids
    for scene_id in source.scene_ids:
        a, b = source.scene(scene_id), twin.scene(scene_id)
        assert a.im_ids == b.im_ids
        for im_id in a.im_ids:
            va, vb = a.view(im_id), b.view(im_id)
            np.testing.assert_allclose(vb.T_world_cam, va.T_world_cam, atol=1e-9)
            np.testing.assert_allclose(vb.camera.K, va.camera.K, atol=1e-6)
            assert [g.obj_id for g in vb.gts] == [g.obj_id for g in va.gts]
            for ga, gb in zip(va.gts, vb.gts, strict=True):
                np.testing.assert_allclose(gb.T_cam_obj, ga.T_cam_obj, atol=1e-6)
                if gb.visib_fract > 0.5:  # seen in the twin: its silhouette is there
                    assert b.load_mask_visib(im_id, gb.gt_idx).sum() == gb.px_count_visib > 0
            assert b.load_rgb(im_id).std() > 5  # something was rendered


def test_a_mesh_with_vertex_colours_is_plastic_of_its_colour(robi_catalog):
    import copy

    import trimesh

    model = copy.copy(robi_catalog[next(iter(robi_catalog))])
    assert plastic_of(model).reflect > 0.3  # no colours: metal
    mesh = trimesh.creation.box((0.05, 0.05, 0.05))
    mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=[255, 255, 0, 255])
    object.__setattr__(model, "mesh", mesh)
    plastic = plastic_of(model)
    np.testing.assert_allclose(plastic.color, (1.0, 1.0, 0.0), atol=1e-6)
    assert plastic.reflect < 0.1 and plastic.diffuse > 0.5
    assert part_material(model) == plastic  # what every render of parts uses
