"""Refinement of a track's full pose over all its views at once (D2CO, Imperoli & Pretto 2015).

Starting from the verified hypothesis (:mod:`estimator.verification`), the pose
``(R_world_obj, t_world_obj)`` is refined by Levenberg-Marquardt on the directional chamfer of
the model's projected edges in every kept view, plus the chamfer of its occluding contour to the
front end's mask boundary (:mod:`estimator.edges`). The cameras are known. Residuals are the
distances read from the maps (RoI pixels), with Huber weights; samples at the truncation (no
edge near: occluded, or clutter-free background) carry no gradient and leave the fit. The
translation Gaussian of the track is a prior, and the leading mixture component's covariance a
prior on the rotation, so a direction the edges do not constrain (the axis of a screw) stays
where the mixture put it, with the mixture's uncertainty.

Perturbations: ``t <- t + dt``, ``R <- exp(dphi) R`` (a left perturbation in the world frame),
so the 6x6 covariance, the inverse of the Gauss-Newton information at the solution, is in the
order x, y, z, rot_x, rot_y, rot_z the daemon publishes. Each view counts at most
``points_per_view`` samples' worth of information (neighbouring samples of one edge are not
independent measurements).

The refinement is local: it starts from one hypothesis and keeps to its basin, so symmetric
equivalents stay apart as in the mixture. A result that moved farther than ``accept_deg`` /
``accept_frac`` of the diameter from its start, or did not lower the cost, is not accepted.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from posefuse.estimator.edges import EdgeView, ModelEdges, pose_edges, project_edges, sample_maps
from posefuse.estimator.geometry import hat, project_jacobian, rotation_angle, so3_exp, so3_log

__all__ = ["RefineConfig", "Refinement", "refine_pose"]


@dataclass(frozen=True)
class RefineConfig:
    # off by default: from a 10 degree error it does not converge yet (tests/test_verification)
    enabled: bool = False
    iterations: int = 8
    sigma_px: float = 1.5  # std of one edge sample's distance, RoI pixels
    huber_px: float = 2.0
    points_per_view: float = 40.0  # at most this many samples' information per view
    rotation_floor_deg: float = 3.0  # the rotation prior's std is at least this
    accept_deg: float = 15.0
    accept_frac: float = 0.1  # of the diameter
    damping: float = 1e-3


@dataclass(frozen=True, eq=False)
class Refinement:
    """R_world_obj: (3, 3); t_world_obj: (3,) metres; cov: (6, 6) over (t, rotation) as in the
    module docstring; cost_start / cost: the objective before and after; accepted: False when
    the result was refused (then R, t are the start and cov the priors')."""

    R_world_obj: np.ndarray
    t_world_obj: np.ndarray
    cov: np.ndarray
    cost_start: float
    cost: float
    iterations: int
    accepted: bool


def _robust(d: np.ndarray, k: float) -> tuple[np.ndarray, np.ndarray]:
    """Huber's rho(d) (as a squared residual) and its IRLS weight."""
    rho = np.where(d <= k, d * d, 2 * k * d - k * k)
    w = np.where(d <= k, 1.0, k / np.maximum(d, 1e-12))
    return rho, w


def _linearize(
    edges: ModelEdges,
    views: list[EdgeView],
    R: np.ndarray,
    t: np.ndarray,
    truncate: float,
    bins: int,
    crease_weight: float,
    mask_weight: float,
    config: RefineConfig,
    want_jacobian: bool = True,
    sets: list[tuple[np.ndarray, np.ndarray]] | None = None,
) -> tuple[float, np.ndarray, np.ndarray, list[tuple[np.ndarray, np.ndarray]]]:
    """The data term's cost, information H (6, 6) and gradient g (6,) at (R, t), and per view
    the (contour, crease) samples used. Given ``sets``, those samples are used instead of the
    ones showing at (R, t): within one step the objective then compares like with like."""
    H = np.zeros((6, 6))
    g = np.zeros(6)
    cost = 0.0
    used = []
    for k, view in enumerate(views):
        R_cw, t_cw = view.T_cam_world[:3, :3], view.T_cam_world[:3, 3]
        R_cam = (R_cw @ R)[None]
        t_cam = (R_cw @ t + t_cw)[None]
        if sets is None:
            points, directions, active, contour = pose_edges(edges, R_cam, t_cam)
            on_contour, crease = contour[0], active[0] & ~contour[0]
        else:
            on_contour, crease = sets[k]
            points, directions = edges.points[None], edges.directions[None]
        used.append((on_contour, crease))
        uv, angle, pts_cam = project_edges(points, directions, R_cam, t_cam, view.K_roi)
        Rp = points[0] @ R.T  # (Q, 3) the samples relative to the origin, world frame
        terms = [(view.dcdt, on_contour, 1.0), (view.dcdt, crease, crease_weight)]
        if view.mask_dt is not None and mask_weight > 0:
            terms.append((view.mask_dt, on_contour, mask_weight))
        b = np.floor(angle[0] / (np.pi / bins) + 0.5).astype(np.intp) % bins
        for maps, use, weight in terms:
            n = int(use.sum())
            if n == 0:
                continue
            d, grad = sample_maps(maps, b if maps.ndim == 3 else None, uv[0], truncate)
            d, grad = d[use], grad[use]
            scale = weight * min(1.0, config.points_per_view / n) / config.sigma_px**2
            rho, w = _robust(np.minimum(d, truncate), config.huber_px)
            cost += scale * float(rho.sum())
            if not want_jacobian:
                continue
            live = d < truncate * 0.999
            if not live.any():
                continue
            J_uv = project_jacobian(pts_cam[0][use][live], view.K_roi)  # (n, 2, 3)
            dp = np.concatenate(
                [np.broadcast_to(R_cw, (int(live.sum()), 3, 3)), -R_cw @ hat(Rp[use][live])],
                axis=2,
            )  # (n, 3, 6): d p_cam / d (dt, dphi)
            J = np.einsum("ni,nij,njk->nk", grad[live], J_uv, dp)  # (n, 6)
            wl = w[live] * scale
            H += np.einsum("n,ni,nj->ij", wl, J, J)
            g += np.einsum("n,n,ni->i", wl, d[live], J)
    return cost, H, g, used


def refine_pose(
    edges: ModelEdges,
    views: list[EdgeView],
    R_start: np.ndarray,
    t_start: np.ndarray,
    t_prior: np.ndarray,
    cov_t_prior: np.ndarray,
    cov_R_prior: np.ndarray,
    truncate_px: float,
    bins: int,
    crease_weight: float,
    mask_weight: float,
    config: RefineConfig,
) -> Refinement:
    """Levenberg-Marquardt on the chamfer over all views, with the priors of the module
    docstring.

    Args:
        R_start: (3, 3) R_world_obj; t_start, t_prior: (3,) metres; cov_t_prior: (3, 3) m^2;
        cov_R_prior: (3, 3) rad^2 (left perturbation, world frame), floored at
        ``rotation_floor_deg``; truncate_px, bins, crease_weight, mask_weight: as the views
        were built and are scored (:class:`estimator.edges.EdgeConfig`,
        :class:`estimator.verification.VerificationConfig`).
    """
    floor = np.deg2rad(config.rotation_floor_deg) ** 2
    w_eig, V = np.linalg.eigh(0.5 * (cov_R_prior + cov_R_prior.T))
    info_R = V @ np.diag(1.0 / np.maximum(w_eig, floor)) @ V.T
    info_t = np.linalg.inv(cov_t_prior)

    def objective(R, t, sets=None):
        cost, H, g, used = _linearize(
            edges, views, R, t, truncate_px, bins, crease_weight, mask_weight, config, True, sets
        )
        r_t = t - t_prior
        r_R = so3_log(R @ R_start.T)
        cost += float(r_t @ info_t @ r_t + r_R @ info_R @ r_R)
        H[:3, :3] += info_t
        H[3:, 3:] += info_R
        g[:3] += info_t @ r_t
        g[3:] += info_R @ r_R
        return cost, H, g, used

    R, t = R_start.copy(), np.asarray(t_start, float).copy()
    cost, H, g, sets = objective(R, t)
    cost_start = cost
    lam = config.damping
    it = 0  # the iterations run, reported in the result
    for it in range(1, config.iterations + 1):  # noqa: B007 (read after the loop)
        A = H + lam * np.diag(np.diag(H))
        delta = -np.linalg.solve(A, g)
        R_new, t_new = so3_exp(delta[3:]) @ R, t + delta[:3]
        # the step is judged on the samples it was computed from, then the set is renewed
        cost_same, *_ = objective(R_new, t_new, sets)
        if cost_same < cost:
            R, t = R_new, t_new
            cost, H, g, sets = objective(R, t)
            lam = max(lam / 3, 1e-7)
            if np.linalg.norm(delta[3:]) < 1e-5 and np.linalg.norm(delta[:3]) < 1e-6:
                break
        else:
            lam *= 5
            if lam > 1e4:
                break
    U, _, Vt = np.linalg.svd(R)
    R = U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt
    moved_deg = float(np.rad2deg(rotation_angle(R @ R_start.T)))
    moved_t = float(np.linalg.norm(t - t_start))
    accepted = (
        cost < cost_start
        and moved_deg <= config.accept_deg
        and moved_t <= config.accept_frac * edges.diameter
    )
    cov = np.linalg.inv(0.5 * (H + H.T))
    if not accepted:
        R, t, cost = R_start.copy(), np.asarray(t_start, float).copy(), cost_start
        cov = np.zeros((6, 6))
        cov[:3, :3] = cov_t_prior
        cov[3:, 3:] = cov_R_prior
    return Refinement(R, t, 0.5 * (cov + cov.T), cost_start, cost, it, accepted)
