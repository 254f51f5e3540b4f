"""The bin the parts lie in: the distance outside it, its checks, its JSON form."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from posefuse.estimator.core.bin_region import BinRegion
from posefuse.estimator.core.geometry import make_transform, so3_exp

BIN = BinRegion((0.4, 0.3), 0.08)


def test_inside_and_above_the_rim_is_inside():
    points = np.array([[0.0, 0.0, 0.0], [0.19, -0.14, 0.02], [0.0, 0.0, 0.5], [-0.2, 0.15, 3.0]])
    np.testing.assert_array_equal(BIN.distance_outside(points), 0.0)


def test_under_the_floor_and_beyond_a_wall_by_the_largest_excess():
    points = np.array([[0.0, 0.0, -0.05], [0.25, 0.0, 0.1], [0.0, -0.2, 0.0], [0.3, 0.0, -0.02]])
    np.testing.assert_allclose(BIN.distance_outside(points), [0.05, 0.05, 0.05, 0.1])
    assert BIN.distance_outside(np.array([0.0, 0.0, -0.01])).shape == ()


@settings(max_examples=50, deadline=None)
@given(
    st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3),
    st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3),
    st.lists(st.floats(-0.5, 0.5), min_size=3, max_size=3),
)
def test_a_moved_bin_measures_what_the_bin_at_the_origin_does(point_bin, rotvec, origin):
    """A point given in the bin's frame lies as far outside the bin wherever it stands."""
    T_world_bin = make_transform(so3_exp(np.array(rotvec)), np.array(origin))
    moved = BinRegion(BIN.size, BIN.wall_height, T_world_bin)
    p_bin = np.array(point_bin)
    p_world = T_world_bin[:3, :3] @ p_bin + T_world_bin[:3, 3]
    assert np.isclose(moved.distance_outside(p_world), BIN.distance_outside(p_bin), atol=1e-12)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"size": (0.0, 0.3)},
        {"size": (0.4, float("nan"))},
        {"size": (0.4,)},
        {"wall_height": -0.1},
        {"T_world_bin": np.eye(3)},
        {"T_world_bin": np.diag([1.0, 1.0, -1.0, 1.0])},
        {"T_world_bin": np.full((4, 4), np.inf)},
    ],
)
def test_a_bin_that_is_not_one_is_refused(kwargs):
    with pytest.raises(ValueError, match="bin region"):
        BinRegion(**{"size": (0.4, 0.3), **kwargs})


def test_json_round_trip_and_its_errors():
    T = make_transform(so3_exp(np.array([0.0, 0.0, 0.3])), np.array([0.5, -0.1, 0.7]))
    region = BinRegion((0.5, 0.35), 0.12, T)
    back = BinRegion.from_json(region.to_json())
    assert back.size == region.size and back.wall_height == region.wall_height
    np.testing.assert_array_equal(back.T_world_bin, region.T_world_bin)
    with pytest.raises(ValueError, match=r"needs \['size'\]"):
        BinRegion.from_json({"wall_height": 0.1})
    with pytest.raises(ValueError, match=r"has no \['height'\]"):
        BinRegion.from_json({"size": [0.4, 0.3], "height": 0.1})
    identity = BinRegion.from_json({"size": [0.4, 0.3], "wall_height": 0.05})
    np.testing.assert_array_equal(identity.T_world_bin, np.eye(4))
    assert isinstance(BinRegion((0.4, 0.3), np.float32(0.08)).wall_height, float)
    with pytest.raises(ValueError, match="is an object"):
        BinRegion.from_json([0.4, 0.3])
    with pytest.raises(ValueError, match="bin region"):
        BinRegion.from_json({"size": [0.4, -0.3], "wall_height": 0.1})
