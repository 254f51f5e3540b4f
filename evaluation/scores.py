"""BOP result files, pose errors of ObjectModels, and detection rates with matching as BOP does.

Errors (``evaluation.pose_error``, equal to bop_toolkit's) are evaluated on each model's
``eval_points`` with its ``eval_symmetries`` (BOP's transformations, ``max_sym_disc_step =
0.01``). Every report gives, for the instances with ``visib_fract > min_visib`` (0.75, the
paper's protocol):

- **ADD-sym < 0.1 d**: the headline (the paper's ADD < 0.1 d, symmetric answers not punished);
- **MSSD < 0.1 d**, and **AR_MSSD**: BOP's mean recall over MSSD thresholds 0.05-0.5 d;
- **precision**: of the estimates, the share that found a scored instance (at ADD-sym < 0.1 d);
- **ADI < 0.1 d**, labelled lenient: it forgives wrong rotations (a random rotation with the
  true center passes for 15-64% of the instances of our parts, 34.5% in all, on the 12 bins of
  docs/performance.md; ADD-sym 3.0%) and is never a headline.

Matching, for each metric and threshold, as BOP's ``pose_matching.match_poses``: in each view
and class, estimates are visited in order of decreasing score; each takes the not yet matched
annotated instance (of any visibility) with the smallest error, and is a match when that error
is below the threshold. A match to an instance with ``visib_fract <= min_visib`` neither counts
nor hurts (BOP's invalid ground truth); an estimate that matches nothing is a false positive.
So a method that outputs several guesses per part pays for it in precision.
"""

from __future__ import annotations

import csv
import json
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from posefuse.estimator.core.errors import ResultsError
from posefuse.evaluation.eval_points import eval_points
from posefuse.evaluation.pose_error import eval_symmetries, transform_points

RESULTS_HEADER = ["scene_id", "im_id", "obj_id", "score", "R", "t", "time"]
METRICS = ("add_sym", "mssd", "adi")
HEADLINE = "add_sym"
METRIC_LABELS = {"add_sym": "ADD-sym", "mssd": "MSSD", "adi": "ADI (lenient)"}
AR_THRESHOLDS = tuple(round(0.05 * k, 2) for k in range(1, 11))  # of the diameter


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


def _check_metric(metric: str) -> None:
    if metric not in METRICS:
        raise ValueError(f"metric must be one of {', '.join(METRICS)}, got {metric!r}")


def error_matrix(
    model,
    T_est: np.ndarray,
    T_gt: np.ndarray,
    metric: str = HEADLINE,
    cutoff: float | None = None,
) -> np.ndarray:
    """(E, G) errors in metres of E estimates against G true poses of one ObjectModel.

    T_est: (E, 4, 4), T_gt: (G, 4, 4) ``T_cam_obj``. Equal, entry by entry, to
    ``evaluation.pose_error`` on ``model.eval_points`` and ``model.eval_symmetries``. With a
    ``cutoff`` (metres), ADD-sym and MSSD entries below it are exact and those at or above it are
    only known to be there (``inf``, or a value above the true one: symmetries whose lower bound
    passes the cutoff are not computed).
    """
    _check_metric(metric)
    T_est = np.asarray(T_est, dtype=np.float64).reshape(-1, 4, 4)
    T_gt = np.asarray(T_gt, dtype=np.float64).reshape(-1, 4, 4)
    pts = eval_points(model)
    out = np.full((len(T_est), len(T_gt)), np.inf)
    if out.size == 0:
        return out
    if metric == "adi":  # pose_error.adi: from each true point to the closest estimated one
        est = transform_points(T_est, pts)  # (E, N, 3)
        gt = transform_points(T_gt, pts)  # (G, N, 3)
        for e in range(len(T_est)):
            dist, _ = cKDTree(est[e]).query(gt.reshape(-1, 3), k=1)
            out[e] = dist.reshape(len(T_gt), -1).mean(axis=1)
        return out
    # Distances are invariant under rigid motion: |T_gt S p - T_est p| = |A p - p| with
    # A = inv(T_est) T_gt S, so each (estimate, truth, symmetry) costs one 3x3 map of the points.
    A = np.linalg.inv(T_est)[:, None, None] @ T_gt[None, :, None] @ eval_symmetries(model)
    M = A[..., :3, :3] - np.eye(3)  # (E, G, S, 3, 3)
    t = A[..., :3, 3]  # (E, G, S, 3)
    # the mean distance is at least the distance of the means (Jensen), and the max at least
    # the mean: a lower bound of both errors for every symmetry
    bound = np.linalg.norm(M @ pts.mean(axis=0) + t, axis=-1)  # (E, G, S)
    reduce = np.mean if metric == "add_sym" else np.max
    for e in range(len(T_est)):
        for g in range(len(T_gt)):
            keep = np.ones(bound.shape[2], dtype=bool) if cutoff is None else bound[e, g] < cutoff
            if not keep.any():
                continue
            diff = pts @ M[e, g, keep].transpose(0, 2, 1) + t[e, g, keep, None, :]  # (K, N, 3)
            out[e, g] = reduce(np.sqrt(np.einsum("knj,knj->kn", diff, diff)), axis=1).min()
    return out


