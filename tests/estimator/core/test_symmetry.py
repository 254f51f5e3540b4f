"""Symmetry detection on primitives with known groups, and BOP-style discretisation."""

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from posefuse.estimator.core.objects import mesh_diameter
from posefuse.estimator.core.symmetry import (
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


@pytest.mark.parametrize(
    "make, main_order",
    [
        (lambda: trimesh.creation.cylinder(radius=0.02, height=0.06, sections=64), 0),
        (lambda: trimesh.creation.cylinder(radius=0.02, height=0.01, sections=6), 6),
        (lambda: trimesh.creation.box([0.05, 0.03, 0.02]), 2),
    ],
)
def test_axes_are_distinct_main_axis_first_and_alternatives_are_not_claims(make, main_order):
    """The report's axes: the main one first (a continuous axis before any discrete one, then
    the highest order), no two along one direction, and no alternative that repeats a claimed
    axis with its order."""
    rep = _detect(make())
    axes = rep.axes
    assert axes and axes[0].order == main_order
    if main_order == 0:
        np.testing.assert_allclose(np.abs(axes[0].axis), [0, 0, 1], atol=1e-3)
    for i, a in enumerate(axes):
        for b in axes[i + 1 :]:
            assert abs(np.dot(a.axis, b.axis)) < 0.99
    assert all(a.order <= axes[0].order for a in axes[1:] if axes[0].order)
    for alt in rep.alternatives:
        assert not any(abs(np.dot(alt.axis, a.axis)) > 0.99 and alt.order == a.order for a in axes)


def test_off_centre_symmetry_axis_carries_its_offset():
    mesh = trimesh.creation.cylinder(radius=0.02, height=0.01, sections=6)
    mesh.apply_transform(trimesh.transformations.rotation_matrix(0.4, [1, 2, 0]))
    mesh.apply_translation([0.03, -0.02, 0.01])
    rep = _detect(mesh)
    _assert_group_preserves_surface(mesh, rep.discrete, 1e-4)
    assert len(rep.discrete) == 11


def test_thin_hex_bar_is_six_fold_with_continuous_as_the_flagged_alternative():
    # Turning a 10 mm hex bar by 30 degrees moves its surface by < 2.5% of its 54 mm diameter, so
    # continuous passes the tolerance; but the bar is exactly 6-fold, and its facets are what an
    # image shows: the exact group is claimed and the continuous one left for a person to choose.
    mesh = trimesh.creation.cylinder(radius=0.01, height=0.05, sections=6)
    rep = _detect(mesh)
    assert not rep.continuous
    assert rep.axes[0].order == 6
    assert [a.order for a in rep.alternatives if a.order == 0] == [0]
    assert any("continuous" in flag for flag in rep.flags)


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
    assert rep.group_residual == 0.0  # no group, nothing of it fails


def test_the_report_carries_the_group_residual_and_the_tolerances_it_was_found_with():
    mesh = trimesh.creation.cylinder(radius=0.02, height=0.01, sections=6)
    rep = detect_symmetries(mesh, mesh_diameter(mesh), tol_frac=0.004, near_frac=0.02)
    assert (rep.tol_frac, rep.near_frac) == (0.004, 0.02)
    # a faceted prism turns onto itself to sampling accuracy: small, but measured, not 0
    assert 0.0 < rep.group_residual <= 0.004


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


def _wheel(n_spokes: int, height: float = 0.0015, width: float = 0.008) -> trimesh.Trimesh:
    """A disc (80 mm) with ``n_spokes`` shallow spokes on both faces: exactly dihedral of order
    n, yet every rotation about the axis moves the surface by at most 1.5 mm, within the 2.5%
    tolerance, so a test of single angles would call it continuous."""
    parts = [trimesh.creation.cylinder(radius=0.04, height=0.01, sections=128)]
    for k in range(n_spokes):
        for side in (1.0, -1.0):
            spoke = trimesh.creation.box([0.03, width, height])
            spoke.apply_translation([0.018, 0.0, side * (0.005 + height / 2)])
            spoke.apply_transform(
                trimesh.transformations.rotation_matrix(2 * np.pi * k / n_spokes, [0, 0, 1])
            )
            parts.append(spoke)
    return trimesh.util.concatenate(parts)


def _rotations_about(discrete, axis):
    out = []
    for T in discrete:
        rotvec = Rotation.from_matrix(T[:3, :3]).as_rotvec()
        if abs(abs(rotvec @ axis) - np.linalg.norm(rotvec)) < 1e-6:
            out.append(np.degrees(np.linalg.norm(rotvec)))
    return sorted(out)


@pytest.mark.parametrize("n_spokes", [4, 5])
def test_exact_spoked_wheel_is_n_fold_not_continuous(n_spokes):
    rep = _detect(_wheel(n_spokes))
    assert not rep.continuous, rep.describe()
    assert rep.axes[0].order == n_spokes
    # the whole group about the axis: exactly the n-1 non-trivial turns, nothing finer
    got = _rotations_about(rep.discrete, np.array([0.0, 0.0, 1.0]))
    expected = sorted(min(a, 360 - a) for a in 360.0 * np.arange(1, n_spokes) / n_spokes)
    np.testing.assert_allclose(sorted(min(a, 360 - a) for a in got), expected, atol=0.5)
    # the looser group it would have claimed is reported and flagged for a person to decide
    assert any(a.order == 0 for a in rep.alternatives)
    assert any("continuous about z" in flag and "not claimed" in flag for flag in rep.flags)
    assert len(rep.discrete) == 2 * n_spokes - 1  # with the n flips between the faces
    _assert_group_preserves_surface(_wheel(n_spokes), rep.discrete, 2e-4)


def test_claims_report_their_residual_and_margin():
    rep = _detect(trimesh.creation.cylinder(radius=0.02, height=0.06, sections=64))
    for axis in rep.axes:
        assert 0.0 <= axis.residual <= rep.tol_frac
        assert rep.margin(axis) == pytest.approx(rep.tol_frac - axis.residual)
    assert rep.group_residual <= rep.tol_frac
    assert rep.flags == ()  # an exact cylinder has nothing near the tolerance


def test_a_near_miss_is_flagged_not_claimed():
    # a box whose x and y sides differ by 4.5 mm (6% of its diameter): the 4-fold turn misses the
    # tolerance by less than 1% of the diameter
    box = trimesh.creation.box([0.050, 0.0545, 0.02])
    rep = _detect(box)
    assert all(a.order == 2 for a in rep.axes)
    flagged = [a for a in rep.alternatives if a.order == 4]
    assert flagged and rep.tol_frac < flagged[0].residual <= rep.tol_frac + rep.near_frac
    assert any("4-fold" in flag and "misses the tolerance" in flag for flag in rep.flags)


def test_a_person_overrides_detection_with_a_spec():
    from posefuse.estimator.core.symmetry import symmetry_from_spec

    mesh = _wheel(5)
    d = mesh_diameter(mesh)
    rep = _detect(mesh)
    disc, cont = symmetry_from_spec("continuous", mesh, d, rep)
    assert len(disc) == 0 and np.allclose(np.abs(cont[0].axis), [0, 0, 1], atol=1e-3)
    disc, cont = symmetry_from_spec("5:z", mesh, d)
    assert cont == () and len(disc) == 4
    assert symmetry_from_spec("none", mesh, d)[0].shape == (0, 4, 4)
    for bad in ("1", "73", "five", "4:w"):
        with pytest.raises(ValueError, match="symmetry"):
            symmetry_from_spec(bad, mesh, d)


# ---------------------------------------------------------------- a person's spec, summaries


def _rotation_axis_of(T):
    rotvec = Rotation.from_matrix(T[:3, :3]).as_rotvec()
    return np.abs(rotvec / np.linalg.norm(rotvec))


@pytest.mark.parametrize("name, index", [("x", 0), ("y", 1), ("z", 2)])
def test_a_spec_turns_about_the_object_axis_it_names(name, index):
    from posefuse.estimator.core.symmetry import symmetry_from_spec

    box = trimesh.creation.box([0.10, 0.06, 0.03])
    disc, cont = symmetry_from_spec(f"2:{name}", box, mesh_diameter(box))
    assert cont == () and disc.shape == (1, 4, 4)
    np.testing.assert_allclose(_rotation_axis_of(disc[0]), np.eye(3)[index], atol=1e-12)


@pytest.mark.parametrize(
    "extents, main",
    [
        ([0.10, 0.02, 0.03], 0),
        ([0.10, 0.09, 0.01], 2),
        ([0.02, 0.10, 0.03], 1),
        # moments 1 : 1.9 : 4.4: the largest stands apart (gaps 0.9 and 2.5), though the sum of
        # the two smaller ones (2.9) is more than either gap
        ([0.10, 0.06, 0.04], 0),
    ],
)
def test_main_without_detection_is_the_principal_axis_that_stands_apart(extents, main):
    """A rod's long axis, a plate's normal: the moment farthest from the other two."""
    from posefuse.estimator.core.symmetry import symmetry_from_spec

    box = trimesh.creation.box(extents)
    _, cont = symmetry_from_spec("continuous", box, mesh_diameter(box))
    np.testing.assert_allclose(np.abs(cont[0].axis), np.eye(3)[main], atol=1e-9)
    disc, _ = symmetry_from_spec("2", box, mesh_diameter(box))
    np.testing.assert_allclose(_rotation_axis_of(disc[0]), np.eye(3)[main], atol=1e-9)


def test_main_is_the_detected_axis_else_the_first_alternative():
    from posefuse.estimator.core.symmetry import SymmetryAxis, SymmetryReport, symmetry_from_spec

    box = trimesh.creation.box([0.10, 0.02, 0.03])  # principal axis x
    d = mesh_diameter(box)
    claimed = SymmetryReport(np.zeros((0, 4, 4)), (), axes=(SymmetryAxis((0, 1, 0), 2, 0.0),))
    flagged = SymmetryReport(
        np.zeros((0, 4, 4)), (), alternatives=(SymmetryAxis((0, 0, 1), 4, 0.03),)
    )
    for report, expected in ((claimed, [0, 1, 0]), (flagged, [0, 0, 1])):
        _, cont = symmetry_from_spec("continuous", box, d, report)
        np.testing.assert_allclose(np.abs(cont[0].axis), expected, atol=1e-12)


def test_a_continuous_spec_passes_through_the_surface_centroid():
    from posefuse.estimator.core.symmetry import symmetry_from_spec

    offset = np.array([0.01, -0.02, 0.03])
    box = trimesh.creation.box([0.10, 0.02, 0.03])
    box.apply_translation(offset)
    disc, cont = symmetry_from_spec("continuous:z", box, mesh_diameter(box))
    assert disc.shape == (0, 4, 4) and len(cont) == 1
    np.testing.assert_allclose(cont[0].offset, offset, atol=1e-9)
    np.testing.assert_allclose(cont[0].axis, [0, 0, 1])


def test_a_spec_accepts_orders_from_2_to_max_order():
    from posefuse.estimator.core.symmetry import MAX_ORDER, symmetry_from_spec

    box = trimesh.creation.box([0.10, 0.06, 0.03])
    d = mesh_diameter(box)
    assert symmetry_from_spec("2:z", box, d)[0].shape == (1, 4, 4)
    assert symmetry_from_spec(f"{MAX_ORDER}:z", box, d)[0].shape == (MAX_ORDER - 1, 4, 4)
    with pytest.raises(ValueError, match=f"2 <= N <= {MAX_ORDER}"):
        symmetry_from_spec(f"{MAX_ORDER + 1}:z", box, d)


def _turn(axis, angle):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.asarray(axis, float) * angle).as_matrix()
    return T


