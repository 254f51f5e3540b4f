"""The procedural parts: watertight solids of real size, bbox-centred, deterministic."""

import numpy as np
import pytest

from posefuse.sim.parts import PARTS, build_part


@pytest.mark.parametrize("name", [n for n, _ in PARTS])
def test_part_is_a_watertight_solid_of_real_size(name):
    mesh = build_part(name)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume > 0
    lo, hi = mesh.bounds
    np.testing.assert_allclose((lo + hi) / 2, 0, atol=1e-9)
    assert 30 <= mesh.extents.max() <= 120  # millimetres


def test_parts_are_deterministic():
    a, b = build_part("gear"), build_part("gear")
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.faces, b.faces)


def test_unknown_part_names_the_choices():
    with pytest.raises(ValueError, match="tube_fitting"):
        build_part("sprocket")
