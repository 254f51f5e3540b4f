"""The ``posefuse`` command line: thin wrappers over the packages, one error message per mistake."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from estimator.errors import PosefuseError

# The procedural catalog committed with the project (found beside the packages in a checkout).
DEFAULT_CATALOG = str(Path(__file__).resolve().parents[1] / "catalogs" / "robi_like")
DEFAULT_BENCHMARKS = str(Path(__file__).resolve().parents[1] / "docs" / "benchmarks.md")
DEFAULT_RECORDING = str(Path(__file__).resolve().parents[1] / "recordings" / "demo.mcap")
# The front end trained on it, shipped with the project.
DEFAULT_MODEL = str(Path(__file__).resolve().parents[1] / "models" / "robi_like.onnx")


def _cmd_catalog(args: argparse.Namespace) -> int:
    from estimator.objects import Catalog, load_mesh, make_model, write_catalog

    if args.mesh:
        models = []
        for k, path in enumerate(args.mesh):
            name = Path(path).stem
            models.append(make_model(k + 1, name, load_mesh(path, units=args.units)))
        catalog = Catalog(models)
    else:
        from sim.catalog import robi_like_catalog

        catalog = robi_like_catalog()
    write_catalog(Path(args.out), catalog)
    print(f"wrote {len(catalog)} objects to {args.out}")
    print(_catalog_table(catalog))
    return 0


def _catalog_table(catalog) -> str:
    rows = ["| obj_id | name | diameter (mm) | symmetries |", "|---|---|---|---|"]
    for obj_id, model in catalog.items():
        diameter_mm = model.diameter * 1000
        symmetries = model.describe_symmetries()
        rows.append(f"| {obj_id} | {model.name} | {diameter_mm:.1f} | {symmetries} |")
    return "\n".join(rows)


def _cmd_synth(args: argparse.Namespace) -> int:
    import dataclasses

    from estimator.objects import load_catalog
    from sim.scenes import INTRINSICS, PROFILES
    from sim.synth import SynthConfig, generate_dataset

    if args.intrinsics not in INTRINSICS:
        raise PosefuseError(
            f"--intrinsics: unknown {args.intrinsics!r}; use one of {sorted(INTRINSICS)}"
        )
    if args.scenes < 1 or args.views < 1:
        raise PosefuseError("--scenes and --views must be at least 1")
    profile = PROFILES[args.profile]
    lo, hi = args.instances or profile.n_instances
    if not 1 <= lo <= hi:
        raise PosefuseError("--instances needs MIN MAX with 1 <= MIN <= MAX")
    catalog = load_catalog(args.catalog)
    obj_ids = tuple(args.obj_ids) if args.obj_ids else None
    for obj_id in obj_ids or ():
        catalog[obj_id]  # raises a CatalogError naming the catalog
    config = SynthConfig(
        n_scenes=args.scenes,
        seed=args.seed,
        split=args.split,
        first_scene_id=args.first_scene,
        camera=INTRINSICS[args.intrinsics],
        scene=dataclasses.replace(profile, n_instances=(lo, hi), n_views=args.views),
        profile=args.profile,
        obj_ids=obj_ids,
    )
    start = time.perf_counter()
    generate_dataset(catalog, args.out, config, show_progress=not args.quiet)
    elapsed = time.perf_counter() - start
    print(f"wrote {args.scenes} scenes x {args.views} views to {args.out} in {elapsed:.1f} s")
    return 0


def _cmd_eval(args: argparse.Namespace) -> int:
    from estimator.dataset import load_dataset
    from estimator.evaluation import evaluate, read_results, read_targets

    dataset = load_dataset(args.dataset, split=args.split)
    results = read_results(args.results)
    targets = read_targets(args.targets) if args.targets else None
    report = evaluate(
        dataset,
        results,
        threshold=args.threshold,
        min_visib=args.min_visib,
        targets=targets,
    )
    print(report.to_markdown())
    if args.json:
        Path(args.json).write_text(json.dumps(report.to_json(), indent=2) + "\n")
        print(f"wrote {args.json}")
    return 0


def _cmd_overlay(args: argparse.Namespace) -> int:
    from estimator.dataset import load_dataset
    from sim.overlay import write_gt_overlay

    dataset = load_dataset(args.dataset, split=args.split)
    write_gt_overlay(dataset, args.scene, args.im, args.out)
    print(f"wrote {args.out}")
    return 0


def _cmd_run_dataset(args: argparse.Namespace) -> int:
    from estimator.dataset import load_dataset
    from estimator.evaluation import checkpoint_markdown, evaluate, write_results, write_targets
    from estimator.frontend.oracle import OracleConfig, OracleFrontend
    from estimator.run_dataset import CHECKPOINTS, run_dataset, summary_markdown, write_rows
    from estimator.tracker import MultiViewEstimator

    if args.frontend not in ("oracle", "network"):
        raise PosefuseError(f"--frontend: {args.frontend!r} is not known; use oracle or network")
    dataset = load_dataset(args.dataset, split=args.split)
    rotation = not args.translation_only
    try:
        oracle = OracleConfig(
            center_sigma_px=args.center_sigma,
            drop_rate=args.drop_rate,
            false_positive_rate=args.false_positive_rate,
            with_masks=rotation,
            seed=args.seed,
        )
    except ValueError as exc:
        raise PosefuseError(f"oracle settings: {exc}") from None
    scene_ids = tuple(args.scenes) if args.scenes else None
    for scene_id in scene_ids or ():
        dataset.scene(scene_id)  # a DatasetError naming the missing scene
    shared = MultiViewEstimator(dataset.catalog, show_progress=not args.quiet)
    if rotation:  # build (or load) every class's templates once, with a progress bar
        for obj_id in dataset.catalog:
            shared.matcher(obj_id)

    def factory():
        return MultiViewEstimator(dataset.catalog, banks=shared.banks())

    if args.frontend == "network":
        from estimator.frontend.network import NetworkFrontend
        from estimator.run_dataset import LabelledNetworkFrontend

        frontend = LabelledNetworkFrontend(
            dataset, NetworkFrontend(args.model, dataset.catalog, seed=args.seed)
        )
    else:
        frontend = OracleFrontend(dataset, oracle)
    run = run_dataset(
        dataset,
        frontend,
        scene_ids=scene_ids,
        show_progress=not args.quiet,
        rotation=rotation,
        estimator_factory=factory,
    )
    out = Path(args.out)
    write_rows(out / "translation_errors.csv", run.rows)
    summary = summary_markdown(run, dataset.catalog)
    (out / "translation_summary.md").write_text(
        "Median translation error (and relative to the camera distance) after 2, 4 and 8 "
        f"views.\n\n{summary}\n"
    )
    print(summary)
    print(f"wrote {out / 'translation_errors.csv'} and {out / 'translation_summary.md'}")
    if rotation:
        reports = {}
        for n in CHECKPOINTS:
            if not run.targets[n]:
                continue
            write_results(out / f"results_{n}views.csv", run.results[n])
            write_targets(out / f"targets_{n}views.json", run.targets[n])
            reports[n] = evaluate(dataset, run.results[n], targets=run.targets[n])
        table = checkpoint_markdown(reports)
        legend = (
            "Pose accuracy (instances with visib_fract > 0.75) in the view after which the "
            "estimates were taken: ADD-sym < 0.1 d (the headline; found instances in brackets), "
            "MSSD < 0.1 d, AR_MSSD (mean recall over MSSD thresholds 0.05-0.5 d), precision "
            "(found instances per estimate), and the lenient ADI < 0.1 d."
        )
        (out / "detection_rate.md").write_text(f"{legend}\n\n{table}\n")
        (out / "detection_rate.json").write_text(
            json.dumps({str(n): r.to_json() for n, r in reports.items()}, indent=1) + "\n"
        )
        print(f"\n{legend}")
        print(table)
        from estimator.fates import fate_table
        from estimator.run_dataset import write_fates

        write_fates(out / "fates.csv", run.fates)
        fates = fate_table(
            [f for f in run.fates if f.n_views >= 2], dataset.catalog, dataset.profile
        )
        fates_legend = (
            "Where each scored instance ended (estimator/fates.py gives the rules, first that "
            f"applies); profile {dataset.profile}, front end {args.frontend}."
        )
        (out / "fates.md").write_text(f"{fates_legend}\n\n{fates}\n")
        print(f"\n{fates_legend}")
        print(fates)
        print(
            "wrote results_*views.csv, targets_*views.json, detection_rate.md, "
            f"detection_rate.json, fates.csv and fates.md to {out}"
        )
    return 0


def _cmd_templates(args: argparse.Namespace) -> int:
    from estimator.objects import load_catalog
    from estimator.templates import build_template_bank

    catalog = load_catalog(args.catalog)
    rows = [
        "| obj_id | name | templates | size (KiB) | build (s) |",
        "|---|---|---|---|---|",
    ]
    for obj_id, model in catalog.items():
        bank = build_template_bank(model, cache_dir=args.cache, show_progress=not args.quiet)
        rows.append(
            f"| {obj_id} | {model.name} | {len(bank)} | {bank.nbytes / 1024:.0f} | "
            f"{bank.build_seconds:.1f} |"
        )
    print("\n".join(rows))
    return 0


def _cmd_train(args: argparse.Namespace) -> int:
    try:
        import torch  # noqa: F401
    except ImportError:
        raise PosefuseError(
            'training needs torch: pip install -e ".[train]" (a CPU build, torch==2.13.0)'
        ) from None
    from estimator.objects import load_catalog
    from sim.train import TrainConfig, train

    load_catalog(args.catalog)  # a CatalogError before any work
    if not args.out.endswith(".onnx"):
        raise PosefuseError(f"--out: {args.out!r} must end in .onnx")
    config = TrainConfig(
        n_scenes=args.scenes,
        views_per_scene=args.views,
        val_scenes=args.val_scenes,
        minutes=args.minutes,
        max_iterations=args.iterations,
        batch=args.batch,
        seed=args.seed,
        workers=args.workers,
        robi_fraction=args.robi_fraction,
    )
    card = train(args.catalog, args.out, config)
    print(json.dumps(card, indent=2))
    print(f"wrote {args.out} and {Path(args.out).with_suffix('.json')}")
    return 0


def _cmd_eval_frontend(args: argparse.Namespace) -> int:
    from estimator.dataset import load_dataset
    from estimator.frontend.metrics import score_frontend
    from estimator.frontend.network import NetworkFrontend

    dataset = load_dataset(args.dataset, split=args.split)
    frontend = NetworkFrontend(args.model, dataset.catalog, threads=args.threads)
    views = [v for v in dataset.views()][: args.max_views or None]

    def detect(view):
        image = dataset.scene(view.scene_id).load_rgb(view.im_id)
        return frontend.detect(image, stamp_seed=view.scene_id * 100_000 + view.im_id)

    score = score_frontend(dataset, detect, views, min_visib=args.min_visib)
    print(f"Front end {args.model} on {args.dataset} (profile {dataset.profile}):\n")
    print(score.to_markdown())
    return 0


def _cmd_frontend_overlay(args: argparse.Namespace) -> int:
    import cv2

    from estimator.dataset import load_dataset
    from estimator.frontend.network import NetworkFrontend
    from sim.overlay import frontend_overlay

    dataset = load_dataset(args.dataset, split=args.split)
    frontend = NetworkFrontend(args.model, dataset.catalog)
    scene = dataset.scene(args.scene)
    view = scene.view(args.im)
    image = scene.load_rgb(args.im)
    raw = frontend.infer(image)
    dets = frontend.detect(image, stamp_seed=args.scene * 100_000 + args.im)
    truth = [view.camera.project(g.T_cam_obj[:3, 3]) for g in view.gts if g.visib_fract > 0.1]
    picture = frontend_overlay(image, raw, dets, frontend.card, np.array(truth).reshape(-1, 2))
    if args.crop:
        x, y, w, h = args.crop
        picture = picture[y : y + h, x : x + w]
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(args.out, picture)
    print(f"wrote {args.out}: {len(dets)} detections")
    return 0


def _settings(args: argparse.Namespace):
    from pydantic import ValidationError

    from service.settings import Settings

    overrides = {}
    for name in ("cell", "mode", "http_host", "http_port", "catalog", "model"):
        value = getattr(args, name, None)
        if value is not None:
            overrides[name] = value
    if getattr(args, "listen", None):
        overrides["listen"] = args.listen
    if getattr(args, "connect", None):
        overrides["connect"] = args.connect
    try:
        return Settings(**overrides)
    except ValidationError as exc:
        first = exc.errors()[0]
        field = ".".join(str(x) for x in first["loc"])
        raise PosefuseError(f"setting {field}: {first['msg']}") from None


def _add_transport_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--cell", help="key prefix of the cell (default posefuse)")
    p.add_argument("--mode", choices=["peer", "client"], help="zenoh mode (default peer)")
    p.add_argument("--listen", nargs="+", help="zenoh listen endpoints, e.g. tcp/127.0.0.1:7447")
    p.add_argument("--connect", nargs="+", help="zenoh endpoints to connect to")


def _cmd_serve(args: argparse.Namespace) -> int:
    import threading

    import uvicorn

    from estimator.objects import load_catalog
    from estimator.tracker import MultiViewEstimator
    from service.api import create_app
    from service.daemon import Daemon
    from service.worker import EstimatorWorker, make_detector

    settings = _settings(args)
    catalog = load_catalog(settings.catalog)
    detect = make_detector(settings, catalog)
    estimator = MultiViewEstimator(catalog, show_progress=True)
    for obj_id in catalog:  # templates before the first frame, not during it
        estimator.matcher(obj_id)
    daemon = Daemon(settings, EstimatorWorker(estimator, detect))
    thread = threading.Thread(target=daemon.run, name="posefuse-daemon", daemon=True)
    thread.start()
    if not daemon.ready.wait(30):
        raise PosefuseError("the Zenoh session did not open within 30 s")
    print(
        f"posefuse: cell {settings.cell!r}, zenoh {settings.mode} "
        f"{' '.join(settings.listen + settings.connect)}; "
        f"HTTP on http://{settings.http_host}:{settings.http_port} (/objects, /stats, /docs)",
        flush=True,
    )
    try:
        uvicorn.run(
            create_app(daemon),
            host=settings.http_host,
            port=settings.http_port,
            log_level="warning",
        )
    finally:
        daemon.stop()
        thread.join(timeout=10)
    return 0


def _cmd_publish(args: argparse.Namespace) -> int:
    import zenoh
    from tqdm import tqdm

    from clients.camera import publish, scene_messages
    from estimator.dataset import load_dataset
    from service.settings import zenoh_config

    settings = _settings(args)
    if args.rate <= 0:
        raise PosefuseError("--rate must be positive")
    dataset = load_dataset(args.dataset, split=args.split)
    dataset.scene(args.scene)  # a DatasetError naming a missing scene
    messages = list(
        scene_messages(
            dataset,
            args.scene,
            settings.cell,
            args.camera,
            args.rate,
            seed=args.seed,
            max_views=args.views,
        )
    )
    with zenoh.open(zenoh_config(settings)) as session:
        time.sleep(args.warmup)  # let the transport connect before the first put
        with tqdm(total=len(messages), desc="publish", unit="msg") as bar:
            n = publish(session, messages, realtime=True, progress=lambda _k: bar.update(1))
        time.sleep(0.5)
    print(f"published {n} messages of scene {args.scene} on {settings.cell}/@v1/cam/{args.camera}")
    return 0


def _cmd_objects(args: argparse.Namespace) -> int:
    from clients.query import objects_http, objects_zenoh, table

    if args.zenoh:
        import zenoh

        from service.settings import zenoh_config

        settings = _settings(args)
        with zenoh.open(zenoh_config(settings)) as session:
            time.sleep(args.warmup)
            objects = objects_zenoh(session, settings.cell)
    else:
        try:
            objects = objects_http(args.url)
        except OSError as exc:
            raise PosefuseError(f"{args.url}: {exc}") from None
    print(json.dumps(objects, indent=2) if args.json else table(objects))
    return 0


def _cmd_record(args: argparse.Namespace) -> int:
    import queue

    import zenoh

    from estimator.objects import load_catalog
    from service.foxglove import FoxgloveMirror
    from service.keys import Keys
    from service.recording import Recorder
    from service.settings import zenoh_config

    settings = _settings(args)
    keys = Keys(settings.cell)
    counts: dict[str, int] = {}
    mirror = FoxgloveMirror(settings.cell, load_catalog(settings.catalog))
    inbox: queue.SimpleQueue = queue.SimpleQueue()

    def on_sample(sample):  # the arrival time is the log time; writing happens below
        inbox.put((str(sample.key_expr), sample.payload.to_bytes(), time.time_ns()))

    def drain(recorder) -> None:
        while True:
            try:
                key, payload, log_time = inbox.get_nowait()
            except queue.Empty:
                return
            recorder.write(key, payload, log_time)
            counts[key] = counts.get(key, 0) + 1

    with Recorder(args.out, metadata={"cell": settings.cell}, mirror=mirror) as recorder:
        with zenoh.open(zenoh_config(settings)) as session:
            session.declare_subscriber(f"{keys.root}/**", on_sample)
            print(f"recording {keys.root}/** to {args.out}; Ctrl-C to stop", flush=True)
            try:
                end = time.monotonic() + args.duration if args.duration else None
                while end is None or time.monotonic() < end:
                    drain(recorder)
                    time.sleep(0.05)
            except KeyboardInterrupt:
                pass
        drain(recorder)
    print(f"wrote {sum(counts.values())} messages on {len(counts)} keys to {args.out}")
    return 0


def _replay_live(args: argparse.Namespace, settings) -> int:
    import zenoh
    from tqdm import tqdm

    from clients.query import _get_json
    from service.recording import read_messages
    from service.replay import replay_live
    from service.settings import zenoh_config

    if args.rate <= 0:
        raise PosefuseError("--rate must be positive")
    messages = [(m.log_time_ns, m.key, m.payload) for m in read_messages(args.file)]
    handled = None
    if args.lockstep:

        def handled() -> int:
            stats = _get_json(f"{args.url.rstrip('/')}/stats")
            return stats["frames_processed"] + sum(stats["frames_dropped"].values())

        try:
            handled()
        except OSError as exc:
            raise PosefuseError(f"--lockstep needs the daemon's API at {args.url}: {exc}") from None
    n_images = sum(k.endswith("/image") for _, k, _ in messages)
    with zenoh.open(zenoh_config(settings)) as session:
        time.sleep(args.warmup)
        with tqdm(total=n_images, desc="replay", unit="frame") as bar:
            sent = replay_live(
                messages,
                session,
                settings.cell,
                rate=args.rate,
                handled=handled,
                progress=lambda: bar.update(1),
            )
    print(f"published {sent} messages of {args.file}")
    return 0


def _cmd_replay(args: argparse.Namespace) -> int:
    from estimator.objects import load_catalog
    from estimator.tracker import MultiViewEstimator
    from service.foxglove import FoxgloveMirror
    from service.recording import Recorder, RecordingError, read_messages
    from service.replay import replay_offline, write_estimates_json
    from service.worker import EstimatorWorker, make_detector

    settings = _settings(args)
    if args.live:
        return _replay_live(args, settings)
    if not args.offline:
        raise PosefuseError("say --offline (feed the estimator here) or --live (over Zenoh)")
    catalog = load_catalog(settings.catalog)
    worker = EstimatorWorker(MultiViewEstimator(catalog), make_detector(settings, catalog))
    messages = []
    damage = None
    try:
        for m in read_messages(args.file):
            messages.append((m.log_time_ns, m.key, m.payload))
    except RecordingError as exc:
        damage = exc
    out_dir = Path(args.out)
    mirror = FoxgloveMirror(settings.cell, catalog)
    metadata = {"cell": settings.cell, "replay_of": Path(args.file).name}
    with Recorder(out_dir / "estimates.mcap", metadata=metadata, mirror=mirror) as recorder:
        result = replay_offline(messages, worker, settings.cell, recorder=recorder)
    out = write_estimates_json(out_dir / "estimates.json", result.published, result.segments)
    print(
        f"replayed {len(messages)} messages: {worker.stats.processed} frames, "
        f"{len(result.published)} updates, {len(result.segments)} segments; wrote {out} and "
        f"{out_dir / 'estimates.mcap'} (inputs, estimates and Foxglove channels)"
    )
    if damage is not None:
        print(
            f"posefuse replay: error: {damage} (estimates are of the frames before it)",
            file=sys.stderr,
        )
        return 2
    return 0


def _cmd_make_demo(args: argparse.Namespace) -> int:
    from estimator.dataset import load_dataset
    from estimator.objects import load_catalog
    from service.demo import make_recording
    from sim.scenes import SceneSpec
    from sim.synth import SynthConfig, generate_dataset

    catalog = load_catalog(args.catalog)
    data = Path(args.work)
    generate_dataset(
        catalog,
        data,
        SynthConfig(n_scenes=args.scenes, seed=args.seed, scene=SceneSpec(n_views=args.views)),
    )
    dataset = load_dataset(data)
    out = make_recording(dataset, dataset.scene_ids, args.out, catalog=catalog)
    print(
        f"wrote {out} ({out.stat().st_size / 1e6:.1f} MB): {args.scenes} scenes x "
        f"{args.views} views, seed {args.seed}"
    )
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from service.demo import run_demo

    settings = _settings(args)
    if not args.listen:  # a free loopback port: the demo needs no network and no other service
        import socket

        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        settings = settings.model_copy(update={"listen": [f"tcp/127.0.0.1:{port}"]})
    run_demo(args.recording, settings, keep_serving=args.serve)
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    from bench.paper_tables import main as bench_main

    return bench_main(args)


def _cmd_quickstart(args: argparse.Namespace) -> int:
    from estimator.dataset import load_dataset
    from estimator.evaluation import evaluate, ground_truth_results, read_results, write_results
    from estimator.objects import load_catalog
    from sim.overlay import write_gt_overlay
    from sim.scenes import SceneSpec
    from sim.synth import SynthConfig, generate_dataset

    out = Path(args.out)
    catalog = load_catalog(args.catalog)
    print(f"1/3 rendering 1 bin scene x 8 views of {len(catalog)} parts into {out}")
    generate_dataset(
        catalog, out, SynthConfig(n_scenes=1, seed=args.seed, scene=SceneSpec(n_views=8))
    )
    dataset = load_dataset(out)
    overlay = out / "overlay_000000_000000.png"
    write_gt_overlay(dataset, 0, 0, overlay)
    print(f"2/3 ground-truth overlay of the first view: {overlay}")
    results_path = out / "results_gt.csv"
    write_results(results_path, ground_truth_results(dataset))
    report = evaluate(dataset, read_results(results_path))
    print(
        "3/3 ADD-sym, MSSD and AR_MSSD of the ground-truth poses read back from "
        f"{results_path} (a check of the data path; the estimator is next):"
    )
    print(report.to_markdown())
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="posefuse",
        description="Multi-view 6D pose estimation of textureless, shiny parts from RGB frames.",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser(
        "catalog", help="write a BOP object catalog (procedural parts or your meshes)"
    )
    p.add_argument("--out", required=True, help="output folder (models/ of a BOP dataset)")
    p.add_argument("--mesh", action="append", help="a mesh file (STL/PLY/OBJ); repeat for more")
    p.add_argument("--units", default="mm", choices=["mm", "cm", "m"], help="units of --mesh files")
    p.set_defaults(func=_cmd_catalog)

    p = sub.add_parser("synth", help="render a BOP multi-view bin-picking dataset")
    p.add_argument("--catalog", default=DEFAULT_CATALOG, help="BOP catalog folder")
    p.add_argument("--out", required=True, help="dataset folder to write")
    p.add_argument("--scenes", type=int, default=2)
    p.add_argument("--views", type=int, default=8)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--split", default="test")
    p.add_argument("--first-scene", type=int, default=0)
    p.add_argument(
        "--profile",
        default="mixed",
        choices=["mixed", "robi"],
        help="mixed: 5-15 parts of 1-3 types, cameras around the bin; robi: 20-40 parts of one "
        "type piled densely, an eye-in-hand sweep over the bin (default mixed)",
    )
    p.add_argument(
        "--instances",
        type=int,
        nargs=2,
        metavar=("MIN", "MAX"),
        help="parts per bin (default: the profile's, 5 15 for mixed, 20 40 for robi)",
    )
    p.add_argument("--intrinsics", default="realsense", help="realsense, realsense-640 or ensenso")
    p.add_argument("--obj-ids", type=int, nargs="+", help="only these objects of the catalog")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_synth)

    p = sub.add_parser(
        "eval",
        help="score a BOP results CSV: ADD-sym, MSSD, AR_MSSD and precision per object",
    )
    p.add_argument("--dataset", required=True)
    p.add_argument("--results", required=True, help="CSV: scene_id,im_id,obj_id,score,R,t,time")
    p.add_argument("--split", default="test")
    p.add_argument("--threshold", type=float, default=0.1, help="fraction of the diameter")
    p.add_argument("--min-visib", type=float, default=0.75)
    p.add_argument("--targets", help="JSON list of {scene_id, im_id}: score only these views")
    p.add_argument("--json", help="also write the report as JSON here")
    p.set_defaults(func=_cmd_eval)

    p = sub.add_parser("overlay", help="draw the ground truth of one view over its image")
    p.add_argument("--dataset", required=True)
    p.add_argument("--split", default="test")
    p.add_argument("--scene", type=int, default=0)
    p.add_argument("--im", type=int, default=0)
    p.add_argument("--out", required=True)
    p.set_defaults(func=_cmd_overlay)

    p = sub.add_parser(
        "run-dataset",
        help="run the estimator over a BOP dataset, views one at a time, and score it",
    )
    p.add_argument("--dataset", required=True)
    p.add_argument("--split", default="test")
    p.add_argument("--out", required=True, help="folder for the error tables")
    p.add_argument(
        "--frontend",
        default="oracle",
        help="oracle (noisy detections from the ground truth) or network (the learned model)",
    )
    p.add_argument("--model", default=DEFAULT_MODEL, help="ONNX model for --frontend network")
    p.add_argument("--scenes", type=int, nargs="+", help="only these scene ids")
    p.add_argument("--center-sigma", type=float, default=2.0, help="oracle center noise, px")
    p.add_argument("--drop-rate", type=float, default=0.1, help="oracle missed detections")
    p.add_argument("--false-positive-rate", type=float, default=0.05)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--translation-only", action="store_true", help="skip the rotation step")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_run_dataset)

    p = sub.add_parser(
        "templates", help="build (or load from the cache) the LINE-2D templates of a catalog"
    )
    p.add_argument("--catalog", default=DEFAULT_CATALOG)
    p.add_argument("--cache", help="cache folder (default $POSEFUSE_CACHE or ~/.cache/posefuse)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_templates)

    p = sub.add_parser("train", help="train the center-voting front end on synthetic renders")
    p.add_argument("--catalog", default=DEFAULT_CATALOG)
    p.add_argument("--out", required=True, help="models/NAME.onnx (its card NAME.json beside)")
    p.add_argument("--scenes", type=int, default=400, help="training scenes to render")
    p.add_argument("--views", type=int, default=4, help="views per training scene")
    p.add_argument("--val-scenes", type=int, default=12)
    p.add_argument("--minutes", type=float, default=40.0, help="training time budget")
    p.add_argument("--iterations", type=int, default=100_000, help="at most this many steps")
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--workers", type=int, default=2, help="rendering processes")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--robi-fraction",
        type=float,
        default=0.5,
        help="share of training scenes in the robi profile, the rest mixed (default 0.5)",
    )
    p.set_defaults(func=_cmd_train)

    p = sub.add_parser("eval-frontend", help="recall, precision and center accuracy of a model")
    p.add_argument("--dataset", required=True)
    p.add_argument("--split", default="test")
    p.add_argument("--model", default=DEFAULT_MODEL)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--min-visib", type=float, default=0.75)
    p.add_argument("--max-views", type=int, default=0, help="score only the first N views")
    p.set_defaults(func=_cmd_eval_frontend)

    p = sub.add_parser("frontend-overlay", help="draw the learned front end's output on a view")
    p.add_argument("--dataset", required=True)
    p.add_argument("--split", default="test")
    p.add_argument("--model", default=DEFAULT_MODEL)
    p.add_argument("--scene", type=int, default=0)
    p.add_argument("--im", type=int, default=0)
    p.add_argument("--crop", type=int, nargs=4, metavar=("X", "Y", "W", "H"))
    p.add_argument("--out", required=True)
    p.set_defaults(func=_cmd_frontend_overlay)

    p = sub.add_parser("serve", help="run the estimator daemon on Zenoh with its HTTP API")
    _add_transport_args(p)
    p.add_argument("--http-host")
    p.add_argument("--http-port", type=int)
    p.add_argument("--catalog")
    p.add_argument("--model")
    p.set_defaults(func=_cmd_serve)

    p = sub.add_parser("publish", help="publish a BOP scene as a camera would (info, JPEG, poses)")
    _add_transport_args(p)
    p.add_argument("--dataset", required=True)
    p.add_argument("--split", default="test")
    p.add_argument("--scene", type=int, default=0)
    p.add_argument("--views", type=int, default=0, help="only the first N views")
    p.add_argument("--rate", type=float, default=2.0, help="images per second")
    p.add_argument("--camera", default="cam0", help="camera id in the keys")
    p.add_argument("--seed", type=int, default=0, help="pose timing jitter")
    p.add_argument("--warmup", type=float, default=1.0, help="seconds to connect first")
    p.set_defaults(func=_cmd_publish)

    p = sub.add_parser("objects", help="the current poses of a running daemon")
    _add_transport_args(p)
    p.add_argument("--url", default="http://127.0.0.1:8000")
    p.add_argument("--zenoh", action="store_true", help="ask over Zenoh instead of HTTP")
    p.add_argument("--json", action="store_true")
    p.add_argument("--warmup", type=float, default=0.5)
    p.set_defaults(func=_cmd_objects)

    p = sub.add_parser("record", help="record a cell's keys to an MCAP file")
    _add_transport_args(p)
    p.add_argument("--out", required=True, help="FILE.mcap")
    p.add_argument("--catalog", help="the catalog whose meshes show the estimates")
    p.add_argument("--duration", type=float, default=0.0, help="seconds (0: until Ctrl-C)")
    p.set_defaults(func=_cmd_record)

    p = sub.add_parser("replay", help="replay an MCAP recording through the estimator")
    _add_transport_args(p)
    p.add_argument("file", help="FILE.mcap")
    p.add_argument("--offline", action="store_true", help="feed the estimator directly")
    p.add_argument("--live", action="store_true", help="publish over Zenoh to a daemon")
    p.add_argument("--rate", type=float, default=1.0, help="--live: times real time")
    p.add_argument(
        "--lockstep",
        action="store_true",
        help="--live: wait for each frame to be processed (reads --url /stats)",
    )
    p.add_argument("--url", default="http://127.0.0.1:8000")
    p.add_argument("--warmup", type=float, default=1.0)
    p.add_argument("--out", default="replay", help="folder for estimates.json")
    p.add_argument("--catalog")
    p.add_argument("--model")
    p.set_defaults(func=_cmd_replay)

    p = sub.add_parser("make-demo", help="render bin scenes and record them as the demo MCAP")
    p.add_argument("--catalog", default=DEFAULT_CATALOG)
    p.add_argument("--out", default=DEFAULT_RECORDING)
    p.add_argument("--work", default="data/demo", help="where the rendered dataset goes")
    p.add_argument("--scenes", type=int, default=3)
    p.add_argument("--views", type=int, default=8)
    p.add_argument("--seed", type=int, default=900)
    p.set_defaults(func=_cmd_make_demo)

    p = sub.add_parser("bench", help="the paper's Tables I and II into docs/benchmarks.md")
    p.add_argument("--dataset", required=True, help="a BOP dataset; rendered there if absent")
    p.add_argument("--quick", action="store_true", help="2 small scenes (CI)")
    p.add_argument("--catalog", default=DEFAULT_CATALOG)
    p.add_argument("--out", default=DEFAULT_BENCHMARKS, help="the Markdown page (and .json)")
    p.add_argument(
        "--profile",
        default="mixed",
        choices=["mixed", "robi"],
        help="scene profile of a dataset rendered by this command (default mixed)",
    )
    p.add_argument(
        "--frontend",
        default="oracle",
        choices=["oracle", "network"],
        help="the detections every method sees (default oracle, the upper bound)",
    )
    p.add_argument("--model", default=DEFAULT_MODEL, help="the network, with --frontend network")
    p.set_defaults(func=_cmd_bench)

    p = sub.add_parser("demo", help="replay the demo recording through the daemon and score it")
    _add_transport_args(p)
    p.add_argument("--recording", default=DEFAULT_RECORDING)
    p.add_argument("--http-port", type=int)
    p.add_argument("--serve", type=float, default=0.0, help="keep the API up this many seconds")
    p.set_defaults(func=_cmd_demo)

    p = sub.add_parser("quickstart", help="render a small dataset and run the evaluation on it")
    p.add_argument("--catalog", default=DEFAULT_CATALOG)
    p.add_argument("--out", default="data/quickstart")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=_cmd_quickstart)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parser.parse_args(argv)
    args.argv = argv[1:]  # what followed the command, for reports that name their command
    try:
        return int(args.func(args) or 0)
    except PosefuseError as exc:
        print(f"posefuse {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # unreadable/unwritable paths: name the file, no traceback
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"posefuse {args.command}: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"posefuse {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
