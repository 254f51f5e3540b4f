"""Measures of the back end against ground truth: association quality, translation error, NEES
of the translation and of the published pose.

Detections carry the index of the true instance they came from (-1 for a false positive). A
track's identity is the instance most of its detections came from.

- precision: of the detections in confirmed tracks, the fraction that belong to the track's
  instance;
- recall: of all true detections, the fraction that ended in the confirmed track holding most
  of their instance's detections (a split track loses the smaller part).
"""

from __future__ import annotations

from collections import Counter, defaultdict
from dataclasses import dataclass

import numpy as np

from posefuse.estimator.core.geometry import so3_log
from posefuse.estimator.rotation.mixture import closest_equivalent


@dataclass(frozen=True)
class AssociationScore:
    precision: float
    recall: float
    n_true_detections: int
    n_in_confirmed_tracks: int


def track_identities(members: dict[str, list[int]]) -> dict[str, int]:
    """object_id -> the instance most of its detections came from (-1 if false positives)."""
    return {oid: Counter(m).most_common(1)[0][0] for oid, m in members.items() if m}


def association_score(
    members: dict[str, list], confirmed: set[str], n_true_detections: int
) -> AssociationScore:
    """members: object_id -> the instance (any hashable; -1 = false positive) of each of its
    detections, in order."""
    identity = track_identities(members)
    in_confirmed = [(oid, x) for oid in confirmed for x in members.get(oid, [])]
    correct = sum(x == identity[oid] and x != -1 for oid, x in in_confirmed)
    # the main track of each instance: the confirmed track holding most of its detections
    holdings: dict[object, Counter] = defaultdict(Counter)
    for oid, x in in_confirmed:
        if x != -1:
            holdings[x][oid] += 1
    recalled = sum(c.most_common(1)[0][1] for c in holdings.values())
    return AssociationScore(
        precision=correct / len(in_confirmed) if in_confirmed else float("nan"),
        recall=recalled / n_true_detections if n_true_detections else float("nan"),
        n_true_detections=n_true_detections,
        n_in_confirmed_tracks=len(in_confirmed),
    )


def update_members(
    members: dict[str, list],
    tracks: dict,
    merged: tuple[tuple[str, str], ...],
    labels: dict[int, list],
) -> None:
    """Refresh ``members`` (object_id -> instance of each detection) after an update.

    A track's detections may come from earlier views (founding pairs, held detections,
    merges), so they are read from the tracks (``track.detections``: (stamp_ns, index)
    pairs) and labelled through ``labels`` (stamp_ns -> the instance of each detection of
    that view). Tracks merged away leave; dropped ones keep their last members.
    """
    for absorbed, _ in merged:
        members.pop(absorbed, None)
    for oid, track in tracks.items():
        members[oid] = [labels[s][j] for s, j in track.detections]


def nees(error: np.ndarray, cov: np.ndarray) -> float:
    """Normalised estimation error squared e^T P^-1 e (expected value: the dimension)."""
    return float(error @ np.linalg.solve(cov, error))


def pose_nees(
    T_world_est: np.ndarray,
    cov: np.ndarray,
    T_world_true: np.ndarray,
    discrete: np.ndarray,
    continuous_axes: np.ndarray,
) -> tuple[float, float]:
    """The NEES of a published pose's translation and of its rotation (each expected 3 when
    the covariance is honest; median 2.37).

    The rotation error is the left perturbation, world frame, taking the symmetric equivalent
    of the estimate closest to the truth onto the truth (the convention of the published
    covariance: docs/conventions.md), so a symmetric part is not charged for its symmetry.

    Args:
        T_world_est, T_world_true: (4, 4); cov: (6, 6) over x, y, z, rot_x, rot_y, rot_z;
        discrete: (D, 3, 3) object-frame symmetries with the identity; continuous_axes: (A, 3).
    Returns:
        (translation NEES, rotation NEES).
    """
    R_eq, _ = closest_equivalent(
        T_world_est[:3, :3], T_world_true[:3, :3], discrete, continuous_axes
    )
    e_t = T_world_true[:3, 3] - T_world_est[:3, 3]
    e_R = so3_log(T_world_true[:3, :3] @ R_eq.T)
    return nees(e_t, cov[:3, :3]), nees(e_R, cov[3:, 3:])
