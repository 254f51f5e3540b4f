"""Data association of one view's detections with the object tracks (paper Section IV).

Per class, every (track, detection) pair gets a cost, or is gated out. A track has two views
or more (it is founded on two: :mod:`estimator.translation.founding`), so it predicts the
detection's center through its Gaussian: the cost is the squared Mahalanobis distance ``r^T S^-1 r``
of the innovation, with ``S = J P J^T + Sigma_k`` (``J`` the projection Jacobian at the mean), gated
at ``gate_chi2``. Detections that fit no track go to founding.

The assignment is solved jointly with :func:`scipy.optimize.linear_sum_assignment`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from posefuse.estimator.translation.gaussian import (
    MIN_DEPTH,
    CenterObservations,
    predict,
)

GATED = 1e9  # cost of a pair that may not be assigned


@dataclass(frozen=True)
class AssociationConfig:
    gate_chi2: float = 16.0  # squared Mahalanobis gate of the 2D innovation (p ~ 3e-4)

    def __post_init__(self) -> None:
        if self.gate_chi2 <= 0:
            raise ValueError(f"invalid association config: {self}")


@dataclass(frozen=True, eq=False)
class TrackView:
    """What association needs of a track.

    t_world_obj: (3,); cov: (3, 3); obs: its center measurements.
    """

    t_world_obj: np.ndarray
    cov: np.ndarray
    obs: CenterObservations


def innovation_cost(
    track: TrackView, T_cam_world: np.ndarray, K: np.ndarray, uv: np.ndarray, cov_uv: np.ndarray
) -> float:
    """Squared Mahalanobis distance of a detection center to the track's predicted center."""
    one = CenterObservations.empty().append(T_cam_world, K, uv, cov_uv, 0)
    pred, J, z = predict(track.t_world_obj, one)
    if z[0] <= MIN_DEPTH:
        return np.inf
    S = J[0] @ track.cov @ J[0].T + cov_uv
    r = pred[0] - uv
    return float(r @ np.linalg.solve(S, r))


def cost_matrix(
    tracks: list[TrackView],
    T_cam_world: np.ndarray,
    K: np.ndarray,
    centers: np.ndarray,
    covs: np.ndarray,
    config: AssociationConfig,
) -> np.ndarray:
    """(T, D) costs of one class's tracks against its detections; GATED where gated out.

    centers: (D, 2) undistorted pixels; covs: (D, 2, 2).
    """
    cost = np.full((len(tracks), len(centers)), GATED)
    for i, track in enumerate(tracks):
        for j, (uv, cov_uv) in enumerate(zip(centers, covs, strict=True)):
            c = innovation_cost(track, T_cam_world, K, uv, cov_uv)
            if c <= config.gate_chi2:
                cost[i, j] = c
    return cost


def assign(cost: np.ndarray) -> list[tuple[int, int]]:
    """The minimum-cost one-to-one assignment among ungated pairs, as (track, detection) pairs
    in track order."""
    if cost.size == 0:
        return []
    rows, cols = linear_sum_assignment(cost)
    return [(int(i), int(j)) for i, j in zip(rows, cols, strict=True) if cost[i, j] < GATED]
