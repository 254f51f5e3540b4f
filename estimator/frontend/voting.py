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

The arithmetic of a round runs in compiled loops (numba): the hypotheses
(:func:`_finite_intersections`), their scores (:func:`_count_inliers`) and the angles to a center
(:func:`_cos_and_distance`) do the numpy expressions' operations in the same order, one element
at a time, and give the same bits without the temporaries of (hypotheses x pixels) arrays; the
line fit (:func:`_line_fit`) sums row by row and solves its 2 x 2 system in closed form, where
numpy's BLAS sums in an order of its own and LAPACK pivots, so it agrees with the numpy
reference (:func:`_normal_equations`) to rounding (1e-13 px on the shipped model's crops), not to
the bit. Those small numpy calls were most of a crop's voting time (0.6 of 0.9 ms). The fit is
not made again over the same pixels, and an instance's covariance is formed once, from its last fit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit


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


def _normal_equations(p: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """(x, A, sigma2): the point closest to all lines (p_k, v_k), the normal matrix A (2, 2)
    and the residual variance; the covariance is ``sigma2 * inv(A)``.

    With unit v: A = sum (I - v v^T) = n I - V^T V, b = sum (I - v v^T) p = sum p - V^T (v.p),
    and the offset of x from line k is (x - p_k) - v_k (v_k . (x - p_k))."""
    vp = np.einsum("ni,ni->n", v, p)
    A = len(p) * np.eye(2) - v.T @ v
    b = p.sum(0) - v.T @ vp
    x = np.linalg.solve(A, b)
    e = x - p
    r = e - v * np.einsum("ni,ni->n", v, e)[:, None]  # perpendicular offsets
    sigma2 = float((r * r).sum() / max(len(p) - 2, 1))
    return x, A, sigma2


def _least_squares_center(p: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Point closest to all lines (p_k, v_k) (p, v: (n, 2), v unit) and its (2, 2) covariance
    from the residual spread (:func:`_normal_equations`)."""
    x, A, sigma2 = _normal_equations(p, v)
    return x, sigma2 * np.linalg.inv(A)


def _compiled(fn):
    """``fn`` compiled and kept in numba's disk cache; compiled anew in each process where no
    cache folder can be written."""
    try:
        return njit(cache=True, nogil=True)(fn)
    except RuntimeError:  # numba: "cannot cache function ...: no locator available"
        return njit(nogil=True)(fn)


def _count_inliers_loops(h, ps, vs, inlier_cos):  # pragma: no cover (compiled)
    """(K,) int64: for each hypothesis h[k] (K, 2), the pixels ps (n, 2) whose unit vector vs
    (n, 2) points at it within ``inlier_cos``: the numpy expression's operations, in its order
    (dx = h - p; norm = sqrt(dx*dx + dy*dy); cos = (dx*vx + dy*vy) / max(norm, 1e-9))."""
    counts = np.zeros(h.shape[0], np.int64)
    for k in range(h.shape[0]):
        c = 0
        for n in range(ps.shape[0]):
            dx = h[k, 0] - ps[n, 0]
            dy = h[k, 1] - ps[n, 1]
            norm = math.sqrt(dx * dx + dy * dy)
            if (dx * vs[n, 0] + dy * vs[n, 1]) / (norm if norm >= 1e-9 else 1e-9) > inlier_cos:
                c += 1
        counts[k] = c
    return counts


def _cos_and_distance_loops(point, p, v):  # pragma: no cover (compiled)
    """((n,) cos, (n,) distance) of the offsets d = point - p[k] (p, v: (n, 2)): the angle's
    cosine to each unit vector v[k], (d . v) / max(|d|, 1e-9), and |d|, in numpy's order."""
    n = p.shape[0]
    cos = np.empty(n)
    dist = np.empty(n)
    for k in range(n):
        dx = point[0] - p[k, 0]
        dy = point[1] - p[k, 1]
        norm = math.sqrt(dx * dx + dy * dy)
        cos[k] = (dx * v[k, 0] + dy * v[k, 1]) / (norm if norm >= 1e-9 else 1e-9)
        dist[k] = norm
    return cos, dist


def _finite_intersections_loops(p, v, i, j):  # pragma: no cover (compiled)
    """The finite rows of :func:`_intersections` (p, v: (n, 2); i, j: (K,) int), in order:
    the same operations one pair at a time."""
    h = np.empty((i.shape[0], 2))
    m = 0
    for k in range(i.shape[0]):
        a0, a1 = v[i[k], 0], v[i[k], 1]
        b0, b1 = -v[j[k], 0], -v[j[k], 1]
        det = a0 * b1 - a1 * b0
        if abs(det) < 1e-3:
            continue
        d0 = p[j[k], 0] - p[i[k], 0]
        d1 = p[j[k], 1] - p[i[k], 1]
        s = (d0 * b1 - d1 * b0) / det
        x = p[i[k], 0] + s * a0
        y = p[i[k], 1] + s * a1
        if math.isfinite(x) and math.isfinite(y):
            h[m, 0] = x
            h[m, 1] = y
            m += 1
    return h[:m].copy()


def _line_fit_loops(p, v, use):  # pragma: no cover (compiled)
    """:func:`_normal_equations` over the rows where ``use`` (n,) is true, summed one row at a
    time and solved in closed form: (x (2,), A (2, 2), sigma2, solved); ``solved`` is False
    where the lines are all parallel (A singular)."""
    n = 0
    s00 = s01 = s11 = sp0 = sp1 = svp0 = svp1 = 0.0
    for k in range(p.shape[0]):
        if not use[k]:
            continue
        n += 1
        vp = v[k, 0] * p[k, 0] + v[k, 1] * p[k, 1]
        s00 += v[k, 0] * v[k, 0]
        s01 += v[k, 0] * v[k, 1]
        s11 += v[k, 1] * v[k, 1]
        sp0 += p[k, 0]
        sp1 += p[k, 1]
        svp0 += v[k, 0] * vp
        svp1 += v[k, 1] * vp
    A = np.empty((2, 2))
    A[0, 0] = n - s00
    A[0, 1] = A[1, 0] = -s01
    A[1, 1] = n - s11
    x = np.zeros(2)
    det = A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]
    if not det > 1e-12 * max(A[0, 0] * A[1, 1], 1e-300):
        return x, A, 0.0, False
    b0, b1 = sp0 - svp0, sp1 - svp1
    x[0] = (A[1, 1] * b0 - A[0, 1] * b1) / det
    x[1] = (A[0, 0] * b1 - A[1, 0] * b0) / det
    rr = 0.0
    for k in range(p.shape[0]):
        if not use[k]:
            continue
        e0, e1 = x[0] - p[k, 0], x[1] - p[k, 1]
        ve = v[k, 0] * e0 + v[k, 1] * e1
        r0, r1 = e0 - v[k, 0] * ve, e1 - v[k, 1] * ve
        rr += r0 * r0 + r1 * r1
    return x, A, rr / max(n - 2, 1), True


_count_inliers = _compiled(_count_inliers_loops)
_cos_and_distance = _compiled(_cos_and_distance_loops)
_finite_intersections = _compiled(_finite_intersections_loops)
_line_fit = _compiled(_line_fit_loops)


def _covariance(A: np.ndarray, sigma2: float) -> np.ndarray:
    """(2, 2) sigma2 * inv(A) of a (2, 2) symmetric positive definite A, in closed form."""
    det = A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]
    return (sigma2 / det) * np.array([[A[1, 1], -A[0, 1]], [-A[1, 0], A[0, 0]]])


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
        Both are taken as float64.
    Returns:
        instances, best supported first.
    """
    rng = np.random.default_rng(seed)
    pixels_xy = np.ascontiguousarray(pixels_xy, np.float64)
    vectors = np.ascontiguousarray(_unit(np.asarray(vectors, np.float64)))
    remaining = np.arange(len(pixels_xy))
    out: list[VotedInstance] = []
    while len(remaining) >= config.min_inliers and len(out) < config.max_instances:
        p, v = pixels_xy[remaining], vectors[remaining]
        i = rng.integers(len(p), size=config.n_hypotheses)
        j = rng.integers(len(p), size=config.n_hypotheses)
        h = _finite_intersections(p, v, i, j)
        if len(h) == 0:
            break
        # score on a random subset (the cost of a round stays bounded on large masks), then
        # take the best hypothesis's inliers among all remaining pixels
        if len(p) > config.max_scoring_pixels:
            sub = rng.choice(len(p), config.max_scoring_pixels, replace=False)
            counts = _count_inliers(h, p[sub], v[sub], config.inlier_cos)
        else:
            counts = _count_inliers(h, p, v, config.inlier_cos)
        best = int(np.argmax(counts))
        cos, _ = _cos_and_distance(h[best], p, v)
        inliers = cos > config.inlier_cos
        if inliers.sum() < config.min_inliers:
            break
        center, A, sigma2, solved = _line_fit(p, v, inliers)
        if not solved:  # every inlier's line parallel: no point to vote for
            break
        # the center comes from the pixels that agree with it closely; the mask takes every
        # pixel that points at it roughly (vectors near the center and at the rims are noisy)
        cos, dist = _cos_and_distance(center, p, v)
        strict = cos > config.inlier_cos
        n_strict = int(strict.sum())
        if n_strict >= config.min_inliers and not np.array_equal(strict, inliers):
            fit = _line_fit(p, v, strict)
            if fit[3]:
                center, A, sigma2 = fit[:3]
        # ... but only near it: a pixel of another part of the class far along the same line
        # also points at it (measured: without this bound the boxes of parts in a pile were
        # three times too large, and their pixels were lost to the first instance)
        core = dist[strict] if n_strict >= config.min_inliers else dist[inliers]
        radius = config.member_radius_factor * _percentile_90(core) + 2.0
        members = (((cos > config.member_cos) | inliers) & (dist <= radius)) | (dist < 3.0)
        cov = _covariance(A, sigma2) * config.cov_scale + np.eye(2) * config.min_center_var
        out.append(VotedInstance(center, cov, remaining[members], int(members.sum())))
        remaining = remaining[~members]
    return out


def compile_kernels() -> None:
    """Compile (or load from numba's disk cache) the voting's loops on a small field, so that
    a front end's first frame does not wait for them (seconds on a cold cache)."""
    ys, xs = np.mgrid[0:12, 0:12]
    pixels = np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64)
    vectors = np.array([5.5, 5.5]) - pixels + 0.25
    vectors /= np.linalg.norm(vectors, axis=1, keepdims=True)
    vote_instances(pixels, vectors, VotingConfig(min_inliers=5), seed=0)
