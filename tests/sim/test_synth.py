"""Bin scenes are physically plausible; synth writes BOP files deterministically."""

import hashlib
import json

import cv2
import numpy as np
import pytest
import trimesh

from posefuse.estimator.core.camera import Camera
from posefuse.estimator.core.objects import Catalog, make_model
from posefuse.sim.scenes import SceneSpec, _Caster, _PilePieces, bin_mesh, make_scene
from posefuse.sim.synth import SynthConfig, generate_dataset

SMALL_CAMERA = Camera(np.array([[231.0, 0, 160.0], [0, 231.0, 90.0], [0, 0, 1]]), 320, 180)


@pytest.fixture(scope="module")
def catalog():
    box = trimesh.creation.box([0.05, 0.03, 0.02])
    cyl = trimesh.creation.cylinder(radius=0.012, height=0.06, sections=32)
    return Catalog(
        [make_model(1, "box", box, detect=False), make_model(2, "rod", cyl, detect=False)]
    )


def _posed(catalog, inst):
    mesh = catalog[inst.obj_id].mesh.copy()
    mesh.apply_transform(inst.T_world_obj)
    return mesh


def test_parts_rest_in_the_bin_without_interpenetrating(catalog):
    spec = SceneSpec(n_instances=(10, 10))
    scene = make_scene(catalog, spec, seed=7)
    assert len(scene.instances) == 10
    meshes = [_posed(catalog, inst) for inst in scene.instances]
    sx, sy = spec.bin.size
    for k, mesh in enumerate(meshes):
        lo, hi = mesh.bounds
        assert lo[2] > -1e-4, "a part sinks into the floor"
        assert np.all(np.abs(lo[:2]) <= [sx / 2, sy / 2]) and np.all(
            np.abs(hi[:2]) <= [sx / 2, sy / 2]
        )
        on_floor = lo[2] < 1e-3
        others = [m for j, m in enumerate(meshes) if j != k]
        if not on_floor:
            # it rests on another part: some other part comes within 1.5 mm of its underside
            pts, _ = trimesh.sample.sample_surface(mesh, 3000, seed=k)
            gaps = [np.min(np.abs(trimesh.proximity.signed_distance(o, pts))) for o in others]
            assert min(gaps) < 1.5e-3, f"part {k} floats {min(gaps) * 1000:.1f} mm above the pile"
        pts, _ = trimesh.sample.sample_surface(mesh, 2000, seed=100 + k)
        for o in others:
            depth = trimesh.proximity.signed_distance(o, pts)  # > 0 inside o
            assert depth.max() < 1.0e-3, (
                f"part {k} penetrates another by {depth.max() * 1000:.2f} mm"
            )


def test_the_piles_pieces_meet_a_ray_where_the_whole_pile_does(catalog):
    """A part falls onto the bin and the parts placed, each with its own intersector, asked
    only where its footprint overlaps the falling part's: the distance is the one the whole
    pile, as one mesh, gives (to float precision), and no closer piece is left out."""
    spec = SceneSpec(n_instances=(8, 8))
    scene = make_scene(catalog, spec, seed=11)
    parts = [_posed(catalog, inst) for inst in scene.instances]
    floor = bin_mesh(spec.bin)
    pieces = _PilePieces(floor)
    for part in parts:
        pieces.add(part)
    whole = _Caster(trimesh.util.concatenate([floor, *parts]))
    rng = np.random.default_rng(0)
    down = np.array([0.0, 0.0, -1.0])
    met_a_part = 0
    for _ in range(40):
        centre = rng.uniform(-0.08, 0.08, 2)
        half = rng.uniform(0.005, 0.04, 2)
        lo, hi = centre - half, centre + half
        origins = np.column_stack([rng.uniform(lo, hi, (200, 2)), np.full(200, 0.5)])
        expected = whole.distance(origins, down)
        assert pieces.distance_down(origins) == pytest.approx(expected, abs=1e-9)
        met_a_part += expected < 0.5 - 1e-3  # above the bin's floor: a part was nearest
    assert met_a_part >= 5


def test_views_look_into_the_bin_from_the_hemisphere(catalog):
    spec = SceneSpec(n_views=12)
    scene = make_scene(catalog, spec, seed=3)
    assert scene.T_world_cams.shape == (12, 4, 4)
    for T in scene.T_world_cams:
        eye, axis = T[:3, 3], T[:3, 2]
        target_dist = np.linalg.norm(eye - [0, 0, 0.02])
        assert 0.45 < target_dist < 0.95
        assert axis[2] < -np.cos(np.deg2rad(40))  # looking down
        np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
        # the bin centre projects near the image centre
        p = T[:3, :3].T @ (np.array([0, 0, 0.02]) - eye)
        uv = SMALL_CAMERA.project(p)
        assert abs(uv[0] - 160) < 40 and abs(uv[1] - 90) < 40