def test_summaries_name_each_axis_by_its_largest_order():
    from posefuse.estimator.core.symmetry import _group_closure

    # the identity in the list is skipped, not the end of it
    assert describe_symmetries(np.stack([np.eye(4), _turn([0, 0, 1], np.pi)]), []) == (
        "2-fold about z"
    )
    # an 8-fold group holds turns of 45, 90 and 135 degrees: the axis is 8-fold
    eight = _group_closure([_turn([0, 0, 1], np.pi / 4)], scale=1.0)
    assert describe_symmetries(eight, []) == "8-fold about z"
    # dihedral: the 6-fold axis first, then its six flips
    d6 = _group_closure([_turn([0, 0, 1], np.pi / 3), _turn([1, 0, 0], np.pi)], scale=1.0)
    assert len(d6) == 11
    assert describe_symmetries(d6, []) == "6-fold about z; 2-fold about 6 axes"
    flips = describe_symmetries([_turn([1, 0, 0], np.pi)], [ContinuousSymmetry((0.0, 0.0, 1.0))])
    assert flips == (
        "continuous about z; 2-fold about x; with the flips about every axis perpendicular to it"
    )
    from posefuse.estimator.core.symmetry import SymmetryAxis

    assert SymmetryAxis((0.6, 0.8, 0.0), 3, 0.0).name() == "3-fold about [0.600, 0.800, 0.000]"


