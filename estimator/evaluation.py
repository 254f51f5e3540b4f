"""Pose errors as bop_toolkit defines them, BOP result files, and the ADD(-S) detection rate.

- ADD: mean distance between the model points under the estimated and the true pose.
- ADI (ADD-S): mean distance from each estimated point to the closest true point.
- MSSD: the maximum point distance, minimised over the object's symmetries.
- ADD(-S): ADI for objects with any symmetry, ADD otherwise (as the ROBI and BOP papers do).

The detection rate follows the paper's protocol: an annotated instance with ``visib_fract``
above ``min_visib`` is found when an estimate of its class in that view has error below
``threshold * diameter``. Estimates are matched greedily in order of decreasing score, each to
the unmatched annotation (of any visibility) with the smallest error, so one estimate finds at
most one instance; estimates matched to barely visible instances neither count nor hurt.
"""

from __future__ import annotations

import csv
import json
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from estimator.errors import ResultsError

RESULTS_HEADER = ["scene_id", "im_id", "obj_id", "score", "R", "t", "time"]


def _apply(T: np.ndarray, pts: np.ndarray) -> np.ndarray:
    return pts @ T[:3, :3].T + T[:3, 3]


def add_error(T_est: np.ndarray, T_gt: np.ndarray, pts: np.ndarray) -> float:
    """ADD. T_est, T_gt: (4, 4); pts: (N, 3) model points, same unit as the translations."""
    return float(np.linalg.norm(_apply(T_est, pts) - _apply(T_gt, pts), axis=1).mean())


def adi_error(T_est: np.ndarray, T_gt: np.ndarray, pts: np.ndarray) -> float:
    """ADI (ADD-S): mean closest-point distance from estimated to true model points."""
    dist, _ = cKDTree(_apply(T_gt, pts)).query(_apply(T_est, pts), k=1)
    return float(dist.mean())


def mssd_error(
    T_est: np.ndarray, T_gt: np.ndarray, pts: np.ndarray, symmetries: np.ndarray
) -> float:
    """MSSD. symmetries: (S, 4, 4) with the identity, continuous axes discretised."""
    est = _apply(T_est, pts)
    errors = [np.linalg.norm(est - _apply(T_gt @ S, pts), axis=1).max() for S in symmetries]
    return float(min(errors))


@dataclass(frozen=True, eq=False)
class PoseResult:
    """One estimate in one view: T_cam_obj (4, 4) metres; score higher is better; time seconds."""

    scene_id: int
    im_id: int
    obj_id: int
    score: float
    T_cam_obj: np.ndarray
    time: float = -1.0


def write_results(path: str | Path, results: list[PoseResult]) -> Path:
    """Write a BOP results CSV (R row-major, t in millimetres)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as f:
        writer = csv.writer(f, lineterminator="\n")
        writer.writerow(RESULTS_HEADER)
        for r in results:
            R = " ".join(f"{v:.12g}" for v in r.T_cam_obj[:3, :3].reshape(-1))
            t = " ".join(f"{v * 1000:.9g}" for v in r.T_cam_obj[:3, 3])
            writer.writerow([r.scene_id, r.im_id, r.obj_id, f"{r.score:.9g}", R, t, f"{r.time:g}"])
    return path


def read_results(path: str | Path) -> list[PoseResult]:
    """Read a BOP results CSV; a malformed row raises ResultsError naming the file and row."""
    path = Path(path)
    if not path.is_file():
        raise ResultsError(path, None, "file not found")
    results = []
    with path.open(newline="") as f:
        reader = csv.reader(f)
        header = next(reader, None)
        if header is None or [h.strip() for h in header] != RESULTS_HEADER:
            raise ResultsError(path, 1, f"header must be {','.join(RESULTS_HEADER)}")
        for row_number, row in enumerate(reader, start=2):
            if not row:
                continue
            if len(row) != len(RESULTS_HEADER):
                raise ResultsError(path, row_number, f"{len(row)} fields, expected 7")
            try:
                scene_id, im_id, obj_id = (int(v) for v in row[:3])
                score, time = float(row[3]), float(row[6])
                R = np.array([float(v) for v in row[4].split()])
                t = np.array([float(v) for v in row[5].split()])
            except ValueError as exc:
                raise ResultsError(path, row_number, f"not a number ({exc})") from None
            if R.size != 9 or t.size != 3:
                raise ResultsError(path, row_number, "R needs 9 numbers and t 3")
            if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t)) and np.isfinite(score)):
                raise ResultsError(path, row_number, "R, t and score must be finite")
            R = R.reshape(3, 3)
            if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0:
                raise ResultsError(path, row_number, "R is not a rotation matrix")
            T = np.eye(4)
            T[:3, :3] = R
            T[:3, 3] = t / 1000.0
            results.append(PoseResult(scene_id, im_id, obj_id, score, T, time))
    return results


def write_targets(path: str | Path, targets: list[tuple[int, int]]) -> Path:
    """The views a results file is scored on, as BOP's ``test_targets`` (one entry per view)."""
    path = Path(path)
    entries = [{"scene_id": s, "im_id": i} for s, i in sorted(set(targets))]
    path.write_text(json.dumps(entries, indent=1) + "\n")
    return path


