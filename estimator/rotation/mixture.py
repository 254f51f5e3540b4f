"""RotationMixture: an object's rotation as a max-mixture on SO(3) (paper Section V-B, V-C).

Each component has a mean ``R_world_obj``, the measurements it accepted (world-frame rotations
with their LINE-2D confidences) and their accumulated confidence ``c_i``; its weight is
``w_i = c_i / sum_j c_j``.

A new measurement is first replaced, for every component, by its symmetric equivalent closest
to that component's mean (discrete symmetries by enumeration; a continuous axis in closed form,
see :func:`closest_equivalent`). The component with the smallest angle takes it if the angle is
below the gate (30 degrees), otherwise it founds a new component. The accepting component's
mean is refined by confidence-weighted Gauss-Newton on so(3), re-selecting every member's
symmetric equivalent at each iteration, with residuals ``r_k = log(R_k R^T)`` (a left
perturbation in the world frame) and their exact Jacobian ``J_r^-1(r_k)``.

The covariance of a component is the inverse of ``sum_k (c_k / sigma^2) J_k^T J_k``: a
measurement of confidence 1 counts as one of standard deviation ``sigma`` per axis. About a
continuous symmetry axis nothing is observable, so the variance there is that of an angle
uniform on the circle.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from posefuse.estimator.core.geometry import rotation_angle, so3_exp, so3_jacobian_inv_gram, so3_log

UNIFORM_ANGLE_VAR = np.pi**2 / 3


@dataclass(frozen=True)
class MixtureConfig:
    gate_deg: float = 30.0
    sigma_deg: float = 10.0  # per-axis std of a measurement of confidence 1
    max_iterations: int = 10
    tolerance_rad: float = 1e-7
    max_members: int = 50  # older members leave the refinement; their confidence stays


@dataclass(eq=False)
class RotationComponent:
    """R_world_obj: (3, 3) mean; members: accepted (R_world_obj (3, 3), confidence);
    cov: (3, 3) rad^2, left perturbation in the world frame."""

    R_world_obj: np.ndarray
    members: list[tuple[np.ndarray, float]] = field(default_factory=list)
    cov: np.ndarray = field(default_factory=lambda: np.eye(3) * UNIFORM_ANGLE_VAR)
    retired_confidence: float = 0.0  # of members dropped from the refinement window
    retired: int = 0
    # discrete symmetries only: per member, the index of its equivalent closest to the mean,
    # the angle by which the runner-up is farther, and how far the mean moved since (rad)
    _selection = None  # (k (M,), margin (M,), moved (M,)); plain attribute, not a field

    @property
    def confidence(self) -> float:
        return float(sum(c for _, c in self.members) + self.retired_confidence)

    @property
    def n(self) -> int:
        return len(self.members) + self.retired


def _axis_angle_optimum(M: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """theta maximising trace(M @ Rot(axis, theta)) (the closest rotation about ``axis``).

    trace(M Rot) = cos(t) (tr M - a^T M a) + sin(t) tr(M hat(a)) + a^T M a.

    Args:
        M: (..., 3, 3). axis: (3,) unit.
    Returns:
        (...) angles in radians.
    """
    a = axis
    A = np.trace(M, axis1=-2, axis2=-1) - np.einsum("i,...ij,j->...", a, M, a)
    hat_a = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    B = np.trace(M @ hat_a, axis1=-2, axis2=-1)
    return np.arctan2(B, A)


def closest_equivalents(
    R_meas: np.ndarray,
    R_ref: np.ndarray,
    discrete: np.ndarray,
    continuous_axes: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """For each of M rotations, its symmetric equivalent ``R_meas @ S`` closest to ``R_ref``.

    Args:
        R_meas: (M, 3, 3) R_world_obj. R_ref: (3, 3). discrete: (D, 3, 3) object-frame
        symmetry rotations with the identity. continuous_axes: (A, 3) unit axes in the object
        frame (A = 0 or 1).
    Returns:
        (M, 3, 3) the closest equivalents and (M,) their angles to R_ref in radians.
    """
    candidates = np.einsum("mij,djk->mdik", R_meas, discrete)  # (M, D, 3, 3)
    if len(continuous_axes):
        a = continuous_axes[0]
        theta = _axis_angle_optimum(np.einsum("ji,mdjk->mdik", R_ref, candidates), a)
        candidates = candidates @ so3_exp(theta[..., None] * a)
    angles = rotation_angle(np.einsum("ji,mdjk->mdik", R_ref, candidates))  # (M, D)
    k = np.argmin(angles, axis=1)
    rows = np.arange(len(candidates))
    return candidates[rows, k], angles[rows, k]


def discrete_selection(
    R_meas: np.ndarray, R_ref: np.ndarray, discrete: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """For each of M rotations, the index of its equivalent ``R_meas @ discrete[k]`` closest to
    ``R_ref`` and the margin to the runner-up (angle difference, rad; inf with one element).

    While ``R_ref`` moves by less than half the margin (geodesic angle), the closest equivalent
    stays the same (triangle inequality of the angle metric on SO(3)).

    Args:
        R_meas: (M, 3, 3). R_ref: (3, 3). discrete: (D, 3, 3).
    Returns:
        k: (M,) int; margin: (M,) radians.
    """
    candidates = np.einsum("mij,djk->mdik", R_meas, discrete)
    angles = rotation_angle(np.einsum("ji,mdjk->mdik", R_ref, candidates))  # (M, D)
    k = np.argmin(angles, axis=1)
    if angles.shape[1] == 1:
        return k, np.full(len(k), np.inf)
    two = np.partition(angles, 1, axis=1)
    return k, two[:, 1] - two[:, 0]


def closest_equivalent(
    R_meas: np.ndarray,
    R_ref: np.ndarray,
    discrete: np.ndarray,
    continuous_axes: np.ndarray,
) -> tuple[np.ndarray, float]:
    """The symmetric equivalent ``R_meas @ S`` (R_meas (3, 3)) closest to ``R_ref``, and its
    angle: :func:`closest_equivalents` of one rotation."""
    R, angle = closest_equivalents(R_meas[None], R_ref, discrete, continuous_axes)
    return R[0], float(angle[0])


def angles_to_means(
    R_meas: np.ndarray,
    R_means: np.ndarray,
    discrete: np.ndarray,
    continuous_axes: np.ndarray,
) -> np.ndarray:
    """The angle from each of C means to the symmetric equivalent of one rotation closest to
    it: :func:`closest_equivalent`'s angle, every component's in one batch.

    Args:
        R_meas: (3, 3). R_means: (C, 3, 3). discrete: (D, 3, 3) with the identity.
        continuous_axes: (A, 3) unit, A = 0 or 1.
    Returns:
        (C,) radians.
    """
    candidates = np.einsum("ij,djk->dik", R_meas, discrete)  # (D, 3, 3)
    relative = np.einsum("cji,djk->cdik", R_means, candidates)  # (C, D, 3, 3) R_mean^T cand
    if len(continuous_axes):
        a = continuous_axes[0]
        theta = _axis_angle_optimum(relative, a)  # (C, D)
        relative = relative @ so3_exp(theta[..., None] * a)
    return rotation_angle(relative).min(axis=1)


class RotationMixture:
    """The max-mixture of one object (see the module docstring)."""

    def __init__(
        self,
        discrete: np.ndarray | None = None,
        continuous_axes: np.ndarray | None = None,
        config: MixtureConfig | None = None,
    ):
        self.discrete = np.eye(3)[None] if discrete is None else np.asarray(discrete)[:, :3, :3]
        if not np.allclose(self.discrete[0], np.eye(3)):
            raise ValueError("RotationMixture: the first discrete symmetry must be the identity")
        self.continuous_axes = (
            np.zeros((0, 3)) if continuous_axes is None else np.asarray(continuous_axes, float)
        )
        self.config = config or MixtureConfig()
        self.components: list[RotationComponent] = []

    @classmethod
    def for_model(cls, model, config: MixtureConfig | None = None) -> RotationMixture:
        discrete = np.concatenate([np.eye(4)[None], model.symmetries_discrete])
        axes = np.array([c.axis for c in model.symmetries_continuous]).reshape(-1, 3)
        return cls(discrete, axes, config)

    def add(self, R_world_obj: np.ndarray, confidence: float) -> int:
        """Add one measurement; returns the index of the component that took it."""
        if not (np.isfinite(confidence) and confidence > 0):
            raise ValueError(f"rotation measurement: confidence must be > 0, got {confidence}")
        R = np.asarray(R_world_obj, dtype=np.float64)
        best, best_angle = -1, np.inf
        if self.components:
            angles = angles_to_means(
                R,
                np.array([comp.R_world_obj for comp in self.components]),
                self.discrete,
                self.continuous_axes,
            )
            best = int(np.argmin(angles))  # the first of equals
            best_angle = float(angles[best])
        if best < 0 or best_angle > np.deg2rad(self.config.gate_deg):
            self.components.append(RotationComponent(R.copy(), [(R.copy(), float(confidence))]))
            best = len(self.components) - 1
        else:
            comp = self.components[best]
            comp.members.append((R.copy(), float(confidence)))
            while len(comp.members) > self.config.max_members:
                _, c = comp.members.pop(0)
                comp.retired_confidence += c
                comp.retired += 1
                if comp._selection is not None:
                    comp._selection = tuple(a[1:] for a in comp._selection)
        self._refine(self.components[best])
        return best

    @property
    def weights(self) -> np.ndarray:
        c = np.array([comp.confidence for comp in self.components])
        return c / c.sum() if len(c) else c

    def best(self) -> RotationComponent | None:
        """The component with the largest weight (the earliest among equals)."""
        if not self.components:
            return None
        return self.components[int(np.argmax(self.weights))]

    def _refine(self, comp: RotationComponent) -> None:
        cfg = self.config
        R_mean = comp.R_world_obj
        info_scale = 1.0 / np.deg2rad(cfg.sigma_deg) ** 2
        R_members = np.array([R for R, _ in comp.members])  # (M, 3, 3)
        conf = np.array([c for _, c in comp.members])  # (M,)
        for _ in range(cfg.max_iterations):
            R_eq = self._equivalents(comp, R_members, R_mean)
            r = so3_log(R_eq @ R_mean.T)  # (M, 3)
            # normal equations with J_k = J_r^-1(r_k): J^T J in closed form, and J^T r = r
            H = np.einsum("m,mij->ij", conf, so3_jacobian_inv_gram(r)) + 1e-9 * np.eye(3)
            g = conf @ r
            delta = np.linalg.solve(H, g)
            R_mean = so3_exp(delta) @ R_mean
            step = float(np.linalg.norm(delta))
            # exp(delta) turns the mean by |delta| (at most; less only beyond pi)
            self._moved_by(comp, step)
            if step < cfg.tolerance_rad:
                break
        # re-orthonormalise against drift
        U, _, Vt = np.linalg.svd(R_mean)
        comp.R_world_obj = U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt
        self._moved(comp, R_mean, comp.R_world_obj)
        cov = np.linalg.inv(H * info_scale)
        for a in self.continuous_axes:
            a_world = comp.R_world_obj @ a
            P = np.eye(3) - np.outer(a_world, a_world)
            cov = P @ cov @ P + UNIFORM_ANGLE_VAR * np.outer(a_world, a_world)
        comp.cov = 0.5 * (cov + cov.T)

    def _equivalents(
        self, comp: RotationComponent, R_members: np.ndarray, R_mean: np.ndarray
    ) -> np.ndarray:
        """(M, 3, 3) every member's equivalent closest to ``R_mean``.

        With discrete symmetries only, a member's choice is kept while the mean has moved by
        less than half its margin (:func:`discrete_selection`) and recomputed otherwise: the
        same choice as a full search, at a fraction of the cost (the gear's 36 equivalents x
        50 members were most of the estimator's time)."""
        if len(self.continuous_axes):
            return closest_equivalents(R_members, R_mean, self.discrete, self.continuous_axes)[0]
        M = len(R_members)
        sel = comp._selection
        if sel is None or len(sel[0]) > M:
            sel = (np.zeros(0, int), np.zeros(0), np.zeros(0))
        k, margin, moved = (
            np.concatenate([a, np.full(M - len(a), v)])
            for a, v in zip(sel, (0, -np.inf, 0.0), strict=True)
        )
        stale = margin <= 2.0 * moved + 1e-9
        if np.any(stale):
            k[stale], margin[stale] = discrete_selection(R_members[stale], R_mean, self.discrete)
            moved[stale] = 0.0
        comp._selection = (k, margin, moved)
        return R_members @ self.discrete[k]

    @staticmethod
    def _moved(comp: RotationComponent, R_old: np.ndarray, R_new: np.ndarray) -> None:
        RotationMixture._moved_by(comp, float(rotation_angle(R_new @ R_old.T)))

    @staticmethod
    def _moved_by(comp: RotationComponent, step: float) -> None:
        if comp._selection is not None:
            k, margin, moved = comp._selection
            comp._selection = (k, margin, moved + step)