def test_a_continuous_axis_is_discretised_in_equal_steps_around_the_whole_turn():
    T = symmetry_transforms(
        np.zeros((0, 4, 4)), [ContinuousSymmetry((0.0, 0.0, 1.0))], max_step_rad=np.deg2rad(10.0)
    )
    assert T.shape == (36, 4, 4)
    angles = np.sort(np.mod(Rotation.from_matrix(T[:, :3, :3]).as_rotvec()[:, 2], 2 * np.pi))
    np.testing.assert_allclose(angles, np.deg2rad(10.0) * np.arange(36), atol=1e-9)


# ------------------------------------------------------------------ the sweep for 2-fold axes


@pytest.mark.parametrize("normal", [[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])
def test_the_flip_sweep_finds_the_best_axis_perpendicular_to_any_normal(normal):
    from posefuse.estimator.core.symmetry import _sweep_flip

    normal = np.array(normal)
    # the true flip axis: perpendicular to the normal, at an angle no coarse grid starts on
    other = np.roll(normal, 1)
    target = np.cos(1.1) * other + np.sin(1.1) * np.cross(normal, other)

    def flip_score(b):
        return 1.0 - abs(float(np.dot(b, target)))

    found = _sweep_flip(normal, np.pi, flip_score, tol_frac=0.025)
    assert found is not None and found.order == 2
    assert abs(np.dot(found.axis, target)) > 1 - 1e-8 and found.residual < 1e-8
    # about a continuous axis every perpendicular flip is alike: the score of one decides,
    # and a score at the tolerance passes
    at_tol = _sweep_flip(normal, 0.0, lambda b: 0.025, tol_frac=0.025)
    assert at_tol is not None and at_tol.residual == 0.025
    assert np.isfinite(at_tol.axis).all() and abs(np.dot(at_tol.axis, normal)) < 1e-12
    assert _sweep_flip(normal, 0.0, lambda b: 0.0251, tol_frac=0.025) is None
