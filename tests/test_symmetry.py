"""Symmetry detection on primitives with known groups, and BOP-style discretisation."""

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from estimator.objects import mesh_diameter
from estimator.symmetry import (
    ContinuousSymmetry,
    describe_symmetries,
    detect_symmetries,
    symmetry_transforms,
)


def _detect(mesh):
    return detect_symmetries(mesh, mesh_diameter(mesh))


def _assert_group_preserves_surface(mesh, transforms, tol):
    pts, _ = trimesh.sample.sample_surface(mesh, 500, seed=3)
    for T in transforms:
        moved = pts @ T[:3, :3].T + T[:3, 3]
        _, dist, _ = trimesh.proximity.closest_point(mesh, moved)
        assert np.percentile(dist, 95) < tol


def test_cylinder_is_continuous_with_a_flip():
    mesh = trimesh.creation.cylinder(radius=0.02, height=0.06, sections=64)
    rep = _detect(mesh)
    assert len(rep.continuous) == 1
    np.testing.assert_allclose(np.abs(rep.continuous[0].axis), [0, 0, 1], atol=1e-3)
    assert len(rep.discrete) == 1  # one flip; the others are it composed with the axis
    assert rep.describe().startswith("continuous about z")


def test_cone_is_continuous_without_flip():
    mesh = trimesh.creation.cone(radius=0.02, height=0.06, sections=64)
    rep = _detect(mesh)
    assert len(rep.continuous) == 1 and len(rep.discrete) == 0


def test_box_with_distinct_sides_has_three_two_fold_axes():
    mesh = trimesh.creation.box([0.05, 0.03, 0.02])
    rep = _detect(mesh)
    assert not rep.continuous
    assert len(rep.discrete) == 3
    angles = Rotation.from_matrix(rep.discrete[:, :3, :3]).magnitude()
    np.testing.assert_allclose(angles, np.pi, atol=1e-3)
    _assert_group_preserves_surface(mesh, rep.discrete, 1e-4)


def test_hexagonal_prism_is_dihedral_of_order_six():
    mesh = trimesh.creation.cylinder(radius=0.02, height=0.01, sections=6)
    rep = _detect(mesh)
    assert not rep.continuous
    assert len(rep.discrete) == 11  # D6 has 12 elements, identity excluded
    assert "6-fold about z" in rep.describe()
    assert "2-fold about 6 axes" in rep.describe()
    _assert_group_preserves_surface(mesh, rep.discrete, 1e-4)


def test_off_centre_symmetry_axis_carries_its_offset():
    mesh = trimesh.creation.cylinder(radius=0.02, height=0.01, sections=6)
    mesh.apply_transform(trimesh.transformations.rotation_matrix(0.4, [1, 2, 0]))
    mesh.apply_translation([0.03, -0.02, 0.01])
    rep = _detect(mesh)
    _assert_group_preserves_surface(mesh, rep.discrete, 1e-4)
    assert len(rep.discrete) == 11


def test_thin_hex_bar_counts_as_continuous_within_the_tolerance():
    # Turning a 10 mm hex bar by 30 degrees moves its surface by < 2.5% of its 54 mm diameter.
    mesh = trimesh.creation.cylinder(radius=0.01, height=0.05, sections=6)
    rep = _detect(mesh)
    assert len(rep.continuous) == 1


def test_asymmetric_part_has_no_symmetry():
    a = trimesh.creation.box([0.05, 0.02, 0.01])
    b = trimesh.creation.box([0.01, 0.03, 0.02])
    b.apply_translation([0.02, 0.02, 0.01])
    c = trimesh.creation.icosphere(2, 0.006)
    c.apply_translation([-0.02, 0.0, 0.01])
    mesh = trimesh.util.concatenate([a, b, c])
    rep = _detect(mesh)
    assert not rep.is_symmetric
    assert rep.describe() == "none"


def test_detection_is_deterministic():
    mesh = trimesh.creation.cylinder(radius=0.02, height=0.01, sections=6)
    a, b = _detect(mesh), _detect(mesh)
    np.testing.assert_array_equal(a.discrete, b.discrete)


def test_symmetry_transforms_identity_first_and_bop_combination():
    flip = np.eye(4)
    flip[:3, :3] = Rotation.from_euler("x", np.pi).as_matrix()
    cont = (ContinuousSymmetry((0.0, 0.0, 1.0), (0.0, 0.0, 0.0)),)
    step = np.deg2rad(10)
    syms = symmetry_transforms(flip[None], cont, step)
    np.testing.assert_array_equal(syms[0], np.eye(4))
    assert len(syms) == 2 * 36
    # every element keeps the z axis on the z line (up to sign)
    np.testing.assert_allclose(np.abs(syms[:, 2, 2]), 1.0, atol=1e-12)
    assert describe_symmetries(np.zeros((0, 4, 4)), cont) == "continuous about z"


def test_bad_diameter_is_rejected():
    with pytest.raises(ValueError, match="diameter"):
        detect_symmetries(trimesh.creation.box([1, 1, 1]), 0.0)
