"""The translation step (paper Section IV): an object's position as a Gaussian N(t_world_obj, P).

Every view k gives the projected model origin ``u_k`` with covariance ``Sigma_k`` (undistorted
pixels) and the camera pose. The estimate minimises

    (t - t0)^T P0^-1 (t - t0) + sum_k rho_Huber(r_k^T Sigma_k^-1 r_k),
    r_k = pi(K_k (R_cam_world_k t + t_cam_world_k)) - u_k,

by Gauss-Newton with iteratively reweighted Huber weights, and its covariance is the inverse of
the information ``P0^-1 + sum_k w_k J_k^T Sigma_k^-1 J_k`` at the solution. ``N(t0, P0)`` is the
weak prior of the first view: back-projected through ``u_1`` at the depth where the model
diameter spans the bbox diagonal (as SSD-6D), with a standard deviation of 50% of that depth.
Together with the first center it gives a one-view track an honest covariance: tight across
the ray, long along it. With more views the measurements dominate it.

The arithmetic is written out for the 3-vector problem rather than calling the batched helpers
of :mod:`estimator.core.geometry`: the general functions' validation and broadcasting cost more than
the problem itself (measured: ~1.1 ms versus ~0.1 ms per 8-view update).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

HUBER_K = 2.5  # in standard deviations of the Mahalanobis residual
PRIOR_DEPTH_REL_SIGMA = 0.5
MIN_DEPTH = 0.02  # metres: a point closer to (or behind) a camera gives no information


@dataclass(frozen=True, eq=False)
class CenterObservations:
    """The center measurements of one track, stacked (N views).

    R_cam_world: (N, 3, 3); t_cam_world: (N, 3) metres; K: (N, 3, 3);
    uv: (N, 2) undistorted pixels; info: (N, 2, 2) inverse covariances, px^-2;
    stamp_ns: (N,) int64.
    """

    R_cam_world: np.ndarray
    t_cam_world: np.ndarray
    K: np.ndarray
    uv: np.ndarray
    info: np.ndarray
    stamp_ns: np.ndarray

    @staticmethod
    def empty() -> CenterObservations:
        return CenterObservations(
            np.zeros((0, 3, 3)),
            np.zeros((0, 3)),
            np.zeros((0, 3, 3)),
            np.zeros((0, 2)),
            np.zeros((0, 2, 2)),
            np.zeros(0, np.int64),
        )

    def __len__(self) -> int:
        return len(self.uv)

    def append(
        self,
        T_cam_world: np.ndarray,
        K: np.ndarray,
        uv: np.ndarray,
        cov: np.ndarray,
        stamp_ns: int,
    ) -> CenterObservations:
        """A new set with one more view (the measurement is validated here)."""
        cov = np.asarray(cov, dtype=np.float64).reshape(2, 2)
        uv = np.asarray(uv, dtype=np.float64).reshape(2)
        if not (np.all(np.isfinite(cov)) and np.all(np.isfinite(uv))):
            raise ValueError("center measurement: uv and cov must be finite")
        eig = np.linalg.eigvalsh((cov + cov.T) / 2)
        if eig.min() <= 1e-9 * max(1.0, eig.max()):
            raise ValueError(f"center measurement: covariance is not positive definite ({eig})")
        return CenterObservations(
            np.concatenate([self.R_cam_world, T_cam_world[None, :3, :3]]),
            np.concatenate([self.t_cam_world, T_cam_world[None, :3, 3]]),
            np.concatenate([self.K, np.asarray(K, dtype=np.float64)[None]]),
            np.concatenate([self.uv, uv[None]]),
            np.concatenate([self.info, np.linalg.inv((cov + cov.T) / 2)[None]]),
            np.concatenate([self.stamp_ns, np.array([stamp_ns], np.int64)]),
        )

    def select(self, keep: np.ndarray) -> CenterObservations:
        """The views where ``keep`` ((N,) bool or indices) holds, in order."""
        return CenterObservations(
            self.R_cam_world[keep],
            self.t_cam_world[keep],
            self.K[keep],
            self.uv[keep],
            self.info[keep],
            self.stamp_ns[keep],
        )

    def concat(self, other: CenterObservations) -> CenterObservations:
        """Both sets of views, ordered by stamp (stable)."""
        both = CenterObservations(
            *(
                np.concatenate([getattr(self, f), getattr(other, f)])
                for f in ("R_cam_world", "t_cam_world", "K", "uv", "info", "stamp_ns")
            )
        )
        return both.select(np.argsort(both.stamp_ns, kind="stable"))


@dataclass(frozen=True, eq=False)
class TranslationEstimate:
    """t_world_obj: (3,) metres; cov: (3, 3) m^2; n_views: views used; weights: (N,) Huber
    weights of the views at the solution (1 = inlier); chi2: (N,) squared Mahalanobis
    residuals at the solution; cost: the robust cost (prior included) at the solution."""

    t_world_obj: np.ndarray
    cov: np.ndarray
    n_views: int
    weights: np.ndarray
    chi2: np.ndarray
    cost: float


def predict(
    t_world_obj: np.ndarray, obs: CenterObservations
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Projected centers, their Jacobians and depths for every view of ``obs``.

    Returns:
        uv: (N, 2) pixels; J: (N, 2, 3) d uv / d t_world_obj; z: (N,) depth in each camera.
    """
    R = obs.R_cam_world
    p = R @ t_world_obj + obs.t_cam_world  # (N, 3)
    z = p[:, 2]
    zs = np.where(np.abs(z) < 1e-12, 1e-12, z)
    xy = p[:, :2] / zs[:, None]  # (N, 2)
    K = obs.K
    x, y = xy[:, 0], xy[:, 1]
    uv = np.stack([K[:, 0, 0] * x + K[:, 0, 1] * y + K[:, 0, 2], K[:, 1, 1] * y + K[:, 1, 2]], 1)
    # d(x, y)/dp = [[1/z, 0, -x/z], [0, 1/z, -y/z]], so d(x, y)/dt = (R[:2] - (x, y) R[2]) / z;
    # duv/d(x, y) = K[:2, :2]
    dxy_dt = (R[:, :2, :] - xy[:, :, None] * R[:, 2:3, :]) / zs[:, None, None]  # (N, 2, 3)
    J = K[:, :2, :2] @ dxy_dt
    return uv, J, z


