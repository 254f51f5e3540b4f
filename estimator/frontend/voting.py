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
reference (:func:`_normal_equations`) to rounding (centres within 4.5e-13 px on the shipped
model's crops), not to the bit. Those small numpy calls were most of a crop's voting time (0.6
of 0.9 ms). The fit is not made again over the same pixels, and an instance's covariance is
formed once, from its last fit. Inliers whose lines are all parallel to rounding (no point to
vote for; ``np.linalg.solve`` raised there, or gave one a million pixels away) are set aside
and the search goes on.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from posefuse.estimator.core.compiled import as_f64, as_plain, compiled


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

    def __post_init__(self) -> None:
        if self.n_hypotheses < 1 or self.max_instances < 1 or self.max_scoring_pixels < 1:
            raise ValueError(
                "VotingConfig: n_hypotheses, max_instances and max_scoring_pixels must be at "
                f"least 1, got {self.n_hypotheses}, {self.max_instances}, "
                f"{self.max_scoring_pixels}"
            )
        if self.min_inliers < 3:  # a point from lines needs two, its spread a third
            raise ValueError(
                f"VotingConfig: min_inliers must be at least 3, got {self.min_inliers}"
            )
        if not (0.0 < self.inlier_cos < 1.0 and -1.0 < self.member_cos < 1.0):
            raise ValueError(
                "VotingConfig: inlier_cos must lie in (0, 1) and member_cos in (-1, 1), got "
                f"{self.inlier_cos}, {self.member_cos}"
            )
        scales = (self.cov_scale, self.member_radius_factor)
        if not all(math.isfinite(x) and x > 0 for x in scales) or not (
            math.isfinite(self.min_center_var) and self.min_center_var >= 0
        ):
            raise ValueError(
                "VotingConfig: cov_scale and member_radius_factor must be positive and "
                f"min_center_var at least 0, got {self.cov_scale}, {self.member_radius_factor}, "
                f"{self.min_center_var}"
            )


@dataclass(frozen=True, eq=False)
class VotedInstance:
    """center: (2,) output-grid pixels (x, y); cov: (2, 2); pixels: (n,) flat indices of its
    inlier pixels; n_votes: inlier count."""

    center: np.ndarray
    cov: np.ndarray
    pixels: np.ndarray
    n_votes: int


# The numpy forms of a round's steps (_intersections, _normal_equations, _least_squares_center,
# _percentile_90): the voting runs the compiled loops below; these are what the tests hold
# those loops to.


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
    """((n,) cos, (n,) distance) of the offsets d = point - p[k] (point (2,); p, v (n, 2)): the
    angle's cosine to each unit vector v[k], (d . v) / max(|d|, 1e-9), and |d|, in numpy's
    order."""
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
    """(m, 2) the finite rows of :func:`_intersections` (p, v: (n, 2); i, j: (K,) int), in
    order: the same operations one pair at a time."""
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
    """:func:`_normal_equations` over the rows of p, v (n, 2) where ``use`` (n,) is true, summed
    one row at a time and solved in closed form: (x (2,), A (2, 2), sigma2, solved); ``solved``
    is False where the lines are all parallel to rounding (A singular: ``np.linalg.solve``
    raised, or gave a point a million pixels away) or the point lies beyond floating point."""
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
    trace = A[0, 0] + A[1, 1]
    # singular to rounding, whatever the lines' direction: the eigenvalues' ratio, about
    # det / trace^2, below 1e-12 (lines within a microradian of parallel meet a million
    # pixels away, if at all)
    if not det > 1e-12 * trace * trace:
        return x, A, 0.0, False
    b0, b1 = sp0 - svp0, sp1 - svp1
    x[0] = (A[1, 1] * b0 - A[0, 1] * b1) / det
    x[1] = (A[0, 0] * b1 - A[1, 0] * b0) / det
    if not (math.isfinite(x[0]) and math.isfinite(x[1])):
        return x, A, 0.0, False
    rr = 0.0
    for k in range(p.shape[0]):
        if not use[k]:
            continue
        e0, e1 = x[0] - p[k, 0], x[1] - p[k, 1]
        ve = v[k, 0] * e0 + v[k, 1] * e1
        r0, r1 = e0 - v[k, 0] * ve, e1 - v[k, 1] * ve
        rr += r0 * r0 + r1 * r1
    return x, A, rr / max(n - 2, 1), True


_count_inliers = compiled(_count_inliers_loops)
_cos_and_distance = compiled(_cos_and_distance_loops)
_finite_intersections = compiled(_finite_intersections_loops)
_line_fit = compiled(_line_fit_loops)


def _percentile_90_sorted_loops(x):  # pragma: no cover (compiled)
    """:func:`_percentile_90` of x (n,) by a full sort (the same order statistics)."""
    xs = np.sort(x)
    pos = 0.9 * (xs.shape[0] - 1)
    lo = int(math.floor(pos))
    hi = min(lo + 1, xs.shape[0] - 1)
    a, b, t = xs[lo], xs[hi], pos - lo
    return a + (b - a) * t if t < 0.5 else b - (b - a) * (1.0 - t)


_percentile_90_sorted = compiled(_percentile_90_sorted_loops)


def _round_loops(
    h, p, v, sub, inlier_cos, min_inliers, member_cos, radius_factor, cov_scale, min_var
):  # pragma: no cover (compiled)
    """One round of :func:`vote_instances` after its hypotheses h (K, 2) are drawn: the best
    scored on the pixels ``sub`` (all where empty), its inliers, the fit over them and over the
    strict inliers of that fit, the members; p, v (n, 2), sub (m,) int. Returns (status,
    center (2,), cov (2, 2), members (n,) bool): status 0 an instance and its members, 1 too few
    inliers, 2 the inliers' lines all parallel (members: those inliers, which then vote for
    nothing)."""
    n = p.shape[0]
    if sub.shape[0] > 0:
        ps = np.empty((sub.shape[0], 2))
        vs = np.empty((sub.shape[0], 2))
        for k in range(sub.shape[0]):
            ps[k, 0], ps[k, 1] = p[sub[k], 0], p[sub[k], 1]
            vs[k, 0], vs[k, 1] = v[sub[k], 0], v[sub[k], 1]
        counts = _count_inliers(h, ps, vs, inlier_cos)
    else:
        counts = _count_inliers(h, p, v, inlier_cos)
    best = 0
    for k in range(1, counts.shape[0]):
        if counts[k] > counts[best]:
            best = k
    cos, _ = _cos_and_distance(h[best], p, v)
    inliers = cos > inlier_cos
    members = np.zeros(n, np.bool_)
    cov = np.zeros((2, 2))
    if inliers.sum() < min_inliers:
        return 1, np.zeros(2), cov, members
    center, A, sigma2, solved = _line_fit(p, v, inliers)
    if not solved:
        return 2, center, cov, inliers
    cos, dist = _cos_and_distance(center, p, v)
    strict = cos > inlier_cos
    n_strict = strict.sum()
    if n_strict >= min_inliers:
        same = True
        for k in range(n):
            if strict[k] != inliers[k]:
                same = False
                break
        if not same:
            c2, A2, s2, ok = _line_fit(p, v, strict)
            if ok:
                center, A, sigma2 = c2, A2, s2
    core = dist[strict] if n_strict >= min_inliers else dist[inliers]
    radius = radius_factor * _percentile_90_sorted(core) + 2.0
    for k in range(n):
        members[k] = (((cos[k] > member_cos) or inliers[k]) and dist[k] <= radius) or (
            dist[k] < 3.0
        )
    f = sigma2 / (A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0])
    cov[0, 0] = (f * A[1, 1]) * cov_scale + min_var
    cov[0, 1] = (f * -A[0, 1]) * cov_scale + 0.0
    cov[1, 0] = (f * -A[1, 0]) * cov_scale + 0.0
    cov[1, 1] = (f * A[0, 0]) * cov_scale + min_var
    return 0, center, cov, members


