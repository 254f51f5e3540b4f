"""Rotational symmetries of object models: detection from a mesh and their discretisation.

A symmetry is a rigid motion ``S`` of the object frame that leaves the object's surface (and so
its appearance) unchanged: poses ``T`` and ``T @ S`` look the same. Symmetries follow the BOP
``models_info.json`` conventions: discrete ones as 4x4 transforms ``(D, 4, 4)``, continuous ones
as an axis and a point on it (``offset``), here in metres.

Detection (:func:`detect_symmetries`) works on the surface only, so it accepts meshes that are
not watertight (as real CAD exports often are). A candidate rotation is accepted as a symmetry
when the 95th percentile of the distances from the rotated surface samples to the surface is at
most ``tol_frac`` times the object diameter, by default 2.5%. That tolerance is a quarter of the
ADD(-S) threshold (10% of the diameter), so two poses related by an accepted symmetry can never
decide whether an estimate counts as correct; for a 60 mm part at 0.7 m and a 924 px focal length
it is about 2 px. It is also what makes a threaded screw continuous: a rotation about its axis
only shifts the helix along the axis by a fraction of the pitch. Candidates are rotations about
axes through the surface centroid (which every symmetry axis passes through): the principal axes
of the surface's second moments and, for an axis of order >= 3 (or a degenerate pair of moments),
the perpendicular axes found by a sweep in the perpendicular plane.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import trimesh
from scipy.optimize import minimize_scalar
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

DEFAULT_TOL_FRAC = 0.025
MAX_ORDER = 72
# Angles (fractions of a turn) that no cyclic group of order <= MAX_ORDER contains together.
_CONTINUOUS_PROBES = (0.1237, 0.2913, 0.4471, 0.0311)


@dataclass(frozen=True)
class ContinuousSymmetry:
    """Any rotation about ``axis`` through the point ``offset`` (BOP ``symmetries_continuous``).

    axis: (3,) unit vector in the object frame; offset: (3,) point on the axis, metres.
    """

    axis: tuple[float, float, float]
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def transform(self, angle: float) -> np.ndarray:
        """The (4, 4) symmetry rotating by ``angle`` radians about the axis."""
        return transform_about_axis(np.asarray(self.axis), angle, np.asarray(self.offset))


@dataclass(frozen=True)
class SymmetryAxis:
    """A detected rotation axis: ``order`` 0 means continuous; ``residual`` is the worst accepted
    95th-percentile surface distance as a fraction of the diameter."""

    axis: tuple[float, float, float]
    order: int
    residual: float


@dataclass(frozen=True)
class SymmetryReport:
    """What :func:`detect_symmetries` found.

    discrete: (D, 4, 4) all discrete symmetries except the identity, metres.
    continuous: the continuous axes (at most one is kept; BOP combines it with ``discrete``).
    axes: the proper rotation axes found, main axis first, for reports.
    """

    discrete: np.ndarray  # (D, 4, 4)
    continuous: tuple[ContinuousSymmetry, ...]
    axes: tuple[SymmetryAxis, ...] = field(default=())

    @property
    def is_symmetric(self) -> bool:
        return len(self.discrete) > 0 or len(self.continuous) > 0

    def describe(self) -> str:
        """A one-line human summary, e.g. ``"18-fold about z; 2-fold about 18 axes ⟂"``."""
        return describe_symmetries(self.discrete, self.continuous)


def transform_about_axis(axis: np.ndarray, angle: float, point: np.ndarray) -> np.ndarray:
    """(4, 4) rotation by ``angle`` about the line through ``point`` along unit ``axis``."""
    axis = np.asarray(axis, dtype=np.float64)
    R = Rotation.from_rotvec(axis / np.linalg.norm(axis) * angle).as_matrix()
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = point - R @ point
    return T


def _canonical_axis(axis: np.ndarray) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    return axis if axis[np.argmax(np.abs(axis))] > 0 else -axis


class _SurfaceDistance:
    """Approximate point-to-surface distance from a dense seeded surface sample.

    Point-to-plane distance to the nearest sample (exact on flat and smooth patches), falling back
    to the point distance minus the sampling gap where a point has left the sampled surface (past
    an edge). Exact mesh proximity queries are ~100x slower and change no decision here.
    """

    def __init__(self, mesh: trimesh.Trimesh, n_dense: int, seed: int):
        pts, face_idx = trimesh.sample.sample_surface(mesh, n_dense, seed=seed)
        self.points = np.asarray(pts)
        self.normals = np.asarray(mesh.face_normals)[face_idx]
        self.tree = cKDTree(self.points)
        nn, _ = self.tree.query(self.points, k=2)
        self.gap = 2.0 * float(np.mean(nn[:, 1]))

    def __call__(self, pts: np.ndarray, cap: float = np.inf) -> np.ndarray:
        """(N,) distances of (N, 3) points to the surface, clipped at ``cap`` (which also bounds
        the search: far points are what make an unbounded k-d tree query slow)."""
        dist, idx = self.tree.query(pts, distance_upper_bound=cap + self.gap)
        far = ~np.isfinite(dist)
        idx = np.where(far, 0, idx)
        plane = np.abs(np.einsum("ij,ij->i", pts - self.points[idx], self.normals[idx]))
        out = np.maximum(plane, dist - self.gap)
        out[far] = cap
        return np.minimum(out, cap)


def detect_symmetries(
    mesh: trimesh.Trimesh,
    diameter: float,
    tol_frac: float = DEFAULT_TOL_FRAC,
    seed: int = 0,
    n_test: int = 1500,
    n_dense: int = 60_000,
) -> SymmetryReport:
    """Find the proper rotational symmetries of a mesh.

    Args:
        mesh: the object's surface (any units; results are in the same units).
        diameter: the object's diameter in the mesh's units.
        tol_frac: a rotation is a symmetry when the 95th percentile of the distances of the
            rotated surface samples to the surface is <= ``tol_frac * diameter`` (default 0.025).
        seed: seed of the surface sampling.
    Returns:
        The symmetries as BOP-style discrete transforms and continuous axes.
    """
    if diameter <= 0 or not np.isfinite(diameter):
        raise ValueError(f"detect_symmetries: diameter must be positive and finite, got {diameter}")
    surface = _SurfaceDistance(mesh, n_dense, seed)
    test_pts, _ = trimesh.sample.sample_surface(mesh, n_test, seed=seed + 1)
    test_pts = np.asarray(test_pts)
    center, second = _surface_moments(mesh)
    tol = tol_frac * diameter

    def score(axis: np.ndarray, angle: float) -> float:
        T = transform_about_axis(axis, angle, center)
        moved = test_pts @ T[:3, :3].T + T[:3, 3]
        return float(np.percentile(surface(moved, cap=1.5 * tol), 95)) / diameter

    moments, vecs = np.linalg.eigh(second)
    eig_axes = [_canonical_axis(vecs[:, i]) for i in range(3)]

    rot_axes: list[SymmetryAxis] = []
    for axis in eig_axes:
        found = _axis_order(lambda a, ax=axis: score(ax, a), tol_frac)
        if found is not None:
            rot_axes.append(SymmetryAxis(tuple(axis), *found))

    # Axes perpendicular to a high-order axis, or in a plane of degenerate moments, are not
    # fixed by the moments: sweep for 2-fold axes there.
    sweep_planes: list[tuple[np.ndarray, float]] = []
    for ax in rot_axes:
        if ax.order == 0 or ax.order >= 3:
            sweep_planes.append((np.asarray(ax.axis), np.pi / ax.order if ax.order else 0.0))
    # Moments sorted ascending: a degenerate pair (0, 1) spans the plane normal to vecs[:, 2],
    # a degenerate pair (1, 2) the plane normal to vecs[:, 0].
    rel = np.diff(moments) / max(moments[-1], 1e-300)
    for i, normal_index in ((0, 2), (1, 0)):
        normal = _canonical_axis(vecs[:, normal_index])
        if rel[i] < 0.05 and not any(abs(np.dot(p, normal)) > 0.99 for p, _ in sweep_planes):
            sweep_planes.append((normal, np.pi))
    flips: list[SymmetryAxis] = []
    for normal, span in sweep_planes:
        flip = _sweep_flip(normal, span, lambda b: score(b, np.pi), tol_frac)
        if flip is not None:
            flips.append(flip)

    # One entry per distinct axis: continuous first, then by order, then by residual.
    axes: list[SymmetryAxis] = []
    for cand in sorted(rot_axes + flips, key=lambda a: (a.order != 0, -a.order, a.residual)):
        if not any(abs(np.dot(cand.axis, a.axis)) > 0.99 for a in axes):
            axes.append(cand)
    continuous = tuple(ContinuousSymmetry(a.axis, tuple(center)) for a in axes if a.order == 0)[:1]
    generators = [
        transform_about_axis(np.asarray(a.axis), 2 * np.pi / a.order, center)
        for a in axes
        if a.order >= 2
    ]
    if continuous:
        # Every flip perpendicular to a continuous axis is one such flip composed with a rotation
        # about the axis: keep a single one (BOP combines discrete and continuous symmetries).
        cont_axis = np.asarray(continuous[0].axis)
        generators = [g for g in generators if abs(np.dot(_rotation_axis(g), cont_axis)) < 0.05][:1]
    discrete = _group_closure(generators, scale=diameter)
    return SymmetryReport(discrete=discrete, continuous=continuous, axes=tuple(axes))


def _surface_moments(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray]:
    """Exact area-weighted centroid (3,) and central second moment (3, 3) of the surface."""
    tris = np.asarray(mesh.triangles, dtype=np.float64)  # (F, 3, 3)
    areas = np.asarray(mesh.area_faces, dtype=np.float64)
    total = areas.sum()
    centroid = (areas[:, None] * tris.mean(axis=1)).sum(axis=0) / total
    rel = tris - centroid
    s = rel.sum(axis=1)
    # Integral of p p^T over a triangle: A/12 * (sum_i v_i v_i^T + s s^T), s = sum_i v_i.
    outer = np.einsum("fij,fik->fjk", rel, rel) + np.einsum("fj,fk->fjk", s, s)
    second = (areas[:, None, None] * outer).sum(axis=0) / (12.0 * total)
    return centroid, second


def _axis_order(score_at, tol_frac: float) -> tuple[int, float] | None:
    """Order of the rotation symmetry about one axis: (order, residual), order 0 = continuous."""
    probes = [score_at(2 * np.pi * f) for f in _CONTINUOUS_PROBES]
    if max(probes) <= tol_frac:
        return 0, max(probes)
    cache: dict[int, float] = {}

    def at(k: int, n: int) -> float:
        # k/n turns, cached by the reduced fraction's angle in 1/LCM units.
        key = round(k * 720720 / n)
        if key not in cache:
            cache[key] = score_at(2 * np.pi * k / n)
        return cache[key]

    passing = [n for n in range(2, MAX_ORDER + 1) if at(1, n) <= tol_frac]
    for n in sorted(passing, reverse=True):
        # Every multiple of 1/n turn must pass too; the ones nearest a half turn move points
        # farthest (small rotations of a flat plate slide it within itself), so test them first.
        ks = sorted(range(1, n), key=lambda k: -min(k, n - k))
        worst = 0.0
        for k in ks:
            worst = max(worst, at(k, n))
            if worst > tol_frac:
                break
        else:
            return n, worst
    return None


def _sweep_flip(normal: np.ndarray, span: float, flip_score, tol_frac: float):
    """Best 2-fold axis perpendicular to ``normal`` within an angle span, if any is a symmetry."""
    u = np.cross(normal, [1.0, 0, 0] if abs(normal[0]) < 0.9 else [0, 1.0, 0])
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)

    def axis_at(theta: float) -> np.ndarray:
        return np.cos(theta) * u + np.sin(theta) * v

    if span == 0.0:  # continuous axis: all perpendicular flips are equivalent
        s = flip_score(u)
        return SymmetryAxis(tuple(_canonical_axis(u)), 2, s) if s <= tol_frac else None
    step = np.deg2rad(0.5)
    thetas = np.arange(0.0, span, step)
    scores = np.array([flip_score(axis_at(t)) for t in thetas])
    best = int(np.argmin(scores))
    res = minimize_scalar(
        lambda t: flip_score(axis_at(t)),
        bounds=(thetas[best] - step, thetas[best] + step),
        method="bounded",
        options={"xatol": 1e-5},
    )
    theta, s = (res.x, res.fun) if res.fun < scores[best] else (thetas[best], scores[best])
    if s > tol_frac:
        return None
    return SymmetryAxis(tuple(_canonical_axis(axis_at(theta))), 2, float(s))


def _rotation_axis(T: np.ndarray) -> np.ndarray:
    rotvec = Rotation.from_matrix(T[:3, :3]).as_rotvec()
    n = np.linalg.norm(rotvec)
    if n < 1e-9:
        return np.zeros(3)
    if abs(n - np.pi) < 1e-6:  # rotvec sign is arbitrary at pi; the axis is the +1 eigenvector
        w, v = np.linalg.eigh((T[:3, :3] + T[:3, :3].T) / 2)
        return _canonical_axis(v[:, np.argmax(w)])
    return rotvec / n


def _group_closure(generators: list[np.ndarray], scale: float, max_size: int = 1000) -> np.ndarray:
    """All products of the generators, without the identity: (D, 4, 4)."""
    if not generators:
        return np.zeros((0, 4, 4))

    def key_close(a: np.ndarray, b: np.ndarray) -> bool:
        d = a - b
        # Loose on purpose: axes found on real meshes are exact only to the detection tolerance,
        # and products of slightly-off generators must still be recognised as the same element.
        return np.abs(d[:3, :3]).max() < 0.02 and np.abs(d[:3, 3]).max() / scale < 0.01

    elems = [np.eye(4)]
    frontier = [np.eye(4)]
    while frontier:
        new = []
        for e in frontier:
            for g in generators:
                p = g @ e
                if not any(key_close(p, q) for q in elems):
                    elems.append(p)
                    new.append(p)
                    if len(elems) > max_size:
                        raise ValueError("symmetry group closure exceeded its size limit")
        frontier = new
    return np.stack(elems[1:]) if len(elems) > 1 else np.zeros((0, 4, 4))


def symmetry_transforms(
    discrete: np.ndarray,
    continuous: tuple[ContinuousSymmetry, ...] | list[ContinuousSymmetry],
    max_step_rad: float = np.deg2rad(1.0),
) -> np.ndarray:
    """All symmetries as (S, 4, 4) transforms, identity first, continuous axes discretised.

    As BOP's ``get_symmetry_transformations``: every discrete symmetry (and the identity) is
    combined with every step of each continuous axis; unlike it, the identity is kept.

    Args:
        discrete: (D, 4, 4) discrete symmetries without the identity.
        continuous: continuous axes.
        max_step_rad: the largest angular step of a continuous axis.
    """
    disc = [np.eye(4)] + [np.asarray(d, dtype=np.float64) for d in discrete]
    cont = [np.eye(4)]
    for sym in continuous:
        n_steps = int(np.ceil(2 * np.pi / max_step_rad))
        cont += [sym.transform(2 * np.pi * i / n_steps) for i in range(1, n_steps)]
    return np.stack([c @ d for d in disc for c in cont])


def describe_symmetries(
    discrete: np.ndarray, continuous: tuple[ContinuousSymmetry, ...] | list[ContinuousSymmetry]
) -> str:
    """A human summary of a symmetry set: the rotation axes with their orders."""
    if len(discrete) == 0 and not continuous:
        return "none"
    orders: dict[tuple, int] = {}
    for T in discrete:
        axis = _rotation_axis(T)
        angle = Rotation.from_matrix(T[:3, :3]).magnitude()
        if angle < 1e-9:
            continue
        key = tuple(np.round(_canonical_axis(axis), 3))
        n = int(round(2 * np.pi / angle))
        orders[key] = max(orders.get(key, 1), n)
    parts = [f"continuous about {_axis_name(np.asarray(c.axis))}" for c in continuous]
    by_order: dict[int, list[tuple]] = {}
    for key, n in orders.items():
        by_order.setdefault(n, []).append(key)
    for n in sorted(by_order, reverse=True):
        axes = by_order[n]
        if len(axes) == 1:
            parts.append(f"{n}-fold about {_axis_name(np.asarray(axes[0]))}")
        else:
            parts.append(f"{n}-fold about {len(axes)} axes")
    if continuous and len(discrete):
        parts.append("with the flips about every axis perpendicular to it")
    return "; ".join(parts)


def _axis_name(axis: np.ndarray) -> str:
    for i, name in enumerate("xyz"):
        if abs(abs(axis[i]) - 1) < 1e-3:
            return name
    return "[" + ", ".join(f"{a:.3f}" for a in axis) + "]"
