"""RotationMixture: symmetric equivalents, gating, founding, the paper's Fig. 6 behaviour."""

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from posefuse.estimator.geometry import rotation_angle, so3_exp
from posefuse.estimator.mixture import (
    MixtureConfig,
    RotationMixture,
    closest_equivalent,
    closest_equivalents,
)
from posefuse.estimator.objects import make_model

DEG = np.pi / 180


def _rot(axis, deg):
    axis = np.asarray(axis, float)
    return so3_exp(axis / np.linalg.norm(axis) * deg * DEG)


def _random(seed):
    return Rotation.random(random_state=seed).as_matrix()


@pytest.fixture(scope="module")
def models(robi_catalog):
    return {m.name: m for m in robi_catalog.values()}


@pytest.mark.parametrize("name", ["gear", "chrome_screw", "tube_fitting"])
def test_closest_equivalent_undoes_any_symmetry(models, name):
    """The chosen rotation is the measurement moved by a symmetry (the part's points land on
    the part again), and no symmetry brings the measurement closer to the reference (a brute
    force over the group, continuous axes at 0.25 deg)."""
    model = models[name]
    mix = RotationMixture.for_model(model)
    pts = model.eval_points[:: max(len(model.eval_points) // 300, 1)]
    group = model.symmetry_transforms(np.deg2rad(0.25))[:, :3, :3]
    rng = np.random.default_rng(0)
    for seed in range(20):
        R_true = _random(seed)
        S = model.symmetry_transforms(np.deg2rad(7))[:, :3, :3]
        sym = S[rng.integers(len(S))]
        noise = _rot(rng.normal(size=3), 5.0)
        R_meas = noise @ R_true @ sym  # an equivalent appearance, measured with 5 deg error
        R_eq, angle = closest_equivalent(R_meas, R_true, mix.discrete, mix.continuous_axes)
        # an equivalent of the measurement: R_meas^T R_eq maps the part's surface onto itself
        rel = R_meas.T @ R_eq
        _, gap, _ = model.mesh.nearest.on_surface(pts @ rel.T)
        assert gap.max() < 0.01 * model.diameter, (seed, gap.max() / model.diameter)
        # the angle returned is the chosen one's, and the closest over the whole group
        assert rotation_angle(R_eq.T @ R_true) == pytest.approx(angle, abs=1e-9)
        brute = rotation_angle(np.einsum("ji,sjk->sik", R_true, R_meas @ group)).min()
        assert brute - 0.2 * DEG <= angle <= brute + 1e-9
        if not model.symmetries_continuous:  # undoing ``sym`` leaves the 5 deg of noise
            assert angle == pytest.approx(5.0 * DEG, abs=0.2 * DEG)


def test_without_symmetry_the_measurement_is_kept():
    mesh = trimesh.creation.box([0.05, 0.03, 0.02])
    mesh.vertices[0] += [0.01, 0.0, 0.0]  # break the box's symmetry
    model = make_model(1, "odd", mesh)
    assert not model.is_symmetric
    mix = RotationMixture.for_model(model)
    R = _random(3)
    R_eq, angle = closest_equivalent(R, np.eye(3), mix.discrete, mix.continuous_axes)
    np.testing.assert_allclose(R_eq, R)
    assert angle == pytest.approx(rotation_angle(R))


def test_gating_founds_and_joins():
    mix = RotationMixture(config=MixtureConfig(gate_deg=30))
    R0 = _random(1)
    assert mix.add(R0, 0.8) == 0
    assert mix.add(_rot([0, 0, 1], 20) @ R0, 0.8) == 0  # within the gate
    assert mix.add(_rot([1, 0, 0], 45) @ R0, 0.8) == 1  # outside: a new component
    assert len(mix.components) == 2
    np.testing.assert_allclose(mix.weights, [2 / 3, 1 / 3])
    # the first component's mean lies between its two members
    assert rotation_angle(mix.components[0].R_world_obj.T @ R0) == pytest.approx(
        10 * DEG, abs=0.5 * DEG
    )


def test_mean_is_refined_across_symmetric_members(models):
    """Members given in different symmetric forms still average to the truth."""
    gear = models["gear"]
    mix = RotationMixture.for_model(gear)
    R_true = _random(5)
    S = gear.symmetry_transforms()[:, :3, :3]
    rng = np.random.default_rng(1)
    for _ in range(12):
        sym = S[rng.integers(len(S))]
        mix.add(_rot(rng.normal(size=3), 6.0) @ R_true @ sym, 0.7)
    assert len(mix.components) == 1
    _, err = closest_equivalent(mix.best().R_world_obj, R_true, mix.discrete, mix.continuous_axes)
    assert err < 4 * DEG


def test_fig6_two_similar_components_then_the_right_one_wins():
    R_true = _random(7)
    R_wrong = _rot([0, 1, 0], 90) @ R_true  # a look-alike pose
    rng = np.random.default_rng(2)
    mix = RotationMixture()
    mix.add(_rot(rng.normal(size=3), 4) @ R_true, 0.80)
    mix.add(_rot(rng.normal(size=3), 4) @ R_wrong, 0.82)
    assert len(mix.components) == 2
    w = mix.weights
    assert abs(w[0] - w[1]) < 0.05  # two similar early components
    assert mix.best() is mix.components[1]  # the wrong one leads, slightly
    mix.add(_rot(rng.normal(size=3), 60) @ R_true, 0.6)  # an outlier founds a third
    for _ in range(3):
        mix.add(_rot(rng.normal(size=3), 4) @ R_true, 0.75)
    assert len(mix.components) == 3
    best = mix.best()
    assert best is mix.components[0] and mix.weights[0] > 0.6
    assert rotation_angle(best.R_world_obj.T @ R_true) < 4 * DEG


def test_continuous_axis_is_unobservable_in_the_covariance(models):
    screw = models["chrome_screw"]
    mix = RotationMixture.for_model(screw)
    R = _random(9)
    for k in range(4):
        mix.add(R @ _rot([0, 0, 1], 40 * k), 0.9)  # spun about its axis: the same measurement
    assert len(mix.components) == 1
    comp = mix.best()
    axis_world = comp.R_world_obj @ np.array([0, 0, 1.0])
    along = axis_world @ comp.cov @ axis_world
    across = np.linalg.eigvalsh(comp.cov)[:2]
    assert along == pytest.approx(np.pi**2 / 3) and np.all(across < (6 * DEG) ** 2)


def test_deterministic_and_refuses_bad_confidence():
    def run():
        mix = RotationMixture()
        rng = np.random.default_rng(4)
        for _ in range(6):
            mix.add(_random(int(rng.integers(3))) @ _rot(rng.normal(size=3), 5), 0.5)
        return [c.R_world_obj for c in mix.components], mix.weights

    (a, wa), (b, wb) = run(), run()
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)
    np.testing.assert_array_equal(wa, wb)
    with pytest.raises(ValueError, match="confidence"):
        RotationMixture().add(np.eye(3), float("nan"))


def test_batched_closest_equivalents_match_one_at_a_time():
    """The refinement uses the batched form; it must pick what the single form picks."""
    R_ref = Rotation.random(random_state=10).as_matrix()
    R_meas = Rotation.random(7, random_state=11).as_matrix()
    flips = np.stack([np.eye(3), np.diag([-1.0, 1.0, -1.0])])
    for discrete, axes in ((flips, np.zeros((0, 3))), (flips, np.array([[0.0, 0.0, 1.0]]))):
        batch, angles = closest_equivalents(R_meas, R_ref, discrete, axes)
        for k in range(len(R_meas)):
            one, angle = closest_equivalent(R_meas[k], R_ref, discrete, axes)
            np.testing.assert_allclose(batch[k], one, atol=1e-12)
            assert angles[k] == pytest.approx(angle, abs=1e-12)


class _FullSearchMixture(RotationMixture):
    """The reference: every member's equivalent searched over all symmetries every time."""

    def _equivalents(self, comp, R_members, R_mean):
        return closest_equivalents(R_members, R_mean, self.discrete, self.continuous_axes)[0]


@pytest.mark.parametrize("seed", range(4))
def test_kept_equivalent_choices_match_a_full_search(models, seed):
    """The refinement keeps a member's chosen equivalent while the mean moves less than half
    its margin; over a long noisy sequence (members retired, components founded) the mixture
    equals one that searches all 36 of the gear's equivalents every iteration."""
    model = models["gear"]
    config = MixtureConfig(max_members=12)
    fast = RotationMixture.for_model(model, config)
    slow = _FullSearchMixture.for_model(model, config)
    rng = np.random.default_rng(seed)
    R_true = [_random(seed), _random(seed + 100)]
    syms = fast.discrete
    for step in range(60):
        R = R_true[step % 3 == 0] @ syms[rng.integers(len(syms))]
        R = so3_exp(rng.normal(0, 6 * DEG, 3)) @ R
        c = float(rng.uniform(0.3, 1.0))
        assert fast.add(R, c) == slow.add(R, c)
    assert len(fast.components) == len(slow.components)
    for a, b in zip(fast.components, slow.components, strict=True):
        np.testing.assert_allclose(a.R_world_obj, b.R_world_obj, atol=1e-9)
        np.testing.assert_allclose(a.cov, b.cov, rtol=1e-6, atol=1e-12)
