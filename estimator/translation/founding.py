"""Founding tracks: detections that fit no track are held, and paired across views.

A learned front end's box is a poor depth cue: the voted mask of an occluded or fragmented part
is small, so the depth where the model would fill the box (SSD-6D) is often wrong by a factor
of two. A track founded from one view inherits that error. Instead, a detection that no track
explains is *held* with its view for up to ``hold_views`` views. Each view's unexplained
detections are paired with the held detections of their class from earlier views: the two rays
are triangulated (:func:`triangulate_pair`), and a pair founds a track when

- the rays meet: the two-view least-squares residual (1 degree of freedom) is within
  ``pair_gate_chi2`` of the centers' covariances;
- the point lies in front of both cameras, with at least ``min_parallax_deg`` between the rays;
- neither box contradicts the triangulated depth by more than ``box_depth_factor`` (a loose
  check: it separates parts of one class that lie on one epipolar line, but never sets a depth).

Triangulating every (held, new) pair was the estimator's largest cost in a pile (30 parts of
a few classes: a hundred pairs a view, 106 of 205 ms a frame in ``python -m
bench.profile_frame``), so every pair is first tested against a lower bound of its residual
(:func:`pair_residual_lower_bounds`, all pairs in a few array operations); a pair whose bound
exceeds the gate would fail it anyway and is not triangulated.

The pairs are chosen jointly (:func:`scipy.optimize.linear_sum_assignment` on the pair costs,
which add a weak box term to the residual). Two views of a camera that does not move give no
parallax; such a pair (the same pixel twice) founds a track from the box depth, as a single
fixed camera can do no better.

Pure functions on the held detections; the tracker owns the state.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from posefuse.estimator.translation.gaussian import (
    MIN_DEPTH,
    CenterObservations,
    estimate_translation,
)

GATED = 1e9


@dataclass(frozen=True)
class FoundingConfig:
    hold_views: int = 4  # a held detection waits this many later views for a partner
    pair_gate_chi2: float = 16.0  # two-view residual (1 dof) of a founding pair
    min_parallax_deg: float = 1.0  # below this the pair is 'static' (no triangulation)
    box_depth_factor: float = 2.5  # triangulated depth within [1/f, f] x each box's depth
    box_depth_log_sigma: float = 0.7  # weak box term of the pair cost: log-depth std
    prior_rel_sigma: float = 1.0  # founded track's prior: isotropic, this x the depth
    static_gate_chi2: float = 16.0  # a static pair: the two centers agree to this

    def __post_init__(self) -> None:
        if self.hold_views < 1 or self.box_depth_factor <= 1 or self.pair_gate_chi2 <= 0:
            raise ValueError(f"invalid founding config: {self}")


@dataclass(frozen=True, eq=False)
class HeldDetection:
    """A detection no track explained, with its view.

    T_cam_world: (4, 4); K: (3, 3); uv: (2,) undistorted pixels; cov: (2, 2) px^2;
    box_depth: metres, the depth the box suggests (NaN when the box is truncated by the image
    border); index: the detection's index in its view;
    mask: (H, W) bool or None (for the rotation step once a track is founded); silhouette:
    whether the mask follows the part's outline (a filled box does not: see
    :class:`~estimator.frontend.detection.Detection`'s ``mask_kind``).
    """

    obj_id: int
    stamp_ns: int
    view_serial: int  # the estimator's count of views when it was held
    T_cam_world: np.ndarray
    K: np.ndarray
    uv: np.ndarray
    cov: np.ndarray
    box_depth: float
    index: int
    mask: np.ndarray | None = None
    silhouette: bool = True  # a state saved before the field existed reads this default


@dataclass(frozen=True, eq=False)
class FoundingPair:
    """A pair that founds a track: ``older`` and ``newer`` held detections, the prior of the
    new track (mean (3,), cov (3, 3)) and whether the pair was static (box depth)."""

    older: HeldDetection
    newer: HeldDetection
    prior_mean: np.ndarray
    prior_cov: np.ndarray
    static: bool
    cost: float


def _ray(h: HeldDetection) -> tuple[np.ndarray, np.ndarray]:
    """Camera centre (3,) and unit direction (3,) of a held detection's center, world frame."""
    R, t = h.T_cam_world[:3, :3], h.T_cam_world[:3, 3]
    d = R.T @ np.linalg.solve(h.K, np.array([h.uv[0], h.uv[1], 1.0]))
    return -R.T @ t, d / np.linalg.norm(d)