_round = compiled(_round_loops)


def _labelled_pixels_loops(logit, vectors):  # pragma: no cover (compiled)
    """((n, 2) pixel (x, y), (n, 2) vectors) of the cells of logit (g, g) above 0, row by row
    (np.nonzero's order), both float64; vectors (2, g, g)."""
    n = 0
    for y in range(logit.shape[0]):
        for x in range(logit.shape[1]):
            if logit[y, x] > 0:
                n += 1
    pix = np.empty((n, 2))
    vec = np.empty((n, 2))
    k = 0
    for y in range(logit.shape[0]):
        for x in range(logit.shape[1]):
            if logit[y, x] > 0:
                pix[k, 0], pix[k, 1] = x, y
                vec[k, 0], vec[k, 1] = vectors[0, y, x], vectors[1, y, x]
                k += 1
    return pix, vec


_labelled_pixels_compiled = compiled(_labelled_pixels_loops)


def labelled_pixels(logit: np.ndarray, vectors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The cells a crop's output labels as its part, and their vectors.

    Args:
        logit: (g, g) the object logit; a cell above 0 is the part's.
        vectors: (2, g, g) the unit vectors (float32 from the network; another float type
            compiles its own loop).
    Returns:
        (n, 2) float64 cell (x, y) and (n, 2) float64 vectors, row by row (np.nonzero's order).
    """
    return _labelled_pixels_compiled(as_plain(logit), as_plain(vectors))


# a vector this far from unit length comes from a network whose own normalisation was rounded
# (an int8 model's); the least squares below holds for unit vectors only
UNIT_TOLERANCE = 1e-3


def _all_unit_loops(vectors, tolerance):  # pragma: no cover (compiled)
    """Whether every row of vectors (n, 2) has a length within ``tolerance`` of 1 (the length
    as ``np.linalg.norm(vectors, axis=1)`` computes it)."""
    for k in range(vectors.shape[0]):
        if (
            not abs(math.sqrt(vectors[k, 0] * vectors[k, 0] + vectors[k, 1] * vectors[k, 1]) - 1.0)
            <= tolerance
        ):
            return False
    return True


_all_unit = compiled(_all_unit_loops)


def _unit(vectors: np.ndarray) -> np.ndarray:
    """(n, 2) float64 C-contiguous: the vectors as they are when every one is unit to
    UNIT_TOLERANCE (a float model's, to its rounding: left bit for bit), else each divided by
    its length."""
    vectors = as_f64(vectors)
    if _all_unit(vectors, UNIT_TOLERANCE):
        return vectors
    norms = np.linalg.norm(vectors, axis=1)
    return vectors / np.maximum(norms, 1e-6)[:, None]


def _percentile_90(x: np.ndarray) -> float:
    """np.percentile(x, 90) (linear interpolation) by partial sorting: the numpy reference
    that :func:`_percentile_90_sorted`, which the voting runs, is held to in the tests."""
    pos = 0.9 * (len(x) - 1)
    lo = int(np.floor(pos))
    hi = min(lo + 1, len(x) - 1)
    part = np.partition(x, (lo, hi))
    a, b, t = float(part[lo]), float(part[hi]), pos - lo
    return a + (b - a) * t if t < 0.5 else b - (b - a) * (1.0 - t)


_ALL = np.zeros(0, np.int64)  # no subset: every pixel scores the hypotheses


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

    Both inputs are taken as float64 (a float32 field is voted in float64, as the front end's
    are: its network's float32 output is converted first).
    """
    rng = np.random.default_rng(seed)
    pixels_xy = as_f64(pixels_xy)
    vectors = _unit(vectors)
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
        # take the best hypothesis's inliers among all remaining pixels; the center comes from
        # the pixels that agree with it closely, and again from those that agree with that
        # center; the mask takes every pixel that points at it roughly (vectors near the center
        # and at the rims are noisy), but only near it: a pixel of another part of the class
        # far along the same line also points at it (measured: without this bound the boxes of
        # parts in a pile were three times too large, and their pixels were lost to the first
        # instance). All in :func:`_round_loops`.
        if len(p) > config.max_scoring_pixels:
            sub = rng.choice(len(p), config.max_scoring_pixels, replace=False)
        else:
            sub = _ALL
        status, center, cov, members = _round(
            h,
            p,
            v,
            sub,
            float(config.inlier_cos),
            int(config.min_inliers),
            float(config.member_cos),
            float(config.member_radius_factor),
            float(config.cov_scale),
            float(config.min_center_var),
        )
        if status == 1:  # too few inliers
            break
        if status == 2:  # inliers whose lines are all parallel point at no center: set aside
            remaining = remaining[~members]
            continue
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
    labelled_pixels(np.ones((4, 4), np.float32), np.zeros((2, 4, 4), np.float32))  # a network's
