"""Detection: what a front end hands the estimator, checked where it is made."""

from __future__ import annotations

import numpy as np
import pytest

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
