"""Data association: the innovation cost against a finite-difference second implementation,
the gate at its edge, and the joint assignment against brute force."""

from itertools import permutations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from posefuse.estimator.translation.association import (
    GATED,
    AssociationConfig,
    TrackView,
    assign,
    cost_matrix,
    innovation_cost,
)
from posefuse.estimator.translation.gaussian import MIN_DEPTH, CenterObservations

K = np.array([[600.0, 0.0, 320.0], [0.0, 580.0, 240.0], [0.0, 0.0, 1.0]])
EMPTY = CenterObservations.empty()


def _track(t, cov):
    return TrackView(np.asarray(t, float), np.asarray(cov, float), EMPTY)


def _project(T_cam_world, K, t):
    p = T_cam_world[:3, :3] @ t + T_cam_world[:3, 3]
    return (K @ (p / p[2]))[:2]


def _pose(seed):
    rng = np.random.default_rng(seed)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rng.normal(0, 0.3, 3)).as_matrix()
    T[:3, 3] = rng.normal(0, 0.1, 3) + [0, 0, 0.6]
    return T


@pytest.mark.parametrize("seed", range(5))
def test_innovation_cost_is_the_mahalanobis_distance_with_a_numeric_jacobian(seed):
    rng = np.random.default_rng(seed)
    T_cam_world = _pose(seed)
    t = rng.normal(0, 0.05, 3)
    A = rng.normal(0, 0.01, (3, 3))
    P = A @ A.T + 1e-6 * np.eye(3)
    uv = _project(T_cam_world, K, t) + rng.normal(0, 8.0, 2)
    B = rng.normal(0, 2.0, (2, 2))
    R = B @ B.T + np.eye(2)
    # the Jacobian of the projection by central differences
    J = np.zeros((2, 3))
    for i in range(3):
        d = np.zeros(3)
        d[i] = 1e-6
        J[:, i] = (_project(T_cam_world, K, t + d) - _project(T_cam_world, K, t - d)) / 2e-6
    S = J @ P @ J.T + R
    r = _project(T_cam_world, K, t) - uv
    expected = r @ np.linalg.solve(S, r)
    got = innovation_cost(_track(t, P), T_cam_world, K, uv, R)
    assert got == pytest.approx(expected, rel=1e-6)
    # the cost does not depend on the sign of the innovation
    uv_mirror = 2 * _project(T_cam_world, K, t) - uv
    assert innovation_cost(_track(t, P), T_cam_world, K, uv_mirror, R) == pytest.approx(got)


def test_a_certain_track_costs_the_squared_pixel_distance_over_the_detection_variance():
    T = np.eye(4)
    track = _track([0.0, 0.0, 1.0], np.zeros((3, 3)))  # projects to (320, 240) exactly
    for d, var in [((3.0, 4.0), 1.0), ((3.0, 4.0), 4.0), ((0.0, -2.0), 0.5)]:
        uv = np.array([320.0, 240.0]) + d
        cost = innovation_cost(track, T, K, uv, var * np.eye(2))
        assert cost == pytest.approx((d[0] ** 2 + d[1] ** 2) / var, rel=1e-12)
    # the track's own uncertainty widens S: the same detection costs less
    wide = _track([0.0, 0.0, 1.0], np.eye(3) * 1e-4)
    assert innovation_cost(wide, T, K, np.array([323.0, 244.0]), np.eye(2)) < 25.0 / 1.0


def test_a_track_behind_or_at_the_camera_never_associates():
    T = np.eye(4)
    cov = np.eye(3) * 1e-6
    uv = np.array([320.0, 240.0])
    for z in (-0.5, 0.0, MIN_DEPTH):
        assert innovation_cost(_track([0, 0, z], cov), T, K, uv, np.eye(2)) == np.inf
    just_in_front = _track([0, 0, MIN_DEPTH * 1.01], cov)
    assert np.isfinite(innovation_cost(just_in_front, T, K, uv, np.eye(2)))


@pytest.mark.parametrize("seed", range(4))
def test_cost_matrix_is_every_pairs_innovation_cost_by_a_linear_solve(seed):
    # a second implementation, pair by pair: the predicted center, its numeric Jacobian and
    # np.linalg.solve, against the batch's written-out 2 x 2 inverse
    rng = np.random.default_rng(100 + seed)
    T_cam_world = _pose(seed)
    tracks, centers, covs = [], [], []
    for _ in range(5):
        A = rng.normal(0, 0.01, (3, 3))
        tracks.append(_track(rng.normal(0, 0.05, 3), A @ A.T + 1e-6 * np.eye(3)))
    for _ in range(7):
        B = rng.normal(0, 2.0, (2, 2))
        covs.append(B @ B.T + 0.5 * np.eye(2))
        centers.append(_project(T_cam_world, K, rng.normal(0, 0.05, 3)))
    got = cost_matrix(
        tracks, T_cam_world, K, np.array(centers), np.array(covs), AssociationConfig(1e12)
    )
    for i, track in enumerate(tracks):
        J = np.zeros((2, 3))
        for a in range(3):
            d = np.zeros(3)
            d[a] = 1e-6
            J[:, a] = (
                _project(T_cam_world, K, track.t_world_obj + d)
                - _project(T_cam_world, K, track.t_world_obj - d)
            ) / 2e-6
        for j in range(len(centers)):
            r = _project(T_cam_world, K, track.t_world_obj) - centers[j]
            expected = r @ np.linalg.solve(J @ track.cov @ J.T + covs[j], r)
            assert got[i, j] == pytest.approx(expected, rel=1e-6)