def midpoint(c1, d1, c2, d2) -> tuple[np.ndarray, float, float]:
    """Midpoint of the closest approach of two rays; the distances along each (may be < 0)."""
    w = c1 - c2
    b = d1 @ d2
    denom = 1.0 - b * b
    if denom < 1e-12:
        return 0.5 * (c1 + c2), np.nan, np.nan
    s1 = (b * (d2 @ w) - (d1 @ w)) / denom
    s2 = ((d2 @ w) - b * (d1 @ w)) / denom
    return 0.5 * (c1 + s1 * d1 + c2 + s2 * d2), float(s1), float(s2)


def pair_observations(a: HeldDetection, b: HeldDetection) -> CenterObservations:
    """The two detections' centers as a track's observations, ``a`` first."""
    return (
        CenterObservations.empty()
        .append(a.T_cam_world, a.K, a.uv, a.cov, a.stamp_ns)
        .append(b.T_cam_world, b.K, b.uv, b.cov, b.stamp_ns)
    )


def box_prior(h: HeldDetection, rel_sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """The one-view prior: the center back-projected at the box depth, isotropic std
    ``rel_sigma`` x depth."""
    c, d = _ray(h)
    z_dir = h.T_cam_world[2, :3] @ d  # depth per unit length along the ray
    point = c + d * (h.box_depth / max(z_dir, 1e-9))
    return point, np.eye(3) * (rel_sigma * h.box_depth) ** 2


def _bound_terms(held: list[HeldDetection], config: FoundingConfig) -> dict[str, np.ndarray]:
    """Per held detection, what :func:`pair_residual_lower_bounds` needs: camera centre ``c``
    (n, 3), unit ray ``d`` (n, 3), ``k`` (n,) with chi2 >= k * sin^2(angle off the ray) for any
    point in front of the camera, and ``D`` (n,), the largest distance from the camera of a
    point that passes both the residual gate and the box-depth check (NaN: the box is
    truncated and gives no bound).

    The bound: the pixel residual r = A dx (A = K[:2, :2], dx the difference of normalised
    image coordinates); chi2 = r^T cov^-1 r >= s_min(A)^2 |dx|^2 / l_max(cov); |dx| >= the chord
    between the two unit rays (radial projection onto the unit ball does not expand distances)
    = 2 sin(angle / 2) >= sin(angle). A point within the gate projects within
    sqrt(gate * l_max(cov)) / s_min(A) of the center in normalised coordinates, which bounds its
    distance per unit depth; its depth is at most ``box_depth_factor`` x the box depth.
    """
    K = np.array([h.K for h in held])  # (n, 3, 3)
    cov = np.array([h.cov for h in held])  # (n, 2, 2)
    R = np.array([h.T_cam_world[:3, :3] for h in held])
    t = np.array([h.T_cam_world[:3, 3] for h in held])
    uv1 = np.array([[h.uv[0], h.uv[1], 1.0] for h in held])
    x = np.linalg.solve(K, uv1[..., None])[..., 0]  # (n, 3) normalised, z = 1
    d = np.einsum("nji,nj->ni", R, x)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    c = -np.einsum("nji,nj->ni", R, t)
    s_min = np.linalg.svd(K[:, :2, :2], compute_uv=False)[:, -1]
    l_max = np.linalg.eigvalsh(cov)[:, -1]
    radius = np.linalg.norm(x[:, :2], axis=1) + np.sqrt(config.pair_gate_chi2 * l_max) / s_min
    box = np.array([h.box_depth for h in held])
    D = config.box_depth_factor * box * np.sqrt(1.0 + radius**2)
    return {"c": c, "d": d, "k": s_min**2 / l_max, "D": D}


def pair_residual_lower_bounds(
    older: list[HeldDetection], newer: list[HeldDetection], config: FoundingConfig
) -> np.ndarray:
    """(len(older), len(newer)) lower bounds of the two-view residual of any point that would
    pass the box-depth check of both detections (0 where a box gives no bound, and for static
    pairs, which are checked without triangulation); see :func:`_bound_terms`.

    For any point t: d(t, ray_a) + d(t, ray_b) >= g, the distance between the two lines, and
    chi2_v >= k_v d(t, ray_v)^2 / |t - c_v|^2 with |t - c_v| <= D_v; the minimum of
    k_a x^2 / D_a^2 + k_b y^2 / D_b^2 over x + y >= g is g^2 / (D_a^2 / k_a + D_b^2 / k_b).
    """
    a, b = _bound_terms(older, config), _bound_terms(newer, config)
    w = b["c"][None] - a["c"][:, None]  # (A, B, 3)
    n = np.cross(a["d"][:, None], b["d"][None])
    norm = np.linalg.norm(n, axis=2)
    along = w - np.einsum("abi,ai->ab", w, a["d"])[..., None] * a["d"][:, None]
    gap = np.where(
        norm > 1e-9,
        np.abs(np.einsum("abi,abi->ab", w, n)) / np.maximum(norm, 1e-300),
        np.linalg.norm(along, axis=2),  # parallel lines: a centre's distance to the other
    )
    spread = a["D"][:, None] ** 2 / a["k"][:, None] + b["D"][None] ** 2 / b["k"][None]
    bound = gap**2 / spread
    static = a["d"] @ b["d"].T > np.cos(np.deg2rad(config.min_parallax_deg))
    return np.where(static | ~np.isfinite(bound), 0.0, bound)


def triangulate_pair(
    a: HeldDetection, b: HeldDetection, config: FoundingConfig
) -> FoundingPair | None:
    """The founding pair of two detections of one class from different views, or None when
    gated out (see the module docstring)."""
    ca, da = _ray(a)
    cb, db = _ray(b)
    parallax = np.degrees(np.arccos(np.clip(da @ db, -1.0, 1.0)))
    if parallax < config.min_parallax_deg:
        if not np.isfinite(b.box_depth):
            return None
        # no triangulation: the same pixel again founds a track at the newer box's depth
        r = a.uv - b.uv
        chi2 = float(r @ np.linalg.solve(a.cov + b.cov, r))
        if np.linalg.norm(ca - cb) > 0.05 * b.box_depth or chi2 > config.static_gate_chi2:
            return None
        mean, cov = box_prior(b, 0.5)
        return FoundingPair(a, b, mean, cov, True, chi2)
    X, sa, sb = midpoint(ca, da, cb, db)
    if not (np.isfinite(sa) and sa > 0 and sb > 0):
        return None
    depth_b = float(b.T_cam_world[2, :3] @ X + b.T_cam_world[2, 3])
    if not depth_b > MIN_DEPTH:  # rays that meet only at a camera centre found nothing
        return None
    prior_cov = np.eye(3) * (config.prior_rel_sigma * depth_b) ** 2
    obs = pair_observations(a, b)
    est = estimate_translation(obs, X, prior_cov)
    t = est.t_world_obj
    residual = float(np.sum(est.chi2))  # squared Mahalanobis residuals of both centers
    if residual > config.pair_gate_chi2:
        return None
    cost = residual
    for h in (a, b):
        z = float(h.T_cam_world[2, :3] @ t + h.T_cam_world[2, 3])
        if z <= MIN_DEPTH:
            return None
        if not np.isfinite(h.box_depth):  # truncated by the image border: no box check
            continue
        ratio = z / h.box_depth
        if not (1 / config.box_depth_factor <= ratio <= config.box_depth_factor):
            return None
        cost += (np.log(ratio) / config.box_depth_log_sigma) ** 2
    return FoundingPair(a, b, t, prior_cov, False, float(cost))


def choose_pairs(
    held: list[HeldDetection], new: list[HeldDetection], config: FoundingConfig
) -> list[FoundingPair]:
    """Pairs (older held, new) of one class chosen jointly by minimum total cost; each detection
    in at most one pair."""
    if not held or not new:
        return []
    pairs: dict[tuple[int, int], FoundingPair] = {}
    cost = np.full((len(held), len(new)), GATED)
    bounds = pair_residual_lower_bounds(held, new, config)
    for i, a in enumerate(held):
        for j, b in enumerate(new):
            if a.view_serial == b.view_serial or a.obj_id != b.obj_id:
                continue
            if bounds[i, j] > config.pair_gate_chi2:
                continue  # would fail the residual gate or the box check
            pair = triangulate_pair(a, b, config)
            if pair is not None:
                pairs[(i, j)] = pair
                cost[i, j] = pair.cost
    rows, cols = linear_sum_assignment(cost)
    return [pairs[(i, j)] for i, j in zip(rows, cols, strict=True) if cost[i, j] < GATED]
