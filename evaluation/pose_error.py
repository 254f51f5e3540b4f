"""Pose errors exactly as bop_toolkit defines them, plus ADD-sym, our headline error.

Every function equals the bop_toolkit function named in its docstring (``bop_toolkit_lib.
pose_error`` and ``bop_toolkit_lib.misc``); ``tests/evaluation/test_evaluation.py`` checks them
against values computed by bop_toolkit itself (``../shared/reference/bop_pose_errors.json``). The
functions are unit-agnostic: the points, the translations and the symmetries' translations must
share one unit (metres inside posefuse, millimetres in BOP files).

Poses are 4x4 ``T_cam_obj`` (``T_est`` the estimate, ``T_gt`` the truth); ``pts`` are the
model's evaluation points in the object frame, (N, 3); ``symmetries`` are the (S, 4, 4)
transformations of :func:`bop_symmetry_transformations`, the identity among them.

- ADD: mean distance between corresponding points. Punishes a symmetric answer.
- ADI (ADD-S): mean distance from each true point to the closest estimated point. Forgives
  rotations that keep the silhouette roughly in place: a random rotation with the right center
  passes 0.1 d for a large share of compact parts, so it is never our headline.
- ADD-sym: ADD against the truth moved by the symmetry closest to the estimate (the minimum over
  the symmetry transformations). As strict as ADD, without punishing an answer that is right up
  to a symmetry. This is the paper's ADD < 0.1 d made meaningful for symmetric parts.
- MSSD: as ADD-sym, with the maximum instead of the mean distance.
- MSPD: as MSSD, on the points' projections (pixels).
"""

from __future__ import annotations

import weakref

import numpy as np
from scipy.spatial import cKDTree

# bop_toolkit's default for the discretisation of continuous symmetries: consecutive steps move
# the point farthest from the axis by at most 1% of the diameter.
MAX_SYM_DISC_STEP = 0.01


