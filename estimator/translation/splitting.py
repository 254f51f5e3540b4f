"""Splitting a track whose views disagree.

A track founded from a wrong pair, or gated onto a neighbour's detection while its depth was
still uncertain, ends up holding views of two parts. The robust estimate follows the majority;
the views it cannot explain (squared Mahalanobis residual above ``outlier_chi2``) leave the
track, provided at least ``min_inliers`` views remain. When two or more views leave and agree
with each other, they make a track of their own (the tracker founds it); otherwise they are
dropped.

Pure functions; the tracker applies the split.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from posefuse.estimator.translation.gaussian import TranslationEstimate


@dataclass(frozen=True)
class SplitConfig:
    outlier_chi2: float = 25.0  # a view's residual beyond 5 sigma
    min_inliers: int = 3  # views that must remain

    def __post_init__(self) -> None:
        if self.outlier_chi2 <= 0 or self.min_inliers < 2:
            raise ValueError(f"invalid split config: {self}")


def outlier_views(estimate: TranslationEstimate, config: SplitConfig) -> np.ndarray:
    """(N,) bool: the views that leave the track; all False when the track keeps them."""
    out = np.asarray(estimate.chi2) > config.outlier_chi2
    if not out.any() or np.count_nonzero(~out) < config.min_inliers:
        return np.zeros(len(out), bool)
    return out
