"""What the published confidence is worth: accuracy and precision of the estimates kept above
a confidence threshold.

A robot that grasps only what it is sure of keeps the estimates whose ``confidence`` passes a
threshold. Each row scores the estimates of one checkpoint that pass it, as
:func:`evaluation.scores.evaluate` scores them all (ADD-sym < 0.1 d of the instances more than
75% visible, and found instances per estimate): what such a robot would find, and how often
what it reaches for is there.
"""

from __future__ import annotations

from dataclasses import dataclass

from posefuse.evaluation.scores import PoseResult, evaluate

THRESHOLDS = (0.0, 0.3, 0.5, 0.6, 0.7, 0.8, 0.9)
CONFIDENCE_LEGEND = (
    "The confirmed estimates whose published confidence is at least a threshold, scored as "
    "detection_rate.md scores them all (ADD-sym < 0.1 d of the instances more than 75% visible; "
    "precision: found instances per estimate kept): what a robot that acts only on those finds, "
    "and how often what it reaches for is there."
)


@dataclass(frozen=True)
class ConfidenceRow:
    """One checkpoint (``n_views``) at one ``threshold``: ``kept`` estimates pass it;
    ``add_sym`` and ``precision`` as ``EvaluationReport.total`` gives them (where none is kept,
    ADD-sym 0 and precision NaN)."""

    n_views: int
    threshold: float
    kept: int
    add_sym: float
    precision: float


def confidence_rows(
    dataset,
    results: dict[int, list[PoseResult]],
    targets: dict[int, list[tuple[int, int]]],
    thresholds: tuple[float, ...] = THRESHOLDS,
) -> list[ConfidenceRow]:
    """Per checkpoint (the keys of ``results``, with ``targets`` the views scored) and per
    threshold, the estimates whose score (the published confidence) is at least the threshold,
    scored. ``thresholds`` must be in [0, 1]."""
    if any(not 0.0 <= t <= 1.0 for t in thresholds):
        raise ValueError(f"confidence thresholds must be in [0, 1], got {thresholds}")
    rows = []
    for n, estimates in sorted(results.items()):
        if not targets.get(n):
            continue
        for t in thresholds:
            kept = [r for r in estimates if r.score >= t]
            total = evaluate(dataset, kept, targets=targets[n], metrics=("add_sym",)).total
            rows.append(ConfidenceRow(n, t, len(kept), total.rate(), total.precision()))
    return rows


def confidence_markdown(rows: list[ConfidenceRow]) -> str:
    """The rows as a table: a line per threshold, ADD-sym / precision per checkpoint."""
    views = sorted({r.n_views for r in rows})
    by = {(r.n_views, r.threshold): r for r in rows}
    thresholds = sorted({r.threshold for r in rows})
    header = " | ".join(f"{n} views: kept, ADD-sym, precision" for n in views)
    lines = [f"| confidence >= | {header} |", "|---|" + "---|" * len(views)]
    for t in thresholds:
        cells = []
        for n in views:
            r = by[(n, t)]
            cells.append(f"{r.kept}, {_pct(r.add_sym)}, {_pct(r.precision)}")
        lines.append(f"| {t:g} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _pct(x: float) -> str:
    return "-" if x != x else f"{100 * x:.1f}%"
