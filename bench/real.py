"""Real photographs and their rendered twin, side by side, per front end and number of views.

python -m posefuse.bench.real --real DIR [--twin DIR] [--parts DIR] [--out DIR] [--json FILE]

``--real`` is a multi-view BOP dataset of real photographs (``../shared/realdata/lmo_mv``, or
one cut by ``evaluation.multiview``). Its twin (``sim.twin``: the same cameras and object
poses, rendered by posefuse) is read from ``--twin``, or rendered there first when the folder
has none (default ``OUT/twin``). Both are run with the front ends:

- ``oracle, silhouettes``: detections from the ground truth (run-dataset's defaults: 2 px of
  centre noise, 10% missed, 5% false), the true visible silhouettes as masks;
- ``oracle, boxes``: the same with each mask the filled visible box, so the rotation step must
  read the part's outline from the image's own edges (what a photograph changes most);
- ``network`` with ``--parts`` (a part set of ``posefuse onboard`` of the dataset's parts).

Printed: ADD-sym < 0.1 d (visib > 0.75) at 2 / 4 / 8 views with the instances scored, real and
rendered, and per object at 4 views; the run folders (BOP results, fates) under ``--out``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from posefuse.estimator.tracker import MultiViewEstimator, TrackerConfig
from posefuse.evaluation.dataset import load_dataset
from posefuse.evaluation.oracle import OracleConfig, OracleFrontend
from posefuse.evaluation.run_dataset import CHECKPOINTS, run_dataset
from posefuse.evaluation.scores import evaluate

ORACLE = dict(center_sigma_px=2.0, drop_rate=0.1, false_positive_rate=0.05)  # run-dataset's


def _frontends(dataset, parts: str | None) -> dict:
    out = {
        "oracle, silhouettes": OracleFrontend(dataset, OracleConfig(**ORACLE)),
        "oracle, boxes": OracleFrontend(dataset, OracleConfig(**ORACLE, masks="box")),
    }
    if parts:
        from posefuse.estimator.frontend.network import NetworkFrontend
        from posefuse.evaluation.run_dataset import LabelledNetworkFrontend
        from posefuse.sim.onboard import load_part_set

        model = str(load_part_set(parts).model)
        out["network"] = LabelledNetworkFrontend(dataset, NetworkFrontend(model, dataset.catalog))
    return out


def estimator_config(frontend) -> TrackerConfig:
    """The estimator's settings for ``frontend``: a network's take what its card gives
    (ModelCard.verification), as run-dataset's and the daemon's do; an oracle's the defaults."""
    card = getattr(getattr(frontend, "network", None), "card", None)
    return TrackerConfig().with_card(card.verification if card is not None else None)


def measure(dataset, frontend, quiet: bool = True) -> dict[int, object]:
    """{views: EvaluationReport} of one front end on one dataset (the rotation step on), with
    :func:`estimator_config`'s settings."""
    config = estimator_config(frontend)
    shared = MultiViewEstimator(dataset.catalog, config, show_progress=not quiet)
    for obj_id in dataset.catalog:
        shared.matcher(obj_id)  # the templates once, for every scene

    def factory():
        return MultiViewEstimator(dataset.catalog, config, banks=shared.banks())

    run = run_dataset(
        dataset, frontend, rotation=True, show_progress=not quiet, estimator_factory=factory
    )
    return {
        n: evaluate(dataset, run.results[n], targets=run.targets[n])
        for n in CHECKPOINTS
        if run.targets[n]
    }


def network_scores(dataset, parts: str):
    """The part set's network front end on every view of ``dataset``: its recall and precision
    (``evaluation.frontend_metrics``: a detection is right on a part more than 75% visible,
    of its class, within 15 px of its centre)."""
    from posefuse.estimator.frontend.network import NetworkFrontend
    from posefuse.evaluation.frontend_metrics import score_frontend
    from posefuse.sim.onboard import load_part_set

    network = NetworkFrontend(str(load_part_set(parts).model), dataset.catalog)

    def detect(view):
        image = dataset.scene(view.scene_id).load_rgb(view.im_id)
        return network.detect(image)

    return score_frontend(dataset, detect, list(dataset.views()))


def _cell(report) -> str:
    if report is None or not report.n_instances:
        return "-"
    return f"{100 * report.rate:.1f}% ({report.n_instances})"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--real", required=True, help="multi-view BOP dataset of photographs")
    parser.add_argument("--twin", help="its rendered twin (rendered here when missing)")
    parser.add_argument("--parts", help="a part set of `posefuse onboard`: the network's rows")
    parser.add_argument("--out", default="runs/real", help="folder for the twin and the tables")
    parser.add_argument("--seed", type=int, default=0, help="the twin's lighting and noise")
    parser.add_argument("--json", help="write the rates here too")
    parser.add_argument("--quiet", action="store_true")
    args = parser.parse_args(argv)

    real = load_dataset(args.real)
    twin_dir = Path(args.twin or Path(args.out) / "twin")
    if not (twin_dir / "camera.json").is_file():
        from posefuse.sim.twin import render_twin

        print(f"rendering the twin of {args.real} into {twin_dir}", flush=True)
        render_twin(real, twin_dir, seed=args.seed, progress=not args.quiet)
    twin = load_dataset(twin_dir, catalog=real.catalog)
    rates: dict = {}
    rows = ["| front end | images | " + " | ".join(f"{n} views" for n in CHECKPOINTS) + " |"]
    rows.append("|---|---|" + "---|" * len(CHECKPOINTS))
    per_object: dict[str, dict[str, object]] = {}
    for name in _frontends(real, args.parts):
        for label, dataset in (("real", real), ("rendered twin", twin)):
            frontend = _frontends(dataset, args.parts)[name]
            reports = measure(dataset, frontend, args.quiet)
            rates[f"{name} / {label}"] = {
                str(n): {"add_sym": r.rate, "instances": r.n_instances} for n, r in reports.items()
            }
            rows.append(
                f"| {name} | {label} | "
                + " | ".join(_cell(reports.get(n)) for n in CHECKPOINTS)
                + " |"
            )
            per_object[f"{name}, {label}"] = reports.get(4)
            print(rows[-1], flush=True)
    if args.parts:
        print("\nthe network front end (parts more than 75% visible, within 15 px):\n")
        print("| images | recall | precision | median centre error px | mean 2D NEES | parts |")
        print("|---|---|---|---|---|---|")
        for label, dataset in (("real", real), ("rendered twin", twin)):
            score = network_scores(dataset, args.parts)
            rates[f"network front end / {label}"] = {
                "recall": score.recall,
                "precision": score.precision,
            }
            print(
                f"| {label} | {score.recall:.3f} | {score.precision:.3f} | "
                f"{score.median_center_error_px:.2f} | {score.mean_nees:.2f} | "
                f"{score.n_instances} |"
            )
    print("\nADD-sym < 0.1 d (visib > 0.75), instances scored in brackets:\n")
    print("\n".join(rows))
    names = list(per_object)
    print("\nper object at 4 views:\n")
    print("| object | " + " | ".join(names) + " |")
    print("|---|" + "---|" * len(names))
    for obj_id, model in real.catalog.items():
        cells = []
        for n in names:
            report = per_object[n]
            score = report.objects.get(obj_id) if report is not None else None
            cells.append(
                f"{100 * score.rate():.0f}% ({score.n_instances})"
                if score and score.n_instances
                else "-"
            )
        if any(c != "-" for c in cells):
            print(f"| {obj_id} {model.name} | " + " | ".join(cells) + " |")
    if args.json:
        Path(args.json).write_text(json.dumps(rates, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