def pose_error(model, T_est: np.ndarray, T_gt: np.ndarray, metric: str = HEADLINE) -> float:
    """One error in metres of one estimate of an ObjectModel: ``add_sym`` (default), ``mssd``
    or ``adi``. T_est, T_gt: (4, 4) ``T_cam_obj``."""
    return float(error_matrix(model, T_est[None], T_gt[None], metric)[0, 0])


def match_estimates(errors: np.ndarray, limit: float) -> list[tuple[int, int]]:
    """BOP's greedy matching. errors: (E, G) with the estimates sorted by decreasing score;
    returns the (estimate, instance) matches with error below ``limit``."""
    free = np.ones(errors.shape[1], dtype=bool)
    matches = []
    for e in range(errors.shape[0]):
        if not free.any():
            break
        row = np.where(free, errors[e], np.inf)
        g = int(np.argmin(row))
        if row[g] < limit:
            free[g] = False
            matches.append((e, g))
    return matches


@dataclass
class ObjectScore:
    """Counts of one class. found / ignored: per metric, at the report's threshold; found_ar:
    instances found at each AR_THRESHOLDS step of MSSD."""

    obj_id: int
    name: str
    n_instances: int = 0  # annotated instances above min_visib
    n_estimates: int = 0
    found: dict[str, int] = field(default_factory=lambda: dict.fromkeys(METRICS, 0))
    ignored: dict[str, int] = field(default_factory=lambda: dict.fromkeys(METRICS, 0))
    found_ar: list[int] = field(default_factory=lambda: [0] * len(AR_THRESHOLDS))

    @property
    def n_found(self) -> int:
        return self.found[HEADLINE]

    def rate(self, metric: str = HEADLINE) -> float:
        return self.found[metric] / self.n_instances if self.n_instances else float("nan")

    def precision(self, metric: str = HEADLINE) -> float:
        """Found instances per estimate, estimates matched to barely visible parts left out."""
        scored = self.n_estimates - self.ignored[metric]
        return self.found[metric] / scored if scored > 0 else float("nan")

    @property
    def ar_mssd(self) -> float:
        if not self.n_instances:
            return float("nan")
        return float(np.mean(self.found_ar)) / self.n_instances

    def add(self, other: ObjectScore) -> None:
        self.n_instances += other.n_instances
        self.n_estimates += other.n_estimates
        for m in METRICS:
            self.found[m] += other.found[m]
            self.ignored[m] += other.ignored[m]
        self.found_ar = [a + b for a, b in zip(self.found_ar, other.found_ar, strict=True)]


