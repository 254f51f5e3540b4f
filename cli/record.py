"""Recordings: MCAP files of a cell's keys, replayed offline or live, and the demo recording.

- ``posefuse record``: record a cell's keys to an MCAP file
- ``posefuse replay``: replay a recording through the estimator (offline) or to a daemon (live)
- ``posefuse make-demo``: render bin scenes and record them as the demo recording
"""

from __future__ import annotations

import argparse
import queue
import signal
import sys
import threading
import time
from pathlib import Path

from posefuse.cli.common import (
    RUNS,
    _add_transport_args,
    _settings,
    add_command,
    add_parts_arg,
    settings_default,
)
from posefuse.estimator.core.errors import PosefuseError
from posefuse.service.keys import Keys
from posefuse.service.resources import DEFAULT_CATALOG


def _cmd_record(args: argparse.Namespace) -> int:
    # lazy: zenoh (native) only for the network commands; the catalog and the recorder load
    # trimesh, scipy, cv2, mcap and pydantic-settings (~0.6 s)
    import zenoh

    from posefuse.estimator.core.objects import load_catalog
    from posefuse.service.foxglove import FoxgloveMirror
    from posefuse.service.recording import Recorder, RecordingFull
    from posefuse.service.settings import zenoh_config

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

    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())  # as Ctrl-C: the file is finished
    full: RecordingFull | None = None
    if args.ros2:  # a rosbag2 folder of ROS 2 messages instead of our own MCAP
        from posefuse.service.ros2 import Ros2BagRecorder  # lazy: rosbags, scipy, cv2

        if Path(args.out).exists():
            raise PosefuseError(f"--out {args.out}: a rosbag2 folder is created; it exists")
        recorder = Ros2BagRecorder(args.out, settings.cell)
    else:
        recorder = Recorder(args.out, metadata={"cell": settings.cell}, mirror=mirror)
    try:
        with zenoh.open(zenoh_config(settings)) as session:
            session.declare_subscriber(f"{keys.root}/**", on_sample)
            print(f"recording {keys.root}/** to {args.out}; Ctrl-C to stop", flush=True)
            end = time.monotonic() + args.duration if args.duration else None
            try:
                while not stop.is_set() and (end is None or time.monotonic() < end):
                    drain(recorder)
                    time.sleep(0.05)
            except KeyboardInterrupt:
                pass
        drain(recorder)
    except RecordingFull as exc:
        full = exc
    finally:
        footer = recorder.close()
    if full is not None:
        print(
            f"{args.out}: writing failed ({full.cause.strerror or full.cause}) after "
            f"{recorder.in_file} messages; "
            + ("the file is finished and readable" if footer else "no footer could be written"),
            file=sys.stderr,
        )
        return 1
    print(f"wrote {sum(counts.values())} messages on {len(counts)} keys to {args.out}")
    return 0


def _replay_live(args: argparse.Namespace, settings) -> int:
    # lazy: zenoh (native) and tqdm only for --live; the replay modules load scipy, trimesh,
    # cv2 and mcap (~0.9 s)
    import zenoh
    from tqdm import tqdm

    from posefuse.clients.query import _get_json
    from posefuse.service.recording import read_messages
    from posefuse.service.replay import replay_live
    from posefuse.service.settings import zenoh_config

    if args.rate <= 0:
        raise PosefuseError("--rate must be positive")
    messages = [(m.log_time_ns, m.key, m.payload) for m in read_messages(args.file)]
    handled = None
    if args.lockstep:

        def handled() -> int:
            stats = _get_json(f"{args.url.rstrip('/')}/stats")
            return stats["frames_handled"]

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
                token=settings.api_token.get_secret_value() if settings.api_token else None,
            )
    print(f"published {sent} messages of {args.file}")
    return 0


