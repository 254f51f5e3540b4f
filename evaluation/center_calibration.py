"""The front end's centre covariances made as honest as their detection score: per score bin,
the factor its covariances must be multiplied by for the 2D NEES ``e^T Sigma^-1 e`` of centres
matched to the truth to have its expected value (2 for a 2D Gaussian).

The factor is fitted on the trimmed mean, the TRIM share of the smallest NEES of a bin, against
the mean of a chi-square variable trimmed the same way: a few centres on the wrong part are the
association gates' to refuse, not the covariance's to cover. Never below 1. Used by
``python -m posefuse.bench.center_calibration`` (the shipped model's factors) and by the
training's calibration (:func:`posefuse.sim.train.calibrate_by_score`, a part set's)."""

from __future__ import annotations

import numpy as np
from scipy import stats

TRIM = 0.95  # the share of the smallest NEES the factors are fitted on
# the shipped model's bins (``center_cov_by_score``): a score's upper edges
DEFAULT_EDGES = (0.4, 0.5, 0.6, 0.7, 0.8, 0.9)


def trimmed_chi2_mean(dof: int = 2, keep: float = TRIM) -> float:
    """The mean of a chi-square variable with ``dof`` degrees of freedom below its ``keep``
    quantile."""
    q = stats.chi2.ppf(keep, dof)
    # E[X; X < q] = dof * P(chi2_{dof+2} < q)
    return dof * stats.chi2.cdf(q, dof + 2) / keep


def nees_table(scores: np.ndarray, nees: np.ndarray, edges) -> list[dict]:
    """One row per score bin [lo, hi) of ``edges`` (ascending within (0, 1), the last bin closed
    at 1): n, and where n > 0 the mean, median and trimmed mean NEES and the bin's factor.

    Args:
        scores: (N,) detection scores in [0, 1].
        nees: (N,) 2D NEES of those detections' centres against the truth.
    """
    scores = np.asarray(scores, dtype=np.float64).reshape(-1)
    nees = np.asarray(nees, dtype=np.float64).reshape(-1)
    if scores.shape != nees.shape:
        raise ValueError(f"scores {scores.shape} and nees {nees.shape} differ in length")
    edges = [float(e) for e in edges]
    if edges != sorted(edges) or not all(0.0 < e < 1.0 for e in edges):
        raise ValueError(f"score edges must increase within (0, 1), got {edges}")
    bounds = [0.0, *edges, 1.0 + 1e-9]
    target = trimmed_chi2_mean()
    rows = []
    for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
        sel = nees[(scores >= lo) & (scores < hi)]
        row = {"lo": lo, "hi": min(hi, 1.0), "n": int(len(sel))}
        if len(sel):
            kept = np.sort(sel)[: max(1, int(np.ceil(TRIM * len(sel))))]
            row.update(
                mean=float(sel.mean()),
                median=float(np.median(sel)),
                trimmed_mean=float(kept.mean()),
                factor=float(max(1.0, kept.mean() / target)),
            )
        rows.append(row)
    return rows


def factors_by_score(
    scores: np.ndarray, nees: np.ndarray, edges=DEFAULT_EDGES, min_matches: int = 10
) -> list[list[float]]:
    """The card's ``center_cov_by_score``: [[upper score, factor], ...] ascending, fitted per bin
    of :func:`nees_table` and made never to fall as the score falls (a lower score is never
    more certain). A bin with fewer than ``min_matches`` centres takes the factor of the bin
    above it (1 at the top), so a few matches decide nothing."""
    rows = nees_table(scores, nees, edges)
    out, above = [], 1.0
    for row in reversed(rows):
        fitted = row["factor"] if row["n"] >= min_matches else above
        above = max(above, fitted)
        out.append([float(row["hi"]), round(float(above), 3)])
    return out[::-1]