@dataclass
class EvaluationReport:
    threshold: float
    min_visib: float
    objects: dict[int, ObjectScore] = field(default_factory=dict)

    @property
    def total(self) -> ObjectScore:
        """Every class pooled (rates over all instances, as BOP pools them); obj_id 0."""
        total = ObjectScore(0, "all")
        for o in self.objects.values():
            total.add(o)
        return total

    @property
    def n_instances(self) -> int:
        return self.total.n_instances

    @property
    def n_found(self) -> int:
        return self.total.n_found

    @property
    def rate(self) -> float:
        """The headline: ADD-sym < threshold x diameter."""
        return self.total.rate()

    def row(self, key: int | str) -> ObjectScore:
        return self.total if key == "all" else self.objects[int(key)]

    def to_markdown(self) -> str:
        t = f"{self.threshold:g}d"
        lines = [
            f"| obj_id | name | instances (visib > {self.min_visib:g}) | estimates | "
            f"ADD-sym-{t} | MSSD-{t} | AR_MSSD | precision | ADI-{t} (lenient) |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for o in [*self.objects.values(), self.total]:
            lines.append(
                f"| {o.obj_id or 'all'} | {o.name if o.obj_id else ''} "
                f"| {o.n_instances} | {o.n_estimates} | {_percent(o.rate())} "
                f"({o.found['add_sym']}) | {_percent(o.rate('mssd'))} | {_percent(o.ar_mssd)} | "
                f"{_percent(o.precision())} | {_percent(o.rate('adi'))} |"
            )
        return "\n".join(lines)

    def to_json(self) -> dict:
        def entry(o: ObjectScore) -> dict:
            return {
                "name": o.name,
                "instances": o.n_instances,
                "estimates": o.n_estimates,
                "found": dict(o.found),
                "add_sym": o.rate(),
                "mssd": o.rate("mssd"),
                "ar_mssd": o.ar_mssd,
                "precision": o.precision(),
                "adi": o.rate("adi"),
            }

        return {
            "headline": f"ADD-sym < {self.threshold:g} d",
            "threshold": self.threshold,
            "min_visib": self.min_visib,
            "ar_thresholds": list(AR_THRESHOLDS),
            "all": entry(self.total),
            "objects": {str(o.obj_id): entry(o) for o in self.objects.values()},
        }


def checkpoint_markdown(reports: dict[int, EvaluationReport], per_object: bool = True) -> str:
    """One table of reports taken after different numbers of views: a row per object (and all)
    and number of views; headline first, the lenient ADI last."""
    first = next(iter(reports.values()), None)
    if first is None:
        return "(no view scored)"
    t = f"{first.threshold:g}d"
    lines = [
        f"| object | views | instances | estimates | ADD-sym-{t} | MSSD-{t} | AR_MSSD | "
        f"precision | ADI-{t} (lenient) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for n, report in sorted(reports.items()):
        rows = [*report.objects.values()] if per_object else []
        for o in [*rows, report.total]:
            name = o.name if o.obj_id else "**all**"
            lines.append(
                f"| {name} | {n} | {o.n_instances} | {o.n_estimates} | "
                f"{_percent(o.rate())} ({o.found['add_sym']}) | {_percent(o.rate('mssd'))} | "
                f"{_percent(o.ar_mssd)} | {_percent(o.precision())} | {_percent(o.rate('adi'))} |"
            )
    return "\n".join(lines)


def _percent(rate: float) -> str:
    return "-" if np.isnan(rate) else f"{100 * rate:.1f}%"


def evaluate(
    dataset,
    results: list[PoseResult],
    threshold: float = 0.1,
    min_visib: float = 0.75,
    targets: list[tuple[int, int]] | None = None,
    metrics: tuple[str, ...] = METRICS,
) -> EvaluationReport:
    """Detection rates, AR_MSSD and precision per object of ``results`` on the annotated views
    of ``dataset``, or only on the ``targets`` views ((scene_id, im_id) pairs). ``metrics``
    may leave out ``adi`` (the slowest) when it is not reported; its counts then stay 0."""
    for m in metrics:
        _check_metric(m)
    report = EvaluationReport(threshold, min_visib)
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
            scored = np.array([g.visib_fract > min_visib for g in gts], dtype=bool)
            score.n_instances += int(scored.sum())
            # a stable sort: equal scores keep the results' order
            estimates = sorted(
                by_view.get((view.scene_id, view.im_id, obj_id), []), key=lambda r: -r.score
            )
            score.n_estimates += len(estimates)
            if not estimates or not gts:
                continue
            model = dataset.catalog[obj_id]
            T_est = np.stack([r.T_cam_obj for r in estimates])
            T_gt = np.stack([g.T_cam_obj for g in gts])
            cutoff = max(threshold, *AR_THRESHOLDS) * model.diameter
            for metric in metrics:
                errors = error_matrix(model, T_est, T_gt, metric, cutoff)
                matched = [g for _, g in match_estimates(errors, threshold * model.diameter)]
                score.found[metric] += int(scored[matched].sum())
                score.ignored[metric] += int((~scored[matched]).sum())
                if metric == "mssd":
                    for k, step in enumerate(AR_THRESHOLDS):
                        hits = [g for _, g in match_estimates(errors, step * model.diameter)]
                        score.found_ar[k] += int(scored[hits].sum())
    return report
