"""RotationMixture: symmetric equivalents, gating, founding, the paper's Fig. 6 behaviour."""

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from posefuse.estimator.core.geometry import rotation_angle, so3_exp
from posefuse.estimator.core.objects import make_model
from posefuse.estimator.rotation.mixture import (
    MixtureConfig,
    RotationMixture,
    _axis_angle_optimum,
    closest_equivalent,
    closest_equivalents,
    discrete_selection,
)
from posefuse.evaluation.eval_points import eval_points

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
    pts = eval_points(model)[:: max(len(eval_points(model)) // 300, 1)]
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


# --- the pieces one at a time, against brute force and written-out values -------------------


def _rot_about(axis, theta):
    return so3_exp(np.asarray(axis, float) * theta)


@pytest.mark.parametrize("seed", range(3))
def test_axis_angle_optimum_maximises_the_trace_about_any_axis(seed):
    """The closed form against a 0.05 degree grid, about an axis that is no coordinate axis, for
    one matrix and for a batch (the form closest_equivalents calls it with)."""
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    grid = np.deg2rad(np.arange(-180.0, 180.0, 0.05))
    turns = so3_exp(grid[:, None] * axis)  # (G, 3, 3)
    M = rng.normal(size=(2, 3, 3, 3))
    theta = _axis_angle_optimum(M, axis)
    assert theta.shape == (2, 3)
    for idx in np.ndindex(2, 3):
        traces = np.trace(M[idx] @ turns, axis1=1, axis2=2)
        best = float(np.trace(M[idx] @ _rot_about(axis, theta[idx])))
        assert best >= traces.max() - 1e-9
        assert best == pytest.approx(traces.max(), abs=1e-5 * np.abs(M[idx]).sum())
        assert float(_axis_angle_optimum(M[idx], axis)) == pytest.approx(theta[idx], abs=1e-12)


def test_closest_equivalent_about_a_tilted_continuous_axis():
    """A part symmetric about a tilted axis: the measurement turned about that axis is undone
    exactly, and the angle is the brute force's over the axis."""
    axis = np.array([1.0, 2.0, 2.0]) / 3.0
    R_ref = _random(21)
    for deg in (-150.0, -20.0, 35.0, 170.0):
        noise = _rot([0.3, -1.0, 0.2], 3.0)
        R_meas = noise @ R_ref @ _rot_about(axis, np.deg2rad(deg))
        R_eq, angle = closest_equivalent(R_meas, R_ref, np.eye(3)[None], axis[None])
        grid = np.deg2rad(np.arange(-180.0, 180.0, 0.05))
        brute = rotation_angle(
            np.einsum("ji,gjk->gik", R_ref, R_meas @ so3_exp(grid[:, None] * axis))
        )
        assert brute.min() - np.deg2rad(0.025) <= angle <= brute.min() + 1e-12  # grid: 0.05 deg
        # the equivalent is the measurement turned about the axis (its points on the axis stay)
        np.testing.assert_allclose(R_eq @ axis, R_meas @ axis, atol=1e-12)
        assert angle <= 3.0 * DEG + 1e-9


def test_discrete_selection_index_and_margin_against_a_sorted_search(models):
    """The index of the closest equivalent and the gap to the runner-up, against sorting all
    of the gear's equivalents; with the identity alone the margin is infinite."""
    gear = models["gear"]
    S = RotationMixture.for_model(gear).discrete
    assert len(S) > 3
    R_ref = _random(30)
    R_meas = np.stack(
        [so3_exp(np.random.default_rng(k).normal(0, 0.5, 3)) @ R_ref for k in range(8)]
    )
    k, margin = discrete_selection(R_meas, R_ref, S)
    for m in range(len(R_meas)):
        angles = rotation_angle(np.einsum("ji,djk->dik", R_ref, R_meas[m] @ S))
        order = np.sort(angles)
        assert k[m] == int(np.argmin(angles))
        assert margin[m] == pytest.approx(order[1] - order[0], abs=1e-12)
        assert margin[m] > 0
    k1, margin1 = discrete_selection(R_meas, R_ref, np.eye(3)[None])
    np.testing.assert_array_equal(k1, 0)
    assert margin1.dtype == float and np.all(np.isinf(margin1))


def test_a_mixture_refuses_symmetries_without_the_identity_first_and_keeps_its_config(models):
    flips = np.stack([np.diag([1.0, -1.0, -1.0]), np.eye(3)])
    with pytest.raises(
        ValueError, match=r"^RotationMixture: the first discrete symmetry must be the identity$"
    ):
        RotationMixture(flips)
    mix = RotationMixture()
    assert mix.continuous_axes.shape == (0, 3) and mix.discrete.shape == (1, 3, 3)
    config = MixtureConfig(gate_deg=12.0, sigma_deg=4.0)
    assert RotationMixture.for_model(models["gear"], config).config is config


@pytest.mark.parametrize("bad", [0.0, -0.5, float("inf"), float("nan")])
def test_a_confidence_must_be_finite_and_positive(bad):
    mix = RotationMixture()
    mix.add(np.eye(3), 0.5)
    with pytest.raises(ValueError, match="confidence must be > 0"):
        mix.add(np.eye(3), bad)
    assert len(mix.components) == 1 and mix.components[0].n == 1  # state untouched


def test_covariance_is_sigma_squared_over_the_summed_confidence():
    """Members that agree exactly: J = I at r = 0, so the covariance is sigma^2 / sum(c) per
    axis (a measurement of confidence 1 counts as one of standard deviation sigma)."""
    sigma = 7.0
    mix = RotationMixture(config=MixtureConfig(sigma_deg=sigma))
    R = _random(40)
    conf = [0.9, 0.4, 0.7]
    for c in conf:
        mix.add(R, c)
    expected = np.deg2rad(sigma) ** 2 / sum(conf)
    np.testing.assert_allclose(
        mix.best().cov, expected * np.eye(3), rtol=1e-6, atol=1e-12 * expected
    )
    np.testing.assert_allclose(mix.best().R_world_obj, R, atol=1e-12)


def test_old_members_retire_from_the_window_but_keep_their_confidence():
    config = MixtureConfig(max_members=5)
    mix = RotationMixture(config=config)
    R = _random(50)
    rng = np.random.default_rng(5)
    conf = rng.uniform(0.2, 1.0, 8)
    for k, c in enumerate(conf):
        mix.add(_rot(rng.normal(size=3), 2.0) @ R, float(c))
        comp = mix.components[0]
        assert len(comp.members) == min(k + 1, 5)
    comp = mix.components[0]
    assert comp.retired == 3 and comp.n == 8
    assert comp.retired_confidence == pytest.approx(conf[:3].sum(), rel=1e-12)
    assert comp.confidence == pytest.approx(conf.sum(), rel=1e-12)
    kept = np.array([c for _, c in comp.members])
    np.testing.assert_allclose(kept, conf[3:], rtol=1e-12)  # the newest five, in order


@pytest.mark.parametrize("seed", range(3))
def test_kept_choices_match_a_full_search_while_the_mean_turns_about_the_axis(models, seed):
    """Members spread over a whole period of the gear's turn, while the truth itself turns about
    that axis a little each step: the mean keeps moving, members' closest equivalents switch,
    and the kept choices must follow exactly as a full search does."""
    gear = models["gear"]
    config = MixtureConfig(max_members=15)
    fast = RotationMixture.for_model(gear, config)
    slow = _FullSearchMixture.for_model(gear, config)
    # the smallest turn about z among the symmetries: the gear's period
    about_z = [S for S in fast.discrete[1:] if abs(S[2, 2] - 1) < 1e-9]
    period = min(rotation_angle(np.array(about_z)))
    rng = np.random.default_rng(seed)
    R0 = _random(60 + seed)
    for step in range(45):
        drift = _rot_about([0, 0, 1], np.deg2rad(1.5) * step)
        spin = _rot_about([0, 0, 1], rng.uniform(-0.5, 0.5) * period)
        R = so3_exp(rng.normal(0, 2 * DEG, 3)) @ R0 @ drift @ spin
        c = float(rng.uniform(0.3, 1.0))
        assert fast.add(R, c) == slow.add(R, c)
    assert len(fast.components) == len(slow.components)
    for a, b in zip(fast.components, slow.components, strict=True):
        np.testing.assert_allclose(a.R_world_obj, b.R_world_obj, atol=1e-9)