def _digest(root):
    h = hashlib.sha256()
    for path in sorted(p for p in root.rglob("*") if p.is_file()):
        h.update(str(path.relative_to(root)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def test_same_seed_same_bytes(tmp_path, catalog):
    config = SynthConfig(
        n_scenes=1, seed=5, camera=SMALL_CAMERA, scene=SceneSpec(n_instances=(4, 6), n_views=2)
    )
    a = generate_dataset(catalog, tmp_path / "a", config, show_progress=False)
    b = generate_dataset(catalog, tmp_path / "b", config, show_progress=False)
    assert _digest(a) == _digest(b)
    c = generate_dataset(
        catalog,
        tmp_path / "c",
        SynthConfig(
            n_scenes=1, seed=6, camera=SMALL_CAMERA, scene=SceneSpec(n_instances=(4, 6), n_views=2)
        ),
        show_progress=False,
    )
    assert _digest(a) != _digest(c)


def test_bop_files_are_consistent(tmp_path, catalog):
    config = SynthConfig(
        n_scenes=1, seed=1, camera=SMALL_CAMERA, scene=SceneSpec(n_instances=(6, 6), n_views=2)
    )
    root = generate_dataset(catalog, tmp_path / "d", config, show_progress=False)
    scene_dir = root / "test" / "000000"
    cams = json.loads((scene_dir / "scene_camera.json").read_text())
    gts = json.loads((scene_dir / "scene_gt.json").read_text())
    infos = json.loads((scene_dir / "scene_gt_info.json").read_text())
    assert sorted(cams) == sorted(gts) == sorted(infos) == ["0", "1"]
    for im in ("0", "1"):
        assert len(gts[im]) == len(infos[im]) == 6
        # instance order is the same in every view: gt k is the same part
        assert [g["obj_id"] for g in gts[im]] == [g["obj_id"] for g in gts["0"]]
        T_cw = np.eye(4)
        T_cw[:3, :3] = np.reshape(cams[im]["cam_R_w2c"], (3, 3))
        T_cw[:3, 3] = cams[im]["cam_t_w2c"]
        for k, info in enumerate(infos[im]):
            assert 0.0 <= info["visib_fract"] <= 1.0
            mask = cv2.imread(str(scene_dir / "mask_visib" / f"{int(im):06d}_{k:06d}.png"), 0)
            assert int((mask > 0).sum()) == info["px_count_visib"]
            assert info["px_count_all"] >= info["px_count_visib"]
        depth = cv2.imread(str(scene_dir / "depth" / f"{int(im):06d}.png"), cv2.IMREAD_UNCHANGED)
        assert depth.dtype == np.uint16 and depth.shape == (180, 320)
        # depth at valid pixels is between 0.3 and 1.2 m (depth_scale 0.1 mm)
        valid = depth[depth > 0] * cams[im]["depth_scale"] / 1000.0
        assert 0.3 < valid.min() and valid.max() < 1.2

    # the same physical part: T_world_obj agrees between the two views
    def world_pose(im, k):
        T_cw = np.eye(4)
        T_cw[:3, :3] = np.reshape(cams[im]["cam_R_w2c"], (3, 3))
        T_cw[:3, 3] = cams[im]["cam_t_w2c"]
        T_co = np.eye(4)
        T_co[:3, :3] = np.reshape(gts[im][k]["cam_R_m2c"], (3, 3))
        T_co[:3, 3] = gts[im][k]["cam_t_m2c"]
        return np.linalg.inv(T_cw) @ T_co

    for k in range(6):
        np.testing.assert_allclose(world_pose("0", k), world_pose("1", k), atol=1e-6)


def test_robi_profile_piles_one_part_type_and_sweeps_over_the_bin(robi_catalog, tmp_path):
    import dataclasses

    from posefuse.cli.main import main
    from posefuse.evaluation.dataset import load_dataset
    from posefuse.sim.scenes import PROFILES

    spec = PROFILES["robi"]
    assert spec.parts_per_scene == (1, 1) and spec.n_instances == (20, 40)
    out = tmp_path / "robi"
    args = ["synth", "--profile", "robi", "--out", str(out), "--scenes", "1", "--views", "4"]
    assert main([*args, "--intrinsics", "realsense-640", "--seed", "5", "--quiet"]) == 0
    ds = load_dataset(out)
    assert ds.profile == "robi"
    views = list(ds.views())
    assert len({g.obj_id for v in views for g in v.gts}) == 1
    assert 20 <= len(views[0].gts) <= 40
    # piled: in every view some parts hide others
    assert all(min(g.visib_fract for g in v.gts) < 0.5 for v in views)
    # a sweep: the camera centres lie near one vertical plane, ordered along it
    centres = np.array([v.T_world_cam[:3, 3] for v in views])
    _, sv, vt = np.linalg.svd(centres[:, :2] - centres[:, :2].mean(axis=0))
    along = (centres[:, :2] - centres[:, :2].mean(axis=0)) @ vt[0]
    assert sv[1] < 0.35 * sv[0]
    assert np.all(np.diff(along) > 0) or np.all(np.diff(along) < 0)
    with pytest.raises(ValueError, match="view_pattern"):
        dataclasses.replace(spec, view_pattern="spiral")


def test_scenes_rendered_in_processes_are_the_same_bytes(tmp_path, catalog):
    config = SynthConfig(
        n_scenes=3, seed=8, camera=SMALL_CAMERA, scene=SceneSpec(n_instances=(3, 4), n_views=2)
    )
    one = generate_dataset(catalog, tmp_path / "one", config, show_progress=False)
    two = generate_dataset(catalog, tmp_path / "two", config, show_progress=False, workers=2)
    assert _digest(one) == _digest(two)
    assert len(list((two / "test").iterdir())) == 3
    with pytest.raises(ValueError, match="workers must be at least 1"):
        generate_dataset(catalog, tmp_path / "x", config, workers=0)