def bbox_diagonal_ratio(points: np.ndarray, diameter: float, n: int = 256, seed: int = 0) -> float:
    """Median over random orientations of (bbox diagonal of the projected points) / diameter.

    A part's box is smaller than its diameter (a screw seen end-on much smaller); dividing by
    this ratio removes the average bias of the SSD-6D depth. Orthographic projection.

    Args:
        points: (N, 3) model surface points, metres. diameter: metres.
    """
    from scipy.spatial.transform import Rotation

    R = Rotation.random(n, random_state=seed).as_matrix()  # (n, 3, 3)
    xy = np.einsum("kij,nj->kni", R[:, :2, :], points)  # (n, N, 2)
    extent = xy.max(axis=1) - xy.min(axis=1)
    return float(np.median(np.hypot(extent[:, 0], extent[:, 1])) / diameter)


def prior_from_first_view(
    T_world_cam: np.ndarray,
    K: np.ndarray,
    uv: np.ndarray,
    bbox_diagonal: float,
    diameter: float,
    depth_rel_sigma: float = PRIOR_DEPTH_REL_SIGMA,
    size_ratio: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """The weak first-view prior N(t0, P0) in the world frame.

    Depth z = f * size_ratio * diameter / bbox_diagonal (``size_ratio`` from
    :func:`bbox_diagonal_ratio`, 1 for the plain SSD-6D rule); t0 is ``uv`` back-projected at
    z; P0 is isotropic with standard deviation ``depth_rel_sigma * z``. It constrains only what
    the first view's center cannot, the depth: the lateral position comes from that center
    itself, which is one of the track's measurements (a prior tight across the ray would count
    it twice).

    Returns:
        t0: (3,) metres; P0: (3, 3) m^2.
    """
    if not (bbox_diagonal > 0 and np.isfinite(bbox_diagonal)):
        raise ValueError(f"bbox diagonal must be positive, got {bbox_diagonal}")
    if not (diameter > 0 and np.isfinite(diameter)):
        raise ValueError(f"diameter must be positive, got {diameter}")
    K = np.asarray(K, dtype=np.float64)
    f = 0.5 * (K[0, 0] + K[1, 1])
    z = f * size_ratio * diameter / bbox_diagonal
    p_cam = np.linalg.solve(K, np.array([uv[0], uv[1], 1.0])) * z
    R = T_world_cam[:3, :3]
    return R @ p_cam + T_world_cam[:3, 3], np.eye(3) * (depth_rel_sigma * z) ** 2


def robust_cost(
    t_world_obj: np.ndarray,
    obs: CenterObservations,
    prior_mean: np.ndarray,
    prior_cov: np.ndarray,
    huber_k: float = HUBER_K,
) -> float:
    """The objective: prior term plus the Huber-robustified squared Mahalanobis residuals."""
    return _cost(t_world_obj, obs, prior_mean, np.linalg.inv(prior_cov), huber_k)[0]


def _cost(t, obs, prior_mean, prior_info, huber_k):
    uv, J, z = predict(t, obs)
    r = uv - obs.uv
    s = np.einsum("ni,nij,nj->n", r, obs.info, r)
    valid = z > MIN_DEPTH
    root = np.sqrt(s)
    rho = np.where(root <= huber_k, s, 2 * huber_k * root - huber_k**2)
    d = t - prior_mean
    return float(d @ prior_info @ d + rho[valid].sum() + 1e6 * np.count_nonzero(~valid)), r, J, z, s


def estimate_translation(
    obs: CenterObservations,
    prior_mean: np.ndarray,
    prior_cov: np.ndarray,
    start: np.ndarray | None = None,
    huber_k: float = HUBER_K,
    max_iterations: int = 15,
    tolerance: float = 1e-6,
    variance_prior_dof: float | None = None,
    shared_std: float = 0.0,
) -> TranslationEstimate:
    """Robust Gauss-Newton for the translation from all views of a track.

    Args:
        obs: the track's center measurements (N >= 1 views).
        prior_mean, prior_cov: (3,), (3, 3) the first-view prior.
        start: (3,) initial guess (the previous estimate); defaults to the prior mean.
        tolerance: stop when the step is below this many metres.
        variance_prior_dof: None, the covariance is the inverse information alone; else it is
            multiplied by :func:`variance_factor` of the centres' scatter with this prior.
        shared_std: metres, >= 0: the standard deviation per axis of the error the views share
            (a bias of the front end's centres, alike in neighbouring views, which more views do
            not average out and their scatter does not show); its variance is added to the
            covariance. The solution itself does not depend on it.
    """
    if not shared_std >= 0:
        raise ValueError(f"shared_std must be at least 0, got {shared_std}")
    prior_info = np.linalg.inv(prior_cov)
    t = np.array(prior_mean if start is None else start, dtype=np.float64)
    cost, r, J, z, s = _cost(t, obs, prior_mean, prior_info, huber_k)
    for _ in range(max_iterations):
        w = _huber_weights(s, huber_k) * (z > MIN_DEPTH)
        WJ = w[:, None, None] * (obs.info @ J)  # (N, 2, 3)
        H = prior_info + (J.transpose(0, 2, 1) @ WJ).sum(0)
        g = prior_info @ (t - prior_mean) + (r[:, None, :] @ WJ).sum(0)[0]
        step = -np.linalg.solve(H, g)
        for _ in range(8):  # backtrack if the step overshoots (far from the solution)
            cand = t + step
            cand_cost, cr, cJ, cz, cs = _cost(cand, obs, prior_mean, prior_info, huber_k)
            if cand_cost <= cost * (1 + 1e-12):
                break
            step = step / 2
        else:
            break
        t, cost, r, J, z, s = cand, cand_cost, cr, cJ, cz, cs
        if np.linalg.norm(step) < tolerance:
            break
    w = _huber_weights(s, huber_k) * (z > MIN_DEPTH)
    H = prior_info + (J.transpose(0, 2, 1) @ (w[:, None, None] * (obs.info @ J))).sum(0)
    cov = np.linalg.inv(H)
    if variance_prior_dof is not None:
        cov = cov * variance_factor(w, s, variance_prior_dof)
    cov = 0.5 * (cov + cov.T) + np.eye(3) * shared_std**2
    return TranslationEstimate(t, cov, len(obs), w, s, cost)


def variance_factor(weights: np.ndarray, chi2: np.ndarray, prior_dof: float) -> float:
    """How much wider the centres scatter about the solution than their covariances say: the a
    posteriori variance factor of the weighted least squares, ``sum_k w_k s_k / (2N - 3)``,
    shrunk towards 1 as if ``prior_dof`` more degrees of freedom had scattered as expected, and
    never below 1 (the centres' covariances are calibrated; scatter can only say they are not
    for this track, as when its views hold detections of two parts).

    Args:
        weights: (N,) the views' Huber weights at the solution (0 for a view behind a camera).
        chi2: (N,) their squared Mahalanobis residuals.
        prior_dof: >= 0; 0 takes the scatter as it is, more trusts it less.
    Returns:
        the factor (>= 1) the covariance is multiplied by; 1 with fewer than two views.
    """
    if prior_dof < 0:
        raise ValueError(f"prior_dof must be at least 0, got {prior_dof}")
    used = weights > 0
    dof = 2 * int(np.count_nonzero(used)) - 3
    if dof < 1:
        return 1.0
    scatter = float(np.sum(weights[used] * chi2[used]))
    return max(1.0, (scatter + prior_dof) / (dof + prior_dof))


def _huber_weights(s: np.ndarray, k: float) -> np.ndarray:
    """IRLS weights of the Huber loss on squared Mahalanobis residuals ``s``."""
    root = np.sqrt(np.maximum(s, 0.0))
    return np.where(root <= k, 1.0, k / np.maximum(root, 1e-300))


def marginalize_oldest(
    obs: CenterObservations,
    prior_mean: np.ndarray,
    prior_cov: np.ndarray,
    t_hat: np.ndarray,
    huber_k: float = HUBER_K,
) -> tuple[CenterObservations, np.ndarray, np.ndarray]:
    """Fold the oldest view into the prior, linearised at ``t_hat``, and drop it.

    Keeps a long-lived track's cost bounded: the prior becomes the Gaussian that reproduces
    the quadratic (t - m)^T P^-1 (t - m) + w (J (t - t_hat) + r)^T Sigma^-1 (J (t - t_hat) + r)
    of the old prior and the dropped view.

    Returns:
        the observations without the oldest, the new prior mean (3,) and covariance (3, 3).
    """
    first = CenterObservations(
        obs.R_cam_world[:1],
        obs.t_cam_world[:1],
        obs.K[:1],
        obs.uv[:1],
        obs.info[:1],
        obs.stamp_ns[:1],
    )
    uv, J, z = predict(t_hat, first)
    r = uv[0] - first.uv[0]
    W = first.info[0]
    if z[0] > MIN_DEPTH:
        W = W * _huber_weights(np.array([r @ W @ r]), huber_k)[0]
    else:
        W = W * 0.0
    A = np.linalg.inv(prior_cov)
    A_new = A + J[0].T @ W @ J[0]
    b = A @ prior_mean + J[0].T @ W @ (J[0] @ t_hat - r)
    mean = np.linalg.solve(A_new, b)
    cov = np.linalg.inv(A_new)
    rest = CenterObservations(
        obs.R_cam_world[1:],
        obs.t_cam_world[1:],
        obs.K[1:],
        obs.uv[1:],
        obs.info[1:],
        obs.stamp_ns[1:],
    )
    return rest, mean, 0.5 * (cov + cov.T)
