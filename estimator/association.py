"""Data association of one view's detections with the object tracks (paper Section IV).

Per class, every (track, detection) pair gets a cost, or is gated out:

- A track seen in two or more views predicts the detection's center through its Gaussian: the
  cost is the squared Mahalanobis distance ``r^T S^-1 r`` of the innovation, with
  ``S = J P J^T + Sigma_k`` (``J`` the projection Jacobian at the mean), gated at ``gate_chi2``.
- A track seen in one view knows its position only up to the depth along the first viewing ray.
  It gates by the epipolar constraint: the detection must lie near the projection of that ray
  (the segment between ``ray_depth_range`` times the prior depth), measured across the segment
  in standard deviations of both centers. The pair's cost is then the exact increase of the
  track's robust least-squares cost when the detection is added (a two-view Gauss-Newton
  solve), which weighs the triangulated depth against the bbox-size prior and so separates
  same-class parts that lie on one epipolar line.

The assignment is solved jointly with :func:`scipy.optimize.linear_sum_assignment`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from estimator.translation import (
    MIN_DEPTH,
    CenterObservations,
    estimate_translation,
    predict,
    robust_cost,
)

GATED = 1e9  # cost of a pair that may not be assigned


@dataclass(frozen=True)
class AssociationConfig:
    gate_chi2: float = 16.0  # squared Mahalanobis gate of the 2D innovation (p ~ 3e-4)
    epipolar_gate_chi2: float = 16.0  # squared distance across the projected ray, in variances
    ray_depth_range: tuple[float, float] = (0.3, 3.0)  # x prior depth: the ray segment searched
    pair_gate_chi2: float = 25.0  # two-view cost increase (incl. both box-depth terms)

    def __post_init__(self) -> None:
        lo, hi = self.ray_depth_range
        if not (0 < lo < 1 < hi) or min(self.gate_chi2, self.pair_gate_chi2) <= 0:
            raise ValueError(f"invalid association config: {self}")


@dataclass(frozen=True, eq=False)
class TrackView:
    """What association needs of a track.

    t_world_obj: (3,); cov: (3, 3); obs: its center measurements; prior_mean (3,),
    prior_cov (3, 3): the first-view prior; cost: its robust cost at the current estimate.
    """

    t_world_obj: np.ndarray
    cov: np.ndarray
    obs: CenterObservations
    prior_mean: np.ndarray
    prior_cov: np.ndarray
    cost: float


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


def epipolar_chi2(
    track: TrackView,
    T_cam_world: np.ndarray,
    K: np.ndarray,
    uv: np.ndarray,
    cov_uv: np.ndarray,
    depth_range: tuple[float, float],
) -> float:
    """Squared distance, in variances, of ``uv`` to the projection of the track's first ray.

    The ray runs from the first camera through the prior mean, between ``depth_range`` times
    the prior depth; the part behind the new camera is cut off.
    """
    R0, t0 = track.obs.R_cam_world[0], track.obs.t_cam_world[0]
    centre = -R0.T @ t0  # first camera centre in the world
    direction = track.prior_mean - centre
    lo, hi = depth_range
    ends = centre + np.outer([lo, hi], direction)  # (2, 3)
    p = ends @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    if p[0, 2] <= MIN_DEPTH and p[1, 2] <= MIN_DEPTH:
        return np.inf
    # clip the segment to the half-space in front of the new camera
    for a, b in ((0, 1), (1, 0)):
        if p[a, 2] <= MIN_DEPTH:
            s = (MIN_DEPTH - p[a, 2]) / (p[b, 2] - p[a, 2])
            p[a] = p[a] + s * (p[b] - p[a]) + [0, 0, 1e-6]
    q = p[:, :2] / p[:, 2:3] @ K[:2, :2].T + K[:2, 2]  # (2, 2) pixels
    seg = q[1] - q[0]
    length2 = float(seg @ seg)
    s_raw = 0.0 if length2 < 1e-12 else float((uv - q[0]) @ seg / length2)
    s = min(max(s_raw, 0.0), 1.0)
    d = uv - (q[0] + s * seg)
    cov_first = np.linalg.inv(track.obs.info[0])  # first view's center noise (approx. scale)
    if length2 < 1e-12 or s != s_raw:
        # beyond an end of the segment, or the new camera looks along the ray (the same pose
        # again): the full 2D distance to the nearest point
        return float(d @ np.linalg.solve(cov_uv + cov_first, d))
    normal = np.array([-seg[1], seg[0]]) / np.sqrt(length2)
    var = float(normal @ (cov_uv + cov_first) @ normal)
    return float(d @ normal) ** 2 / var


def pair_cost(
    track: TrackView,
    T_cam_world: np.ndarray,
    K: np.ndarray,
    uv: np.ndarray,
    cov_uv: np.ndarray,
    box_depth: float | None = None,
    box_depth_rel_sigma: float = 0.5,
) -> float:
    """Increase of the track's robust cost when the detection is added (two-view solve).

    With ``box_depth`` (the depth the detection's box size suggests, metres) the triangulated
    depth in the new camera must also agree with it, to ``box_depth_rel_sigma``: two rays of
    different parts can meet, but rarely at the depths both boxes suggest.
    """
    obs = track.obs.append(T_cam_world, K, uv, cov_uv, 0)
    est = estimate_translation(obs, track.prior_mean, track.prior_cov, start=track.t_world_obj)
    cost = robust_cost(est.t_world_obj, obs, track.prior_mean, track.prior_cov) - track.cost
    if box_depth is not None:
        z = T_cam_world[2, :3] @ est.t_world_obj + T_cam_world[2, 3]
        cost += ((z - box_depth) / (box_depth_rel_sigma * box_depth)) ** 2
    return float(cost)


def cost_matrix(
    tracks: list[TrackView],
    T_cam_world: np.ndarray,
    K: np.ndarray,
    centers: np.ndarray,
    covs: np.ndarray,
    config: AssociationConfig,
    box_depths: np.ndarray | None = None,
) -> np.ndarray:
    """(T, D) costs of one class's tracks against its detections; GATED where gated out.

    centers: (D, 2) undistorted pixels; covs: (D, 2, 2); box_depths: (D,) metres, the depth
    each detection's box size suggests (used for one-view tracks), or None.
    """
    cost = np.full((len(tracks), len(centers)), GATED)
    for i, track in enumerate(tracks):
        for j, (uv, cov_uv) in enumerate(zip(centers, covs, strict=True)):
            if len(track.obs) >= 2:
                c = innovation_cost(track, T_cam_world, K, uv, cov_uv)
                if c <= config.gate_chi2:
                    cost[i, j] = c
            else:
                e = epipolar_chi2(track, T_cam_world, K, uv, cov_uv, config.ray_depth_range)
                if e <= config.epipolar_gate_chi2:
                    hint = None if box_depths is None else float(box_depths[j])
                    c = pair_cost(track, T_cam_world, K, uv, cov_uv, hint)
                    if c <= config.pair_gate_chi2:
                        cost[i, j] = c
    return cost


def assign(cost: np.ndarray) -> list[tuple[int, int]]:
    """The minimum-cost one-to-one assignment among ungated pairs, as (track, detection) pairs
    in track order."""
    if cost.size == 0:
        return []
    rows, cols = linear_sum_assignment(cost)
    return [(int(i), int(j)) for i, j in zip(rows, cols, strict=True) if cost[i, j] < GATED]
