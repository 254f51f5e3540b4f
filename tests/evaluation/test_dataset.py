"""Reading BOP datasets: poses in metres, consistent frames, clear errors naming the file."""

import json
import shutil

import numpy as np
import pytest

from posefuse.estimator.core.errors import DatasetError
from posefuse.evaluation.dataset import load_dataset


def test_views_and_poses(small_dataset_root):
    ds = load_dataset(small_dataset_root)
    assert ds.scene_ids == (0, 1)
    scene = ds.scene(0)
    assert scene.im_ids == (0, 1, 2)
    views = list(scene.views())
    for view in views:
        assert view.camera.width == 640 and view.camera.height == 360
        np.testing.assert_allclose(view.T_world_cam @ view.T_cam_world, np.eye(4), atol=1e-9)
        assert all(0 <= g.visib_fract <= 1 for g in view.gts)
    # every annotated instance has one pose in the world, whichever view it is read from
    for k in range(len(views[0].gts)):
        poses = [v.T_world_cam @ v.gts[k].T_cam_obj for v in views]
        for T in poses[1:]:
            np.testing.assert_allclose(T, poses[0], atol=1e-6)
    # translations are metres: the bin is 0.5-0.9 m away
    assert all(0.3 < np.linalg.norm(g.T_cam_obj[:3, 3]) < 1.2 for g in views[0].gts)
    rgb = scene.load_rgb(0)
    assert rgb.shape == (360, 640, 3) and rgb.dtype == np.uint8
    depth = scene.load_depth(0)
    assert 0.3 < np.median(depth[depth > 0]) < 1.2
    mask = scene.load_mask_visib(0, 0)
    assert mask.dtype == bool and mask.sum() == views[0].gts[0].px_count_visib


def test_missing_and_malformed_files_are_named(small_dataset_root, tmp_path):
    with pytest.raises(DatasetError, match="dataset folder not found"):
        load_dataset(tmp_path / "nope")
    with pytest.raises(DatasetError, match="split 'val' not found"):
        load_dataset(small_dataset_root, split="val")
    copy = tmp_path / "copy"
    shutil.copytree(small_dataset_root, copy)
    path = copy / "test" / "000000" / "scene_camera.json"
    data = json.loads(path.read_text())
    del data["1"]["cam_R_w2c"]
    data["2"]["cam_R_w2c"] = [2, 0, 0, 0, 1, 0, 0, 0, 1]
    path.write_text(json.dumps(data))
    scene = load_dataset(copy).scene(0)
    with pytest.raises(DatasetError, match=r"scene_camera.json: image 1: missing 'cam_R_w2c'"):
        scene.view(1)
    with pytest.raises(DatasetError, match="image 2: rotation is not a rotation matrix"):
        scene.view(2)
    (copy / "test" / "000001" / "scene_gt.json").write_text("{not json")
    with pytest.raises(DatasetError, match=r"scene_gt.json: not valid JSON"):
        load_dataset(copy).scene(1).view(0)
    with pytest.raises(DatasetError, match="no scene 7"):
        load_dataset(copy).scene(7)


def test_the_bin_synth_rendered_is_recorded_and_read(small_dataset_root, tmp_path):
    """A synth dataset records its bin (the renderer's own: floor at z = 0, centred); one
    without it (made elsewhere, or before) has none; a malformed one is named."""
    from posefuse.sim.scenes import SceneSpec

    region = load_dataset(small_dataset_root).bin
    spec = SceneSpec().bin
    assert region is not None and region.size == spec.size
    assert region.wall_height == spec.wall_height
    np.testing.assert_array_equal(region.T_world_bin, np.eye(4))
    # every true part's centre lies in it
    for view in load_dataset(small_dataset_root).views():
        centres = np.array([(view.T_world_cam @ g.T_cam_obj)[:3, 3] for g in view.gts])
        assert np.all(region.distance_outside(centres) == 0.0)
    copy = tmp_path / "copy"
    shutil.copytree(small_dataset_root, copy)
    record = json.loads((copy / "synth.json").read_text())
    record["bin"] = {"size": [0.4, -1.0], "wall_height": 0.08}
    (copy / "synth.json").write_text(json.dumps(record))
    with pytest.raises(DatasetError, match=r"synth.json: 'bin': bin region"):
        _ = load_dataset(copy).bin
    del record["bin"]
    (copy / "synth.json").write_text(json.dumps(record))
    assert load_dataset(copy).bin is None
    (copy / "synth.json").unlink()
    assert load_dataset(copy).bin is None