def test_a_detection_covariance_that_is_not_positive_definite_is_refused():
    tracks = [_track([0.0, 0.0, 1.0], np.eye(3) * 1e-6)]
    centers = np.array([[320.0, 240.0], [330.0, 240.0]])
    for bad in (np.diag([1.0, 0.0]), np.diag([1.0, np.nan]), -np.eye(2)):
        covs = np.stack([np.eye(2), bad])
        with pytest.raises(ValueError, match="center measurement"):
            cost_matrix(tracks, np.eye(4), K, centers, covs, AssociationConfig())


def test_cost_matrix_gates_at_gate_chi2_inclusive():
    T = np.eye(4)
    tracks = [_track([0.0, 0.0, 1.0], np.zeros((3, 3))), _track([0.1, 0.0, 1.0], np.zeros((3, 3)))]
    # track 0 projects to (320, 240), track 1 to (380, 240)
    centers = np.array([[324.0, 240.0], [320.0, 240.0 + 4.0 + 1e-6], [380.0, 242.0]])
    covs = np.stack([np.eye(2)] * 3)
    cost = cost_matrix(tracks, T, K, centers, covs, AssociationConfig(gate_chi2=16.0))
    assert cost.shape == (2, 3)
    assert cost[0, 0] == pytest.approx(16.0, abs=1e-9)  # on the gate: kept
    assert cost[0, 1] == GATED  # just beyond it
    assert cost[0, 2] == GATED and cost[1, 0] == GATED and cost[1, 1] == GATED
    assert cost[1, 2] == pytest.approx(4.0)
    # a wider gate lets the far pair in, with its true cost
    wide = cost_matrix(tracks, T, K, centers, covs, AssociationConfig(gate_chi2=3700.0))
    assert wide[0, 2] == pytest.approx(60.0**2 + 2.0**2)
    assert cost_matrix([], T, K, centers, covs, AssociationConfig()).shape == (0, 3)
    none = cost_matrix(tracks, T, K, np.zeros((0, 2)), np.zeros((0, 2, 2)), AssociationConfig())
    assert none.shape == (2, 0)


def test_the_gate_must_be_positive():
    assert AssociationConfig().gate_chi2 == 16.0
    assert AssociationConfig(gate_chi2=0.5).gate_chi2 == 0.5  # a tight gate is a valid choice
    for bad in (0.0, -1.0):
        with pytest.raises(ValueError, match="association config"):
            AssociationConfig(gate_chi2=bad)


def test_centers_and_covariances_of_different_lengths_are_refused():
    tracks = [_track([0.0, 0.0, 1.0], np.zeros((3, 3)))]
    centers = np.array([[320.0, 240.0], [330.0, 240.0]])
    with pytest.raises(ValueError):  # never silently truncated to the shorter
        cost_matrix(tracks, np.eye(4), K, centers, np.eye(2)[None], AssociationConfig())


def _brute_force(cost):
    """The minimum total over one-to-one assignments, gated pairs left unassigned, most pairs
    first (what linear_sum_assignment gives with a huge cost for a gated pair)."""
    T, D = cost.shape
    best = None
    if T <= D:
        options = (list(zip(range(T), p, strict=True)) for p in permutations(range(D), T))
    else:
        options = (list(zip(p, range(D), strict=True)) for p in permutations(range(T), D))
    for pairs in options:
        kept = [(i, j) for i, j in pairs if cost[i, j] < GATED]
        key = (-len(kept), sum(cost[i, j] for i, j in kept))
        if best is None or key < best[0]:
            best = (key, sorted(kept))
    return best


def test_assign_is_the_joint_minimum_not_the_greedy_one():
    cost = np.array([[1.0, 2.0], [2.0, 100.0]])
    assert assign(cost) == [(0, 1), (1, 0)]  # greedy would take (0, 0) then (1, 1): 101
    assert assign(np.zeros((0, 3))) == [] and assign(np.zeros((2, 0))) == []
    gated = np.array([[GATED, 1.0], [GATED, 2.0]])
    assert assign(gated) == [(0, 1)]  # track 1's only option is taken, the gated one never
    assert assign(np.full((2, 2), GATED)) == []
    rng = np.random.default_rng(0)
    for _ in range(60):
        T, D = rng.integers(1, 5, 2)
        cost = rng.uniform(0, 16, (T, D))
        cost[rng.random((T, D)) < 0.35] = GATED
        got = assign(cost)
        key, pairs = _brute_force(cost)
        assert sorted(got) == pairs or (
            len(got) == -key[0] and sum(cost[i, j] for i, j in got) == pytest.approx(key[1])
        )
        assert [i for i, _ in got] == sorted(i for i, _ in got)  # in track order
        assert all(isinstance(i, int) and isinstance(j, int) for i, j in got)
