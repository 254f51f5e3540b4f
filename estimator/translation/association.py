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


def _checked_centers(uv: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``uv`` (D, 2) and ``cov`` (D, 2, 2) as float arrays, each covariance finite and positive
    definite (the check :meth:`CenterObservations.append` makes), else ValueError."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    cov = np.asarray(cov, dtype=np.float64).reshape(-1, 2, 2)
    if len(uv) != len(cov):
        raise ValueError(f"centers and covariances differ in length: {len(uv)} and {len(cov)}")
    if not (np.all(np.isfinite(cov)) and np.all(np.isfinite(uv))):
        raise ValueError("center measurement: uv and cov must be finite")
    if len(cov):
        eig = np.linalg.eigvalsh((cov + np.swapaxes(cov, 1, 2)) / 2)  # (D, 2) ascending
        bad = eig[:, 0] <= 1e-9 * np.maximum(1.0, eig[:, 1])
        if np.any(bad):
            raise ValueError(
                f"center measurement: covariance is not positive definite ({eig[bad][0]})"
            )
    return uv, cov


def innovation_costs(
    t_world_obj: np.ndarray,
    cov: np.ndarray,
    T_cam_world: np.ndarray,
    K: np.ndarray,
    uv: np.ndarray,
    cov_uv: np.ndarray,
) -> np.ndarray:
    """Squared Mahalanobis distances of D detection centers to T tracks' predicted centers in
    one camera, all pairs at once: ``r^T S^-1 r`` with ``S = J P J^T + Sigma`` (the 2 x 2
    inverse written out). A track at or behind ``MIN_DEPTH`` costs inf against every center.

    Args:
        t_world_obj: (T, 3) metres. cov: (T, 3, 3) m^2. T_cam_world: (4, 4). K: (3, 3).
        uv: (D, 2) undistorted pixels. cov_uv: (D, 2, 2) px^2, finite and positive definite.
    Returns:
        (T, D).
    """
    uv, cov_uv = _checked_centers(uv, cov_uv)
    t = np.asarray(t_world_obj, dtype=np.float64).reshape(-1, 3)
    P = np.asarray(cov, dtype=np.float64).reshape(-1, 3, 3)
    R, K = T_cam_world[:3, :3], np.asarray(K, dtype=np.float64)
    p = t @ R.T + T_cam_world[:3, 3]  # (T, 3)
    z = p[:, 2]
    zs = np.where(np.abs(z) < 1e-12, 1e-12, z)
    xy = p[:, :2] / zs[:, None]
    pred = xy @ K[:2, :2].T + K[:2, 2]  # (T, 2), as gaussian.predict
    J = K[:2, :2] @ ((R[None, :2, :] - xy[:, :, None] * R[None, 2:3, :]) / zs[:, None, None])
    S = (J @ P @ np.swapaxes(J, 1, 2))[:, None] + cov_uv[None]  # (T, D, 2, 2)
    r = pred[:, None, :] - uv[None]  # (T, D, 2)
    det = S[..., 0, 0] * S[..., 1, 1] - S[..., 0, 1] * S[..., 1, 0]
    quad = (
        S[..., 1, 1] * r[..., 0] ** 2
        - (S[..., 0, 1] + S[..., 1, 0]) * r[..., 0] * r[..., 1]
        + S[..., 0, 0] * r[..., 1] ** 2
    )
    with np.errstate(divide="ignore", invalid="ignore"):
        out = quad / det
    out[z <= MIN_DEPTH] = np.inf
    return out


def innovation_cost(
    track: TrackView, T_cam_world: np.ndarray, K: np.ndarray, uv: np.ndarray, cov_uv: np.ndarray
) -> float:
    """Squared Mahalanobis distance of a detection center to the track's predicted center
    (:func:`innovation_costs` of one pair)."""
    return float(
        innovation_costs(
            track.t_world_obj[None], track.cov[None], T_cam_world, K, uv[None], cov_uv[None]
        )[0, 0]
    )


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
    if len(centers) != len(covs):
        raise ValueError(
            f"centers and covariances differ in length: {len(centers)} and {len(covs)}"
        )
    if not tracks or not len(centers):
        return cost
    c = innovation_costs(
        np.array([t.t_world_obj for t in tracks]),
        np.array([t.cov for t in tracks]),
        T_cam_world,
        K,
        centers,
        covs,
    )
    keep = c <= config.gate_chi2  # NaN and inf never pass
    cost[keep] = c[keep]
    return cost


def assign(cost: np.ndarray) -> list[tuple[int, int]]:
    """The minimum-cost one-to-one assignment among ungated pairs, as (track, detection) pairs
    in track order."""
    if cost.size == 0:
        return []
    rows, cols = linear_sum_assignment(cost)
    return [(int(i), int(j)) for i, j in zip(rows, cols, strict=True) if cost[i, j] < GATED]