def transform_points(T: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """T: (..., 4, 4); pts: (N, 3) -> (..., N, 3). ``misc.transform_pts_Rt`` with a batch."""
    T = np.asarray(T, dtype=np.float64)
    return np.einsum("...ij,nj->...ni", T[..., :3, :3], pts) + T[..., None, :3, 3]


def project_points(K: np.ndarray, T: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """K: (3, 3); T: (..., 4, 4); pts: (N, 3) -> (..., N, 2) pixels. ``misc.project_pts``."""
    p = transform_points(T, pts) @ np.asarray(K, dtype=np.float64).T
    return p[..., :2] / p[..., 2:3]


def _axis_rotation(angles: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """(A,) angles about a unit axis -> (A, 3, 3), as ``transformations.rotation_matrix``."""
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    s, c = np.sin(angles)[:, None, None], np.cos(angles)[:, None, None]
    cross = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return c * np.eye(3) + (1.0 - c) * np.outer(axis, axis) + s * cross


def bop_symmetry_transformations(
    symmetries_discrete: np.ndarray,
    continuous_axes: list[tuple[np.ndarray, np.ndarray]] | tuple = (),
    max_sym_disc_step: float = MAX_SYM_DISC_STEP,
) -> np.ndarray:
    """All symmetry transformations, ``misc.get_symmetry_transformations``.

    Two discretisations exist on purpose: this one is bop_toolkit's, to the bit, so the pose
    errors are the benchmark's, while the method's own
    (:func:`estimator.core.symmetry.symmetry_transforms`, for templates and matching) may step
    differently without moving the measure.

    Args:
        symmetries_discrete: (D, 4, 4) discrete symmetries without the identity (BOP's
            ``symmetries_discrete``, reshaped).
        continuous_axes: (axis (3,), offset (3,)) pairs (BOP's ``symmetries_continuous``); the
            offset in the unit of the translations.
        max_sym_disc_step: BOP's parameter: ``ceil(pi / step)`` rotations per continuous axis.

    Returns:
        (S, 4, 4): the identity and the discrete symmetries, each combined with every step of
        each continuous axis (``R = R_cont R_disc``, ``t = R_cont t_disc + t_cont``), in
        bop_toolkit's order.
    """
    disc = [np.eye(4)] + [
        np.asarray(d, dtype=np.float64).reshape(4, 4) for d in symmetries_discrete
    ]
    cont = []
    for axis, offset in continuous_axes:
        n_steps = int(np.ceil(np.pi / max_sym_disc_step))
        R = _axis_rotation(np.arange(n_steps) * (2.0 * np.pi / n_steps), axis)
        offset = np.asarray(offset, dtype=np.float64).reshape(3)
        T = np.tile(np.eye(4), (n_steps, 1, 1))
        T[:, :3, :3] = R
        T[:, :3, 3] = offset - R @ offset
        cont.extend(T)
    if not cont:
        return np.stack(disc)
    return np.stack([c @ d for d in disc for c in cont])


def eval_symmetries(model) -> np.ndarray:
    """(S, 4, 4) the symmetry transformations of ``model``'s pose errors (an
    ``estimator.core.objects.ObjectModel``), metres: :func:`bop_symmetry_transformations` with
    ``max_sym_disc_step = 0.01``, identity first; made once per model."""
    cached = _EVAL_SYMMETRIES.get(model)
    if cached is None:
        cached = _EVAL_SYMMETRIES[model] = bop_symmetry_transformations(
            model.symmetries_discrete,
            [(np.asarray(c.axis), np.asarray(c.offset)) for c in model.symmetries_continuous],
        )
    return cached


_EVAL_SYMMETRIES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # model -> (S, 4, 4)


def add(T_est: np.ndarray, T_gt: np.ndarray, pts: np.ndarray) -> float:
    """ADD, ``pose_error.add``. T_est, T_gt: (4, 4); pts: (N, 3)."""
    diff = transform_points(T_est, pts) - transform_points(T_gt, pts)
    return float(np.linalg.norm(diff, axis=1).mean())


def adi(T_est: np.ndarray, T_gt: np.ndarray, pts: np.ndarray) -> float:
    """ADI (ADD-S), ``pose_error.adi``: for each point under the true pose, the distance to the
    closest point under the estimated pose, averaged over the true points."""
    dist, _ = cKDTree(transform_points(T_est, pts)).query(transform_points(T_gt, pts), k=1)
    return float(dist.mean())


def _symmetric_distances(
    T_est: np.ndarray, T_gt: np.ndarray, pts: np.ndarray, symmetries: np.ndarray
) -> np.ndarray:
    """(S, N) distances between the estimated points and the truth moved by each symmetry."""
    est = transform_points(T_est, pts)
    gt_sym = transform_points(np.asarray(T_gt, dtype=np.float64) @ symmetries, pts)
    return np.linalg.norm(gt_sym - est, axis=2)


def add_sym(T_est: np.ndarray, T_gt: np.ndarray, pts: np.ndarray, symmetries: np.ndarray) -> float:
    """ADD-sym: ``min over S of pose_error.add(T_est, T_gt @ S)``. Not a bop_toolkit function:
    ``pose_error.mssd`` with the mean instead of the max distance. Equals ADD for an object
    without symmetries (``symmetries`` holds the identity only)."""
    return float(_symmetric_distances(T_est, T_gt, pts, symmetries).mean(axis=1).min())


def mssd(T_est: np.ndarray, T_gt: np.ndarray, pts: np.ndarray, symmetries: np.ndarray) -> float:
    """MSSD, ``pose_error.mssd``: the maximum point distance, minimised over the symmetries."""
    return float(_symmetric_distances(T_est, T_gt, pts, symmetries).max(axis=1).min())


def mspd(
    T_est: np.ndarray, T_gt: np.ndarray, K: np.ndarray, pts: np.ndarray, symmetries: np.ndarray
) -> float:
    """MSPD, ``pose_error.mspd``: the maximum distance of the projections (pixels), minimised
    over the symmetries. K: (3, 3)."""
    est = project_points(K, T_est, pts)
    gt_sym = project_points(K, np.asarray(T_gt, dtype=np.float64) @ symmetries, pts)
    return float(np.linalg.norm(gt_sym - est, axis=2).max(axis=1).min())
