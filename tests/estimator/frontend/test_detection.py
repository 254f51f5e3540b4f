"""Detection: what a front end hands the estimator, checked where it is made."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from posefuse.estimator.frontend.detection import Detection


def _detection(**kw) -> Detection:
    mask = np.zeros((8, 8), bool)
    mask[2:5, 3:6] = True
    args = dict(obj_id=1, bbox_xywh=[3, 2, 3, 3], center_uv=[4, 3], center_cov=np.eye(2), mask=mask)
    return Detection(**{**args, **kw})


def test_a_silhouette_is_read_as_the_outline_and_a_box_is_not():
    silhouette = _detection()
    box = _detection(mask_kind="box")
    assert silhouette.mask_kind == "silhouette" and silhouette.silhouette is silhouette.mask
    assert box.silhouette is None and box.mask is not None  # the box still bounds the RoI
    assert _detection(mask=None).silhouette is None


def test_an_unknown_mask_kind_is_refused_naming_the_field():
    with pytest.raises(ValueError, match="mask_kind must be one of"):
        _detection(mask_kind="polygon")


@pytest.mark.parametrize(
    "field, value, message",
    [
        ("center_cov", np.diag([1.0, -1.0]), "positive definite"),
        ("center_uv", [np.nan, 1.0], "finite"),
        ("bbox_xywh", [0, 0, 0, 3], "positive"),
        ("mask", np.zeros((8, 8), np.uint8), "2D bool"),
    ],
)
def test_bad_fields_are_refused(field, value, message):
    with pytest.raises(ValueError, match=message):
        _detection(**{field: value})


@settings(max_examples=300, deadline=None)
@given(
    st.lists(st.floats(-1e3, 1e3, allow_subnormal=False), min_size=4, max_size=4),
    st.sampled_from([0.0, 1e-12, 1e-7, 1e-3]),
)
def test_the_covariance_checks_decide_as_numpys_allclose_and_eigvalsh(values, skew):
    """The scalar checks refuse exactly the covariances numpy's own tests would: not
    symmetric to ``np.allclose`` (atol 1e-9 x the largest entry), or not positive definite by
    ``np.linalg.eigvalsh`` of the lower triangle (away from a tie at zero)."""
    cov = np.array(values).reshape(2, 2)
    cov[0, 1] = cov[1, 0] * (1 + skew) + skew
    symmetric = np.allclose(cov, cov.T, atol=1e-9 * max(1.0, float(np.abs(cov).max())))
    smallest = float(np.linalg.eigvalsh(cov).min())
    if not symmetric:
        with pytest.raises(ValueError, match="symmetric"):
            _detection(center_cov=cov)
    elif abs(smallest) > 1e-9 * max(1.0, float(np.abs(cov).max())):
        if smallest > 0:
            _detection(center_cov=cov)
        else:
            with pytest.raises(ValueError, match="positive definite"):
                _detection(center_cov=cov)


@pytest.mark.parametrize(
    "cov",
    [
        # allclose's tolerance is 2e-6 + 1e-5 x the entry compared with: 0.010002 one way,
        # 0.0100021 the other; an offset between the two is within it one way only
        [[2000.0, 1000.0], [1000.01000205, 2000.0]],
        [[2000.0, 1000.0], [1000.0 + 0.0095, 2000.0]],  # within it both ways
        [[1e200, 5e199], [5e199, 1e200]],  # products beyond float64
        [[1e-200, 0.0], [0.0, 1e-200]],  # products below it
        [[1e-170, 5e-171], [5e-171, 1e-170]],
        [[1e-200, 0.0], [0.0, -1e-200]],
        [[0.0, 0.0], [0.0, 0.0]],
    ],
)
def test_the_covariance_checks_decide_as_numpy_at_the_edges(cov):
    cov = np.array(cov)
    symmetric = np.allclose(cov, cov.T, atol=1e-9 * max(1.0, float(np.abs(cov).max())))
    if not symmetric:
        with pytest.raises(ValueError, match="symmetric"):
            _detection(center_cov=cov)
    elif np.linalg.eigvalsh(cov).min() > 0:
        _detection(center_cov=cov)
    else:
        with pytest.raises(ValueError, match="positive definite"):
            _detection(center_cov=cov)


def test_an_asymmetric_or_infinite_covariance_is_refused():
    with pytest.raises(ValueError, match="symmetric"):
        _detection(center_cov=[[1.0, 0.5], [0.4, 1.0]])
    with pytest.raises(ValueError, match="finite"):
        _detection(center_cov=[[np.inf, 0.0], [0.0, 1.0]])