def read_targets(path: str | Path) -> list[tuple[int, int]]:
    path = Path(path)
    if not path.is_file():
        raise ResultsError(path, None, "file not found")
    try:
        entries = json.loads(path.read_text())
        return [(int(e["scene_id"]), int(e["im_id"])) for e in entries]
    except (json.JSONDecodeError, UnicodeDecodeError, TypeError, KeyError, ValueError):
        raise ResultsError(path, None, "needs a JSON list of {scene_id, im_id}") from None


def ground_truth_results(dataset) -> list[PoseResult]:
    """The annotations of every view as results with score 1 (a check of the data path)."""
    return [
        PoseResult(view.scene_id, view.im_id, gt.obj_id, 1.0, gt.T_cam_obj, 0.0)
        for view in dataset.views()
        for gt in view.gts
    ]


@dataclass
class ObjectScore:
    obj_id: int
    name: str
    n_instances: int = 0  # annotated instances above min_visib
    n_found: int = 0
    n_estimates: int = 0

    @property
    def rate(self) -> float:
        return self.n_found / self.n_instances if self.n_instances else float("nan")


@dataclass
class EvaluationReport:
    metric: str
    threshold: float
    min_visib: float
    objects: dict[int, ObjectScore] = field(default_factory=dict)

    @property
    def n_instances(self) -> int:
        return sum(o.n_instances for o in self.objects.values())

    @property
    def n_found(self) -> int:
        return sum(o.n_found for o in self.objects.values())

    @property
    def rate(self) -> float:
        return self.n_found / self.n_instances if self.n_instances else float("nan")

    def to_markdown(self) -> str:
        name = "ADD(-S)" if self.metric == "adds" else "MSSD"
        lines = [
            f"| obj_id | name | instances (visib > {self.min_visib:g}) | estimates | found | "
            f"{name}-{self.threshold:g}d |",
            "|---|---|---|---|---|---|",
        ]
        for o in self.objects.values():
            lines.append(
                f"| {o.obj_id} | {o.name} | {o.n_instances} | {o.n_estimates} | {o.n_found} | "
                f"{_percent(o.rate)} |"
            )
        lines.append(
            f"| all | | {self.n_instances} | {sum(o.n_estimates for o in self.objects.values())}"
            f" | {self.n_found} | {_percent(self.rate)} |"
        )
        return "\n".join(lines)

    def to_json(self) -> dict:
        return {
            "metric": self.metric,
            "threshold": self.threshold,
            "min_visib": self.min_visib,
            "rate": self.rate,
            "objects": {
                str(o.obj_id): {
                    "name": o.name,
                    "instances": o.n_instances,
                    "estimates": o.n_estimates,
                    "found": o.n_found,
                    "rate": o.rate,
                }
                for o in self.objects.values()
            },
        }


def _percent(rate: float) -> str:
    return "-" if np.isnan(rate) else f"{100 * rate:.1f}%"


def pose_error(model, T_est: np.ndarray, T_gt: np.ndarray, metric: str = "adds") -> float:
    """ADD(-S) or MSSD of one estimate for an ObjectModel, metres."""
    if metric == "adds":
        fn = adi_error if model.is_symmetric else add_error
        return fn(T_est, T_gt, model.points)
    if metric == "mssd":
        return mssd_error(T_est, T_gt, model.points, model.symmetry_transforms())
    raise ValueError(f"metric must be 'adds' or 'mssd', got {metric!r}")


def evaluate(
    dataset,
    results: list[PoseResult],
    threshold: float = 0.1,
    min_visib: float = 0.75,
    metric: str = "adds",
    targets: list[tuple[int, int]] | None = None,
) -> EvaluationReport:
    """Detection rate per object of ``results`` on the annotated views of ``dataset``, or only
    on the ``targets`` views ((scene_id, im_id) pairs)."""
    if metric not in ("adds", "mssd"):
        raise ValueError(f"metric must be 'adds' or 'mssd', got {metric!r}")
    report = EvaluationReport(metric, threshold, min_visib)
    for obj_id, model in dataset.catalog.items():
        report.objects[obj_id] = ObjectScore(obj_id, model.name)
    by_view: dict[tuple[int, int, int], list[PoseResult]] = defaultdict(list)
    for r in results:
        by_view[(r.scene_id, r.im_id, r.obj_id)].append(r)
    if targets is None:
        views = dataset.views()
    else:
        views = (dataset.scene(s).view(i) for s, i in sorted(set(targets)))
    for view in views:
        for obj_id, score in report.objects.items():
            gts = [g for g in view.gts if g.obj_id == obj_id]
            score.n_instances += sum(g.visib_fract > min_visib for g in gts)
            estimates = sorted(
                by_view.get((view.scene_id, view.im_id, obj_id), []), key=lambda r: -r.score
            )
            score.n_estimates += len(estimates)
            model = dataset.catalog[obj_id]
            limit = threshold * model.diameter
            free = set(range(len(gts)))
            for est in estimates:
                best, best_error = None, limit
                for k in free:
                    error = pose_error(model, est.T_cam_obj, gts[k].T_cam_obj, metric)
                    if error < best_error:
                        best, best_error = k, error
                if best is not None:
                    free.discard(best)
                    score.n_found += gts[best].visib_fract > min_visib
    return report