def _cmd_replay(args: argparse.Namespace) -> int:
    # lazy: the estimator and the replay modules load trimesh, scipy, cv2 and mcap (~0.9 s)
    from posefuse.estimator.core.objects import load_catalog
    from posefuse.estimator.tracker import MultiViewEstimator
    from posefuse.service.foxglove import FoxgloveMirror
    from posefuse.service.recording import Recorder, RecordingError, read_messages
    from posefuse.service.replay import replay_offline, write_estimates_json
    from posefuse.service.worker import EstimatorWorker, make_detector, tracker_config

    settings = _settings(args)
    if args.live:
        return _replay_live(args, settings)
    if not args.offline:
        raise PosefuseError("say --offline (feed the estimator here) or --live (over Zenoh)")
    catalog = load_catalog(settings.catalog)
    # the daemon's settings, verification included, so offline and live replays agree
    estimator = MultiViewEstimator(catalog, tracker_config(settings))
    worker = EstimatorWorker(estimator, make_detector(settings, catalog))
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
    # lazy: the renderer and the recorder load trimesh, scipy, cv2 and mcap (~0.6 s)
    from posefuse.clients.demo import make_recording
    from posefuse.estimator.core.objects import load_catalog
    from posefuse.evaluation.dataset import load_dataset
    from posefuse.sim.scenes import SceneSpec
    from posefuse.sim.synth import SynthConfig, generate_dataset

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


def register(subparsers) -> None:
    p = add_command(subparsers, "record", "record a cell's keys to an MCAP file")
    _add_transport_args(p)
    p.add_argument("--out", required=True, help="FILE.mcap to write (--ros2: a folder)")
    p.add_argument(
        "--ros2",
        action="store_true",
        help="write a rosbag2 folder (MCAP storage, ROS 2 messages, cdr) instead",
    )
    p.add_argument(
        "--catalog",
        help="the catalog whose meshes show the estimates in Foxglove ("
        + settings_default("POSEFUSE_CATALOG", "the shipped catalogs/robi_like")
        + ")",
    )
    p.add_argument(
        "--duration", type=float, default=0.0, help="seconds to record (0: until Ctrl-C)"
    )
    p.set_defaults(func=_cmd_record)

    p = add_command(
        subparsers,
        "replay",
        "replay an MCAP recording through the estimator",
        "--offline feeds the recording to the daemon's own worker in this process and writes "
        "OUT/estimates.json and OUT/estimates.mcap; --live publishes it over Zenoh to a "
        "running daemon.",
    )
    _add_transport_args(p)
    p.add_argument("file", help="FILE.mcap to replay")
    p.add_argument("--offline", action="store_true", help="feed the estimator here, directly")
    p.add_argument("--live", action="store_true", help="publish over Zenoh to a daemon")
    p.add_argument("--rate", type=float, default=1.0, help="--live: times real time")
    p.add_argument(
        "--lockstep",
        action="store_true",
        help="--live: wait for each frame to be processed (reads --url /stats)",
    )
    p.add_argument("--url", default="http://127.0.0.1:8000", help="--lockstep: the daemon's API")
    p.add_argument(
        "--warmup", type=float, default=1.0, help="--live: seconds to connect before publishing"
    )
    p.add_argument(
        "--out",
        default=f"{RUNS}/replay",
        help="--offline: folder for estimates.json and estimates.mcap, relative to the current "
        "folder",
    )
    p.add_argument(
        "--catalog",
        help="--offline: BOP catalog folder ("
        + settings_default("POSEFUSE_CATALOG", "the shipped catalogs/robi_like")
        + ")",
    )
    p.add_argument(
        "--model",
        help="--offline: ONNX model of the front end ("
        + settings_default("POSEFUSE_MODEL", "the shipped models/robi_like.onnx")
        + ")",
    )
    add_parts_arg(p)
    p.set_defaults(func=_cmd_replay)

    p = add_command(
        subparsers,
        "make-demo",
        "render bin scenes and record them as the demo MCAP",
        "The shipped demo recording is recordings/demo.mcap; replacing it takes an explicit "
        "--out recordings/demo.mcap.",
    )
    p.add_argument("--catalog", default=DEFAULT_CATALOG, help="BOP catalog folder")
    p.add_argument(
        "--out",
        default=f"{RUNS}/demo/demo.mcap",
        help="FILE.mcap to write, relative to the current folder",
    )
    p.add_argument(
        "--work",
        default=f"{RUNS}/demo-work",
        help="where the rendered dataset goes, relative to the current folder",
    )
    p.add_argument("--scenes", type=int, default=3, help="bin scenes to render")
    p.add_argument("--views", type=int, default=8, help="views per scene")
    p.add_argument("--seed", type=int, default=900, help="random seed of the scenes")
    p.set_defaults(func=_cmd_make_demo)
