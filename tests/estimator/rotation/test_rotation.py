"""Template banks, the scale-aware re-crop, the viewing-ray correction, and matching."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from posefuse.estimator.core.geometry import random_rotations, rotation_angle
from posefuse.estimator.rotation.matching import RotationMatcher, _best_first, ray_correction
from posefuse.estimator.rotation.recrop import crop_roi
from posefuse.estimator.rotation.render import DirectionalLight, Lighting, Renderer
from posefuse.estimator.rotation.templates import (
    TEMPLATE_LIGHTS_CAM,
    TEMPLATE_MATERIAL,
    TemplateConfig,
    build_template_bank,
    template_rotations,
)
from posefuse.sim.scenes import REALSENSE_1280x720 as CAM

COARSE = TemplateConfig(subdivisions=1, inplane_step_deg=15.0)


@pytest.fixture(scope="module")
def tube(robi_catalog):
    return robi_catalog.by_name("tube_fitting")


@pytest.fixture(scope="module")
def tube_bank(tube, tmp_path_factory):
    return build_template_bank(tube, COARSE, tmp_path_factory.mktemp("tpl"), show_progress=False)


def test_fundamental_region_sizes(robi_catalog):
    full = len(template_rotations(COARSE))
    assert full == 42 * 24
    for name, order in (("tube_fitting", 2), ("gear", 36)):
        model = robi_catalog.by_name(name)
        kept = len(template_rotations(COARSE, model.symmetry_transforms(np.deg2rad(5))))
        assert kept == pytest.approx(full / order, rel=0.35)


def test_bank_is_cached(tube, tube_bank, tmp_path_factory):
    cache = tmp_path_factory.mktemp("tpl2")
    a = build_template_bank(tube, COARSE, cache, show_progress=False)
    assert len(list(cache.glob("*.npz"))) == 1
    b = build_template_bank(tube, COARSE, cache, show_progress=False)
    np.testing.assert_array_equal(a.feat_x, b.feat_x)
    np.testing.assert_array_equal(a.R_cam_obj, b.R_cam_obj)
    assert b.build_seconds == a.build_seconds  # loaded, not rebuilt
    other = TemplateConfig(subdivisions=1, inplane_step_deg=20.0)
    build_template_bank(tube, other, cache, show_progress=False)
    assert len(list(cache.glob("*.npz"))) == 2  # another key
    assert a.feat_valid.sum(1).min() > 20 and len(a) > 300


def test_ray_correction_takes_the_axis_to_the_ray():
    for t in ([0.1, -0.2, 0.6], [0, 0, 1.0], [-0.3, 0.05, 0.4]):
        d = np.array(t) / np.linalg.norm(t)
        np.testing.assert_allclose(ray_correction(np.array(t)) @ [0, 0, 1], d, atol=1e-12)


def _render(model, R, t):
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    T_wc = np.linalg.inv(T)
    lights = tuple(
        DirectionalLight(tuple(T_wc[:3, :3] @ np.asarray(d)), c) for d, c in TEMPLATE_LIGHTS_CAM
    )
    renderer = Renderer([model.mesh], materials=[TEMPLATE_MATERIAL])
    lighting = Lighting(lights, ambient=(0.15,) * 3, background=(0, 0, 0))
    return renderer.render(CAM, T_wc, lighting, shadows=False)


def test_recrop_normalises_the_scale(tube, tube_bank):
    R = random_rotations(1, 0)[0]
    areas = []
    for t in ([0.05, 0.02, 0.5], [-0.1, 0.05, 0.9]):
        res = _render(tube, R, np.array(t))
        _, roi_mask = crop_roi(res.image, CAM.K, np.array(t), tube_bank, res.instance >= 0, 0)
        areas.append((roi_mask > 0).sum())
    assert areas[0] == pytest.approx(areas[1], rel=0.1)


def test_matching_recovers_the_rotation_off_axis(tube, default_banks):
    matcher = RotationMatcher(default_banks[tube.obj_id])
    S = tube.symmetry_transforms()[:, :3, :3]
    errors = []
    for R in random_rotations(12, 5):
        t = np.array([0.12, -0.07, 0.7])  # well off the optical axis
        res = _render(tube, R, t)
        hyp = matcher.measure(res.image, CAM.K, t, res.instance >= 0)
        assert hyp and 0 < hyp[0].confidence <= 1
        err = rotation_angle(np.einsum("sji,jk->sik", R @ S, hyp[0].R_cam_obj)).min()
        errors.append(np.rad2deg(err))
    # the bank's grid (162 viewpoints x 10 deg) limits accuracy; most views land near the truth
    assert np.median(errors) < 12, errors


def test_top_k_hypotheses_are_distinct(tube, tube_bank):
    from posefuse.estimator.rotation.matching import RotationConfig

    matcher = RotationMatcher(tube_bank, RotationConfig(top_k=3, nms_deg=15, min_confidence=0))
    t = np.array([0.0, 0.0, 0.7])
    res = _render(tube, random_rotations(1, 8)[0], t)
    hyp = matcher.measure(res.image, CAM.K, t, res.instance >= 0)
    assert len(hyp) == 3
    assert hyp[0].confidence >= hyp[1].confidence >= hyp[2].confidence
    for i in range(3):
        for j in range(i):
            assert rotation_angle(hyp[i].R_cam_obj.T @ hyp[j].R_cam_obj) >= np.deg2rad(15) - 1e-9


@settings(max_examples=300, deadline=None)
@given(
    st.lists(st.integers(0, 12), min_size=1, max_size=200),
    st.floats(0.0, 1.0),
    st.integers(1, 80),
)
def test_best_first_is_a_stable_sort_above_the_floor(ticks, floor, head):
    # coarse scores make many ties, at the head's boundary too
    scores = np.array(ticks, float) / 12
    expected = [int(k) for k in np.argsort(-scores, kind="stable") if scores[k] >= floor]
    assert [int(k) for k in _best_first(scores, floor, head)] == expected
