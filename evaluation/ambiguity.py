"""How honest the published ambiguity is: of the poses published as unambiguous, how many are
right; of those published as ambiguous, how often the truth is the pose or one of the turns
published beside it (:class:`~estimator.tracker.published.AlternativeTurn`)."""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from posefuse.evaluation.eval_points import eval_points
from posefuse.evaluation.pose_error import add_sym, eval_symmetries


@dataclass(frozen=True)
class AmbiguityRow:
    """A published pose against its instance after ``n_views`` views: its ambiguity (the
    largest odds of a near-symmetric turn), whether it was published as ambiguous (with
    alternatives), whether it is right (ADD-sym < 0.1 d), and whether the truth is the pose or
    one of its published alternatives (at the pose's translation)."""

    n_views: int
    obj_id: int
    ambiguity: float
    ambiguous: bool
    right: bool
    right_among_turns: bool


def ambiguity_rows(scored, catalog, n_views: int) -> list[AmbiguityRow]:
    """One :class:`AmbiguityRow` per (ObjectEstimate, T_world_true (4, 4)) of ``scored``."""
    out = []
    for e, T_true in scored:
        model = catalog[e.class_id]
        points, symmetries = eval_points(model), eval_symmetries(model)
        limit = 0.1 * model.diameter
        right = bool(add_sym(e.T_world_obj, T_true, points, symmetries) < limit)
        among = right
        for alt in e.alternatives:
            T = e.T_world_obj.copy()
            T[:3, :3] = Rotation.from_quat(alt.q).as_matrix()
            among = among or bool(add_sym(T, T_true, points, symmetries) < limit)
        out.append(AmbiguityRow(n_views, e.class_id, e.ambiguity, e.ambiguous, right, among))
    return out


def write_ambiguity(path: str | Path, rows: list[AmbiguityRow]) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(["n_views", "obj_id", "ambiguity", "ambiguous", "right", "right_among_turns"])
        for r in rows:
            w.writerow(
                [
                    r.n_views,
                    r.obj_id,
                    f"{r.ambiguity:.6f}",
                    int(r.ambiguous),
                    int(r.right),
                    int(r.right_among_turns),
                ]
            )
    return path


def _share(hits: int, n: int) -> str:
    return f"{100 * hits / n:.1f}% ({hits}/{n})" if n else "-"


def ambiguity_markdown(rows: list[AmbiguityRow], catalog) -> str:
    """Per number of views and object, then all: poses published unambiguous and the share
    right; published ambiguous, the share right, and the share whose truth is one of the
    published turns."""
    lines = [
        "| views | object | unambiguous | right | ambiguous | right | truth among its turns |",
        "|---|---|---|---|---|---|---|",
    ]
    for n in sorted({r.n_views for r in rows}):
        at_n = [r for r in rows if r.n_views == n]
        groups = {o: [r for r in at_n if r.obj_id == o] for o in sorted({r.obj_id for r in at_n})}
        groups["**all**"] = at_n
        for key, group in groups.items():
            plain = [r for r in group if not r.ambiguous]
            unsure = [r for r in group if r.ambiguous]
            name = key if isinstance(key, str) else catalog[key].name
            lines.append(
                f"| {n} | {name} | {len(plain)} | {_share(sum(r.right for r in plain), len(plain))}"
                f" | {len(unsure)} | {_share(sum(r.right for r in unsure), len(unsure))} | "
                f"{_share(sum(r.right_among_turns for r in unsure), len(unsure))} |"
            )
    return "\n".join(lines)


def rates_at(rows: list[AmbiguityRow], min_odds: float) -> tuple[float, int, float]:
    """For a threshold ``min_odds`` on the recorded ambiguity: the share right among the poses
    it leaves unambiguous, how many it calls ambiguous, and the share of those right (the
    threshold's sweep on a tuning set; the alternatives themselves are not re-derived)."""
    amb = np.array([r.ambiguity >= min_odds for r in rows], bool)
    right = np.array([r.right for r in rows], bool)
    plain = right[~amb]
    return (
        float(plain.mean()) if len(plain) else float("nan"),
        int(amb.sum()),
        float(right[amb].mean()) if amb.any() else float("nan"),
    )
