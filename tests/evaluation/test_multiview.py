"""BOP's single-image scenes made multi-view: rotations stored orthonormal to 1e-2 load with one
warning per file, an anchor object stands for the world, and objects that moved are refused."""

import json
import shutil

import numpy as np
import pytest
from conftest import extra_shared
from scipy.spatial.transform import Rotation

from posefuse.estimator.core.errors import DatasetError, DatasetWarning
from posefuse.estimator.core.objects import load_catalog
from posefuse.evaluation.dataset import load_dataset
from posefuse.evaluation.multiview import MultiviewGroup, multiview_scene, write_multiview_scene


def _rot(seed: int, jitter: float = 0.0) -> np.ndarray:
    R = Rotation.random(random_state=seed).as_matrix()
    return R + jitter * np.random.default_rng(seed).standard_normal((3, 3))


def _dataset(root, catalog_root, views: dict, K=(500.0, 0, 320, 0, 500.0, 240, 0, 0, 1)):
    """A BOP scene of single images: views {im_id: [(obj_id, R, t_mm)]}, no camera poses."""
    scene = root / "test" / "000002"
    scene.mkdir(parents=True)
    (root / "camera.json").write_text(json.dumps({"width": 640, "height": 480}))
    cam = {str(i): {"cam_K": list(K), "depth_scale": 1.0} for i in views}
    gt = {
        str(i): [
            {"cam_R_m2c": np.ravel(R).tolist(), "cam_t_m2c": list(t), "obj_id": o}
            for o, R, t in objs
        ]
        for i, objs in views.items()
    }
    (scene / "scene_camera.json").write_text(json.dumps(cam))
    (scene / "scene_gt.json").write_text(json.dumps(gt))
    return load_dataset(root, catalog=catalog_root)


def _pose(R, t_mm):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, np.asarray(t_mm) / 1000.0
    return T


def _scene_of_two_objects(jitter: float, moved_mm: float = 0.0):
    """Object 1 (the anchor) and 2 at rest relative to each other, seen from three cameras."""
    T_world_2 = _pose(_rot(7), [60.0, -20.0, 10.0])
    views = {}
    for im_id, seed in ((3, 11), (5, 12), (9, 13)):
        T_cam_world = _pose(_rot(seed), [10.0 * seed, 5.0, 900.0])
        T_cam_2 = T_cam_world @ T_world_2
        if im_id == 9:
            T_cam_2[:3, 3] += T_cam_world[:3, :3] @ [moved_mm / 1000.0, 0, 0]
        R1 = T_cam_world[:3, :3] + jitter * np.random.default_rng(seed).standard_normal((3, 3))
        views[im_id] = [
            (1, R1, 1000.0 * T_cam_world[:3, 3]),
            (2, T_cam_2[:3, :3], 1000.0 * T_cam_2[:3, 3]),
        ]
    return views, T_world_2


def test_rotations_orthonormal_to_1e2_are_projected_with_one_warning_per_file(
    tmp_path, robi_catalog
):
    views, _ = _scene_of_two_objects(jitter=1e-3)
    data = _dataset(tmp_path / "d", robi_catalog, views)
    scene = data.scene(2)
    with pytest.warns(DatasetWarning, match="scene_gt.json: 3 rotations .* nearest rotation"):
        gts = scene.ground_truth(3)
    R = gts[0].T_cam_obj[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) > 0
    # the projection is the nearest rotation: within the jitter of what was stored
    assert np.abs(R - views[3][0][1]).max() < 1e-2
    with pytest.raises(DatasetError, match="image 3: missing 'cam_R_w2c'"):
        scene.view(3)  # a single image has no camera pose


