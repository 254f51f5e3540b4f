"""Multi-instance RANSAC voting for object centers from a unit-vector field (as PVNet).

Per class, every pixel labelled with it carries a unit vector towards its instance's center.
Hypotheses are intersections of the vector lines of random pixel pairs; a pixel votes for a
hypothesis when its vector points at it within ``inlier_cos``. The best-supported hypothesis
makes an instance; its inliers are removed and the search repeats until no hypothesis has
``min_inliers`` votes. Each instance's center is the least-squares intersection of its inlier
lines, with the covariance of that estimate (the residual variance times the inverse normal
matrix) multiplied by ``cov_scale``: neighbouring pixels' vectors are not independent, and the
factor is calibrated on held-out renders when the network is trained (see its model card).

All randomness comes from the ``seed`` argument.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class VotingConfig:
    n_hypotheses: int = 64
    inlier_cos: float = 0.99  # about 8 degrees
    min_inliers: int = 25  # pixels at the network's output resolution
    max_instances: int = 30  # per class
    cov_scale: float = 1.0
    min_center_var: float = 0.05  # output px^2: a floor for a perfectly consistent field
    max_scoring_pixels: int = 400  # hypotheses are scored on a random subset of this size
    member_cos: float = 0.9  # looser: the pixels that make the instance's mask (about 25 deg)
    member_radius_factor: float = 1.3  # x the 90th percentile of the inliers' distances


@dataclass(frozen=True, eq=False)
class VotedInstance:
    """center: (2,) output-grid pixels (x, y); cov: (2, 2); pixels: (n,) flat indices of its
    inlier pixels; n_votes: inlier count."""

    center: np.ndarray
    cov: np.ndarray
    pixels: np.ndarray
    n_votes: int


def _intersections(p: np.ndarray, v: np.ndarray, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """(K, 2) intersections of the lines (p_i, v_i) and (p_j, v_j); NaN where parallel."""
    a, b = v[i], -v[j]
    det = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    d = p[j] - p[i]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (d[:, 0] * b[:, 1] - d[:, 1] * b[:, 0]) / det
    s[np.abs(det) < 1e-3] = np.nan
    return p[i] + s[:, None] * a


def _least_squares_center(p: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Point closest to all lines (p_k, v_k) and its covariance from the residual spread.

    With unit v: A = sum (I - v v^T) = n I - V^T V, b = sum (I - v v^T) p = sum p - V^T (v.p),
    and the offset of x from line k is (x - p_k) - v_k (v_k . (x - p_k))."""
    vp = np.einsum("ni,ni->n", v, p)
    A = len(p) * np.eye(2) - v.T @ v
    b = p.sum(0) - v.T @ vp
    x = np.linalg.solve(A, b)
    e = x - p
    r = e - v * np.einsum("ni,ni->n", v, e)[:, None]  # perpendicular offsets
    sigma2 = float((r * r).sum() / max(len(p) - 2, 1))
    return x, sigma2 * np.linalg.inv(A)


# a vector this far from unit length comes from a network whose own normalisation was rounded
# (an int8 model's); the least squares below holds for unit vectors only
UNIT_TOLERANCE = 1e-3


def _unit(vectors: np.ndarray) -> np.ndarray:
    """(n, 2) the vectors as they are when every one is unit to UNIT_TOLERANCE (a float model's,
    to its rounding: left bit for bit), else each divided by its length."""
    norms = np.linalg.norm(vectors, axis=1)
    if not len(norms) or np.all(np.abs(norms - 1.0) <= UNIT_TOLERANCE):
        return vectors
    return vectors / np.maximum(norms, 1e-6)[:, None]


def _percentile_90(x: np.ndarray) -> float:
    """np.percentile(x, 90) (linear interpolation) by partial sorting: numpy's general
    percentile was an eighth of the voting time at these sizes."""
    pos = 0.9 * (len(x) - 1)
    lo = int(np.floor(pos))
    hi = min(lo + 1, len(x) - 1)
    part = np.partition(x, (lo, hi))
    a, b, t = float(part[lo]), float(part[hi]), pos - lo
    return a + (b - a) * t if t < 0.5 else b - (b - a) * (1.0 - t)


def vote_instances(
    pixels_xy: np.ndarray,
    vectors: np.ndarray,
    config: VotingConfig,
    seed: int | np.random.Generator,
) -> list[VotedInstance]:
    """Instances of one class.

    Args:
        pixels_xy: (n, 2) pixel centres (x, y) of the class's pixels.
        vectors: (n, 2) unit vectors at those pixels.
    Returns:
        instances, best supported first.
    """
    rng = np.random.default_rng(seed)
    vectors = _unit(vectors)
    remaining = np.arange(len(pixels_xy))
    out: list[VotedInstance] = []
    while len(remaining) >= config.min_inliers and len(out) < config.max_instances:
        p, v = pixels_xy[remaining], vectors[remaining]
        i = rng.integers(len(p), size=config.n_hypotheses)
        j = rng.integers(len(p), size=config.n_hypotheses)
        h = _intersections(p, v, i, j)
        h = h[np.all(np.isfinite(h), axis=1)]
        if len(h) == 0:
            break
        # score on a random subset (the cost of a round stays bounded on large masks), then
        # take the best hypothesis's inliers among all remaining pixels
        if len(p) > config.max_scoring_pixels:
            sub = rng.choice(len(p), config.max_scoring_pixels, replace=False)
        else:
            sub = np.arange(len(p))
        # (K, n_sub) offsets from the scored pixels to the hypotheses, x and y apart
        ps, vs = p[sub], v[sub]
        dx = h[:, 0, None] - ps[None, :, 0]
        dy = h[:, 1, None] - ps[None, :, 1]
        norm = np.sqrt(dx * dx + dy * dy)
        cos = (dx * vs[None, :, 0] + dy * vs[None, :, 1]) / np.maximum(norm, 1e-9)
        counts = (cos > config.inlier_cos).sum(1)
        best = int(np.argmax(counts))
        d = h[best][None] - p
        inliers = (d * v).sum(1) / np.maximum(np.linalg.norm(d, axis=1), 1e-9) > config.inlier_cos
        if inliers.sum() < config.min_inliers:
            break
        center, cov = _least_squares_center(p[inliers], v[inliers])
        # the center comes from the pixels that agree with it closely; the mask takes every
        # pixel that points at it roughly (vectors near the center and at the rims are noisy)
        d = center[None] - p
        cos = (d * v).sum(1) / np.maximum(np.linalg.norm(d, axis=1), 1e-9)
        strict = cos > config.inlier_cos
        if strict.sum() >= config.min_inliers:
            center, cov = _least_squares_center(p[strict], v[strict])
        # ... but only near it: a pixel of another part of the class far along the same line
        # also points at it (measured: without this bound the boxes of parts in a pile were
        # three times too large, and their pixels were lost to the first instance)
        dist = np.linalg.norm(d, axis=1)
        core = dist[strict] if strict.sum() >= config.min_inliers else dist[inliers]
        radius = config.member_radius_factor * _percentile_90(core) + 2.0
        members = (((cos > config.member_cos) | inliers) & (dist <= radius)) | (dist < 3.0)
        cov = cov * config.cov_scale + np.eye(2) * config.min_center_var
        out.append(VotedInstance(center, cov, remaining[members], int(members.sum())))
        remaining = remaining[~members]
    return out
