"""Merging tracks that converge on one 3D position.

Two tracks of one class may hold the same part: a missed view let a second track found, or a
split detection did. Once both are triangulated they converge. Two tracks merge when

- their translations agree within their covariances: ``d^T (P_a + P_b)^-1 d`` at most
  ``gate_chi2`` (3 degrees of freedom);
- their centers are closer than ``max_distance_rel`` x the part's diameter (two distinct
  parts cannot overlap that much, whatever the covariances say);
- no view saw both as distinct: in every view that observed both, their centers agree within
  ``same_view_gate_chi2``.

Pure functions; the tracker combines the chosen pairs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from posefuse.estimator.translation.gaussian import CenterObservations


@dataclass(frozen=True)
class MergeConfig:
    gate_chi2: float = 11.34  # chi2(3) at p = 0.01
    max_distance_rel: float = 0.25  # x diameter
    same_view_gate_chi2: float = 16.0

    def __post_init__(self) -> None:
        if self.gate_chi2 <= 0 or self.max_distance_rel <= 0:
            raise ValueError(f"invalid merge config: {self}")


@dataclass(frozen=True, eq=False)
class MergeCandidate:
    """What merging needs of a track: t_world_obj (3,), cov (3, 3), its views."""

    key: str
    t_world_obj: np.ndarray
    cov: np.ndarray
    obs: CenterObservations


def seen_apart(a: CenterObservations, b: CenterObservations, gate_chi2: float) -> bool:
    """True when some view observed both tracks at centers that differ beyond the gate."""
    common = np.intersect1d(a.stamp_ns, b.stamp_ns)
    for stamp in common:
        for i in np.flatnonzero(a.stamp_ns == stamp):
            for j in np.flatnonzero(b.stamp_ns == stamp):
                r = a.uv[i] - b.uv[j]
                cov = np.linalg.inv(a.info[i]) + np.linalg.inv(b.info[j])
                if r @ np.linalg.solve(cov, r) > gate_chi2:
                    return True
    return False


def merge_chi2(a: MergeCandidate, b: MergeCandidate) -> float:
    d = a.t_world_obj - b.t_world_obj
    return float(d @ np.linalg.solve(a.cov + b.cov, d))


def merge_pairs(
    tracks: list[MergeCandidate], diameter: float, config: MergeConfig
) -> list[tuple[str, str]]:
    """(a, b) key pairs of one class's tracks to merge, best first; each track in at most one
    pair."""
    scored = []
    for i, a in enumerate(tracks):
        for b in tracks[i + 1 :]:
            if np.linalg.norm(a.t_world_obj - b.t_world_obj) > config.max_distance_rel * diameter:
                continue
            chi2 = merge_chi2(a, b)
            if chi2 > config.gate_chi2:
                continue
            if seen_apart(a.obs, b.obs, config.same_view_gate_chi2):
                continue
            scored.append((chi2, a.key, b.key))
    out, used = [], set()
    for _, ka, kb in sorted(scored):
        if ka in used or kb in used:
            continue
        used |= {ka, kb}
        out.append((ka, kb))
    return out