def test_a_rotation_further_off_is_still_refused_naming_the_image(tmp_path, robi_catalog):
    views, _ = _scene_of_two_objects(jitter=0.0)
    views[5][1] = (2, views[5][1][1] * 1.05, views[5][1][2])  # 5% off: no rotation
    scene = _dataset(tmp_path / "d", robi_catalog, views).scene(2)
    with pytest.raises(DatasetError, match=r"image 5 instance 1: rotation is not a rotation"):
        scene.ground_truth(5)


def test_an_anchor_object_makes_the_images_one_multiview_scene(tmp_path, robi_catalog):
    views, T_world_2 = _scene_of_two_objects(jitter=0.0)
    scene = _dataset(tmp_path / "d", robi_catalog, views).scene(2)
    built = multiview_scene(scene, MultiviewGroup((3, 5, 9), (1, 2), anchor=1))
    assert max(built.spread[2]) < 1e-6
    out = tmp_path / "mv"
    write_multiview_scene(built, out / "test" / "000000")
    shutil.copy(tmp_path / "d" / "camera.json", out / "camera.json")
    mv = load_dataset(out, catalog=robi_catalog).scene(0)
    for im_id in (3, 5, 9):
        view = mv.view(im_id)
        T_world_2_seen = view.T_world_cam @ view.gts[1].T_cam_obj
        np.testing.assert_allclose(T_world_2_seen, T_world_2, atol=1e-9)
        np.testing.assert_allclose(view.T_world_cam @ view.gts[0].T_cam_obj, np.eye(4), atol=1e-9)


def test_an_object_that_moved_is_refused(tmp_path, robi_catalog):
    views, _ = _scene_of_two_objects(jitter=0.0, moved_mm=10.0)
    scene = _dataset(tmp_path / "d", robi_catalog, views).scene(2)
    with pytest.raises(DatasetError, match="object 2 moved 6.7 mm"):
        multiview_scene(scene, MultiviewGroup((3, 5, 9), (1, 2), anchor=1))
    with pytest.raises(ValueError, match="anchor 4 is not one of"):
        MultiviewGroup((3,), (1, 2), anchor=4)


def test_extra_lmo_own_files_load_with_a_warning_and_cut_into_the_shared_scenes(tmp_path):
    """LM-O's own files (rotations as stored, orthonormal to 9.4e-3) load with one warning, and
    cut the way ../shared/realdata/README.md describes they give its multi-view scenes."""
    raw = extra_shared("realdata", "lmo_raw", "test", "000002")
    shared = extra_shared("realdata", "lmo_mv")
    root = tmp_path / "lmo"
    shutil.copytree(raw, root / "test" / "000002")
    (root / "camera.json").write_text(json.dumps({"width": 640, "height": 480}))
    data = load_dataset(root, catalog=load_catalog(shared / "models"))
    groups = json.loads((shared / "synth.json").read_text())["groups"]
    with pytest.warns(DatasetWarning, match=r"scene_gt.json: \d+ rotations .* 9.4e-03"):
        data.scene(2).ground_truth(27)
    for scene_id, group in groups.items():
        built = multiview_scene(
            data.scene(2),
            MultiviewGroup(tuple(group["frames"]), tuple(group["objects"]), group["anchor"]),
        )
        target = f"{int(scene_id):06d}"
        write_multiview_scene(built, tmp_path / "mv" / "test" / target)
        expected = load_dataset(shared).scene(int(scene_id))
        for im_id in group["frames"]:
            ours = json.loads((tmp_path / "mv" / "test" / target / "scene_camera.json").read_text())
            view = expected.view(im_id)
            T_cam_world = np.linalg.inv(view.T_world_cam)
            np.testing.assert_allclose(
                np.reshape(ours[str(im_id)]["cam_R_w2c"], (3, 3)), T_cam_world[:3, :3], atol=1e-6
            )
            np.testing.assert_allclose(
                ours[str(im_id)]["cam_t_w2c"], 1000 * T_cam_world[:3, 3], atol=1e-6
            )
        assert all(mm <= 3.0 and deg <= 1.0 for mm, deg in built.spread.values())
