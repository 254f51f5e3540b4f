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

A candidate is always a whole group: a cyclic order ``n`` is accepted only when every multiple of
``1/n`` turn passes, and the closure of all accepted axes is checked element by element. Exact
structure wins over a looser claim: when an axis carries an exact group (every element within
``exact_frac``, 1% of the diameter, the level of the mesh's own imprecision) and a larger group
passes only the looser tolerance, the exact group is claimed and the larger one reported as an
alternative. A five-spoke wheel with recessed spokes is 5-fold, not continuous: the recesses are
what the templates see. Where no exact group exists the loose claim stands (a thread is
continuous). Claims within ``near_frac`` of the tolerance, and groups that miss it by less, are
near-symmetries: :attr:`SymmetryReport.flags` lists them for a person to decide.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import trimesh
from scipy.optimize import minimize_scalar
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

DEFAULT_TOL_FRAC = 0.025
# Exact symmetries of real CAD meshes score below this (0.1-0.6% of the diameter on the five
# evaluation meshes and the procedural parts); near-symmetric features score 1-2.5%.
DEFAULT_EXACT_FRAC = 0.01
# A claim this close to the tolerance, or a group that misses it by less, is flagged.
DEFAULT_NEAR_FRAC = 0.01
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
    """A rotation axis through the surface centroid: ``order`` 0 means continuous; ``residual``
    is the worst 95th-percentile surface distance over the group's elements, as a fraction of the
    diameter."""

    axis: tuple[float, float, float]
    order: int
    residual: float

    def name(self) -> str:
        """E.g. ``"4-fold about z"`` or ``"continuous about [0.707, 0.707, 0.000]"``."""
        kind = "continuous" if self.order == 0 else f"{self.order}-fold"
        return f"{kind} about {_axis_name(np.asarray(self.axis))}"


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
    # groups considered and not claimed: a looser group over an exact one, or one that misses
    # the tolerance by less than near_frac
    alternatives: tuple[SymmetryAxis, ...] = field(default=())
    group_residual: float = 0.0  # worst element of the claimed discrete group, / diameter
    tol_frac: float = DEFAULT_TOL_FRAC
    near_frac: float = DEFAULT_NEAR_FRAC

    @property
    def is_symmetric(self) -> bool:
        return len(self.discrete) > 0 or len(self.continuous) > 0

    def margin(self, axis: SymmetryAxis) -> float:
        """Tolerance minus residual, a fraction of the diameter (negative: the group fails)."""
        return self.tol_frac - axis.residual

    @property
    def flags(self) -> tuple[str, ...]:
        """Near-symmetries a person should decide on, one sentence each."""
        out = []
        for a in self.axes:
            if self.margin(a) < self.near_frac:
                out.append(
                    f"claimed {a.name()} only {100 * self.margin(a):.2f}% of the diameter inside "
                    f"the tolerance (residual {100 * a.residual:.2f}%)"
                )
        for a in self.alternatives:
            if a.residual <= self.tol_frac:
                out.append(
                    f"not claimed: {a.name()} passes the tolerance (residual "
                    f"{100 * a.residual:.2f}%) but the exact group on that axis is smaller"
                )
            else:
                out.append(
                    f"not claimed: {a.name()} misses the tolerance by "
                    f"{100 * -self.margin(a):.2f}% of the diameter"
                )
        return tuple(out)

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
    exact_frac: float = DEFAULT_EXACT_FRAC,
    near_frac: float = DEFAULT_NEAR_FRAC,
) -> SymmetryReport:
    """Find the proper rotational symmetries of a mesh.

    Args:
        mesh: the object's surface (any units; results are in the same units).
        diameter: the object's diameter in the mesh's units.
        tol_frac: a rotation is a symmetry when the 95th percentile of the distances of the
            rotated surface samples to the surface is <= ``tol_frac * diameter`` (default 0.025).
        seed: seed of the surface sampling.
        exact_frac: a group whose every element scores <= ``exact_frac * diameter`` is exact,
            and is claimed over a larger group that passes only ``tol_frac`` (default 0.01).
        near_frac: claims within this of the tolerance, and groups missing it by less, are
            flagged in the report (default 0.01).
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

    def score_transform(T: np.ndarray) -> float:
        moved = test_pts @ T[:3, :3].T + T[:3, 3]
        return float(np.percentile(surface(moved, cap=1.5 * tol + near_frac * diameter), 95)) / (
            diameter
        )

    def score(axis: np.ndarray, angle: float) -> float:
        return score_transform(transform_about_axis(axis, angle, center))

    moments, vecs = np.linalg.eigh(second)
    eig_axes = [_canonical_axis(vecs[:, i]) for i in range(3)]

    rot_axes: list[SymmetryAxis] = []
    alternatives: list[SymmetryAxis] = []
    for axis in eig_axes:
        claimed, alternative = _axis_symmetry(
            lambda a, ax=axis: score(ax, a), tol_frac, exact_frac, near_frac
        )
        if claimed is not None:
            rot_axes.append(SymmetryAxis(tuple(axis), *claimed))
        if alternative is not None:
            alternatives.append(SymmetryAxis(tuple(axis), *alternative))

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
    # Where an axis's exact group was claimed over a looser one, the part has exact structure
    # that the looser claim would hide: flips must then be exact too.
    flip_tol = exact_frac if any(a.residual <= tol_frac for a in alternatives) else tol_frac
    flips: list[SymmetryAxis] = []
    for normal, span in sweep_planes:
        flip = _sweep_flip(normal, span, lambda b: score(b, np.pi), tol_frac)
        if flip is not None and flip.residual <= flip_tol:
            flips.append(flip)
        elif flip is not None:
            alternatives.append(flip)

    # One entry per distinct axis: continuous first, then by order, then by residual.
    axes: list[SymmetryAxis] = []
    for cand in sorted(rot_axes + flips, key=lambda a: (a.order != 0, -a.order, a.residual)):
        if not any(abs(np.dot(cand.axis, a.axis)) > 0.99 for a in axes):
            axes.append(cand)
    alternatives = [
        a
        for a in alternatives
        if not any(abs(np.dot(a.axis, b.axis)) > 0.99 and a.order == b.order for b in axes)
    ]

    # The group as a whole: the closure of the accepted axes, every element scored. Products of
    # axes that pass alone can fail together (axes found to within the tolerance); then the
    # weakest axis is dropped until the whole group passes.
    while True:
        continuous, discrete = _claimed_group(axes, center, diameter)
        elements = list(discrete)
        if continuous:  # a flip composed with steps about the continuous axis
            elements += [
                continuous[0].transform(2 * np.pi * f) @ d
                for f in _CONTINUOUS_PROBES
                for d in discrete
            ]
        residuals = [score_transform(T) for T in elements]
        group_residual = max(residuals, default=0.0)
        if (group_residual <= tol_frac and _orders_kept(axes, discrete)) or len(axes) <= 1:
            break
        weakest = max(range(1, len(axes)), key=lambda i: axes[i].residual)
        alternatives.append(axes.pop(weakest))
    if continuous:
        group_residual = max(group_residual, axes[0].residual)
    return SymmetryReport(
        discrete=discrete,
        continuous=continuous,
        axes=tuple(axes),
        alternatives=tuple(alternatives),
        group_residual=group_residual,
        tol_frac=tol_frac,
        near_frac=near_frac,
    )


def _orders_kept(axes: list[SymmetryAxis], discrete: np.ndarray) -> bool:
    """Whether the closure rotates about each claimed axis by no more than its claimed order: two
    flips that each pass loosely can generate rotations about the main axis that the main axis
    itself was not granted (a 5-fold wheel with flips 90 degrees apart would become 120-fold)."""
    rot_axes = [_rotation_axis(T) for T in discrete]
    for a in axes:
        if a.order >= 2:
            about = sum(abs(float(np.dot(r, a.axis))) > 0.99 for r in rot_axes)
            if about > a.order - 1:
                return False
    return True


def _claimed_group(axes: list[SymmetryAxis], center: np.ndarray, diameter: float):
    """The continuous axis (at most one) and the discrete closure (D, 4, 4) of the axes."""
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
    return continuous, _group_closure(generators, scale=diameter)


def _axis_symmetry(score_at, tol_frac: float, exact_frac: float, near_frac: float):
    """The group claimed about one axis and an alternative not claimed, each (order, residual)
    or None (order 0: continuous).

    The loose group passes ``tol_frac``; the exact one ``exact_frac``. A larger loose group
    over an exact one is the alternative; so is a larger group missing the tolerance by less
    than ``near_frac``.
    """
    loose = _axis_order(score_at, tol_frac)
    nearly = _axis_order(score_at, tol_frac + near_frac)
    if nearly is not None and (loose is None or _contains(nearly[0], loose[0])):
        near_alternative = nearly if nearly[1] > tol_frac else None
    else:
        near_alternative = None
    if loose is None:
        return None, near_alternative
    exact = _axis_order(score_at, exact_frac)
    if exact is not None and _contains(loose[0], exact[0]):
        # the exact group's residual is its worst element at the loose tolerance's scoring
        return exact, loose
    return loose, near_alternative


def _contains(bigger: int, smaller: int) -> bool:
    """Whether the cyclic group of order ``bigger`` (0: continuous) strictly contains the one of
    order ``smaller``."""
    if bigger == smaller:
        return False
    return bigger == 0 or (smaller != 0 and bigger % smaller == 0)


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

    Two discretisations exist on purpose: this one is the method's (templates, matching and the
    mixture, stepped by angle), while the pose errors use bop_toolkit's own to the bit
    (``evaluation.pose_error.bop_symmetry_transformations``), so the measure never moves with
    the method's choices.

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


def symmetry_from_spec(
    spec: str, mesh: trimesh.Trimesh, diameter: float, detected: SymmetryReport | None = None
) -> tuple[np.ndarray, tuple[ContinuousSymmetry, ...]]:
    """A person's symmetry decision, overriding detection: ``(discrete (D, 4, 4), continuous)``.

    ``spec`` is ``none``, ``continuous[:AXIS]`` or ``N[:AXIS]`` (N-fold, N >= 2), where AXIS is
    ``x``, ``y``, ``z`` (object frame) or ``main`` (the default: the detected main axis, else the
    surface's most distinct principal axis). The axis passes through the surface centroid.

    Raises:
        ValueError: a malformed spec, with what is accepted.
    """
    kind, _, axis_name = spec.strip().lower().partition(":")
    axis_name = axis_name or "main"
    center, second = _surface_moments(mesh)
    if axis_name in ("x", "y", "z"):
        axis = np.eye(3)["xyz".index(axis_name)]
    elif axis_name == "main":
        if detected is not None and (detected.axes or detected.alternatives):
            axis = np.asarray((detected.axes or detected.alternatives)[0].axis)
        else:
            moments, vecs = np.linalg.eigh(second)
            # the axis whose moment stands apart from the other two
            gaps = [moments[1] - moments[0], moments[2] - moments[1]]
            axis = vecs[:, 0] if gaps[0] > gaps[1] else vecs[:, 2]
    else:
        raise ValueError(f"symmetry {spec!r}: unknown axis {axis_name!r}; use x, y, z or main")
    if kind == "none":
        return np.zeros((0, 4, 4)), ()
    if kind == "continuous":
        cont = ContinuousSymmetry(tuple(map(float, axis)), tuple(map(float, center)))
        return np.zeros((0, 4, 4)), (cont,)
    try:
        order = int(kind)
    except ValueError:
        order = 0
    if order < 2 or order > MAX_ORDER:
        raise ValueError(
            f"symmetry {spec!r}: use none, continuous[:AXIS] or N[:AXIS] with 2 <= N <= "
            f"{MAX_ORDER} (AXIS: x, y, z or main)"
        )
    generator = transform_about_axis(axis, 2 * np.pi / order, center)
    return _group_closure([generator], scale=diameter), ()
