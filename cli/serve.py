"""The live cell: the daemon, a camera publishing a BOP scene, the current poses, the demo.

- ``posefuse serve``: the estimator daemon on Zenoh with its HTTP API
- ``posefuse publish``: a camera client publishing a BOP scene
- ``posefuse objects``: the current poses of a running daemon
- ``posefuse demo``: the demo recording replayed through an embedded daemon, scored
"""

from __future__ import annotations

import argparse
import ctypes
import ctypes.util
import json
import logging
import os
import signal
import socket
import sys
import threading
import time
from pathlib import Path

from posefuse.cli.common import (
    _add_transport_args,
    _settings,
    add_command,
    add_parts_arg,
    claim_http_port,
    settings_default,
)
from posefuse.estimator.core.errors import PosefuseError
from posefuse.service.resources import DEFAULT_RECORDING


def _cmd_serve(args: argparse.Namespace) -> int:
    # lazy: uvicorn and the service (fastapi, pydantic, trimesh, scipy, cv2; ~0.9 s) are only
    # for this command, too slow for --help
    import uvicorn

    from posefuse.estimator.core.objects import load_catalog
    from posefuse.estimator.tracker import MultiViewEstimator
    from posefuse.service.api import create_cells_app
    from posefuse.service.cells import CellSet
    from posefuse.service.daemon import Daemon
    from posefuse.service.state import StateStore, catalog_fingerprint
    from posefuse.service.worker import EstimatorWorker, make_detector, tracker_config

    limit_malloc_arenas()
    settings = claim_http_port(_settings(args))
    catalog = load_catalog(settings.catalog)
    detect = make_detector(settings, catalog)  # one network for every cell of the process
    warm = MultiViewEstimator(catalog, show_progress=True)
    warm.warm_up()  # templates and size ratios before the first frame, not during it

    def make_daemon(cell_settings) -> Daemon:
        estimator = MultiViewEstimator(catalog, tracker_config(settings), banks=warm.banks())
        estimator.warm_up()
        store = None
        if cell_settings.state_dir is not None:
            store = StateStore(cell_settings.state_dir, catalog_fingerprint(catalog))
        daemon = Daemon(cell_settings, EstimatorWorker(estimator, detect), state_store=store)
        restored = daemon.restore_state()
        if store is not None:
            print(f"posefuse: state in {store.path} ({restored} objects restored)", flush=True)
        return daemon

    cells = CellSet(settings, make_daemon)
    thread = threading.Thread(target=cells.run, name="posefuse-cells", daemon=True)
    thread.start()
    if not cells.ready.wait(60):
        raise PosefuseError("the Zenoh session did not open within 60 s")
    roles = ", ".join(
        f"{c} ({'active' if cells.daemons[c].active else 'standby'})" for c, _ in cells.cells
    )
    print(
        f"posefuse: cell {roles}, zenoh {settings.mode} "
        f"{' '.join(settings.listen + settings.connect)}; "
        f"HTTP on http://{settings.http_host}:{settings.http_port} (/objects, /stats, /docs)",
        flush=True,
    )
    if settings.bin_known:
        width, depth = settings.nbv_bin_size
        x, y, z = settings.nbv_bin_center
        print(
            f"posefuse: the bin is known ({width:g} x {depth:g} m, its floor's centre at "
            f"({x:g}, {y:g}, {z:g}) m in the world frame): a track outside it is published "
            "tentative",
            flush=True,
        )
    server = _server(
        uvicorn.Config(
            create_cells_app(cells),
            host=settings.http_host,
            port=settings.http_port,
            log_level="warning",
            timeout_graceful_shutdown=5,  # an open /events stream must not hold the stop
        )
    )
    try:
        server.run()
    finally:
        _stop_cells(cells, thread)
    if server.stop_signal is not None:
        print(f"posefuse: stopped by {signal.Signals(server.stop_signal).name}", flush=True)
    _leave(0)
    return 0  # not reached


def _leave(code: int) -> None:
    """End the process now that every cell has fused its frame in flight, written its snapshot
    and closed its Zenoh session: flush the output, then skip the interpreter's finalization.

    Finalization is where native threads that are still alive (Zenoh's, which call back into
    Python) are cut mid-unwind when they reach for the interpreter: glibc then aborts with
    "FATAL: exception not rethrown" (exit -6) after a clean stop. It happened to one SIGTERM
    test in a suite run beside a training job; nothing is left to do at that point, so nothing
    is lost by not finalizing."""
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    os._exit(code)


def _server(config):
    """uvicorn's server, except that a SIGTERM or SIGINT only stops it: uvicorn re-raises the
    signal once it has stopped, which kills the process before the daemon has fused its frame
    in flight and written its snapshot. The caller stops the cells, then returns 0."""
    import uvicorn  # lazy: only `serve` runs a server (~45 ms)

    from posefuse.service.api import begin_closing  # lazy: fastapi (~0.3 s)

    class Server(uvicorn.Server):
        stop_signal: int | None = None

        def handle_exit(self, sig, frame) -> None:
            if self.should_exit and sig == signal.SIGINT:
                self.force_exit = True  # a second Ctrl-C: stop serving open requests now
            self.stop_signal = sig
            self.should_exit = True
            begin_closing(self.config.app)  # open /events streams end now, not at the timeout

    return Server(config)


def _stop_cells(cells, thread) -> None:
    """Stop every cell: each fuses the frame in flight and writes its snapshot. A SIGTERM in the
    meantime is ignored (a supervisor repeating it would otherwise kill the snapshot)."""
    previous = signal.signal(signal.SIGTERM, signal.SIG_IGN)
    try:
        cells.stop()
        thread.join(timeout=60)
    finally:
        signal.signal(signal.SIGTERM, previous)


def limit_malloc_arenas(arenas: int = 2) -> None:
    """Few glibc malloc arenas: with one per thread (the default), freed image buffers stay
    with the process and RSS only grows under load. No-op where mallopt is missing."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        M_ARENA_MAX = -8
        libc.mallopt(M_ARENA_MAX, arenas)
    except (OSError, AttributeError):
        pass


def _cmd_publish(args: argparse.Namespace) -> int:
    # lazy: zenoh (native) and tqdm only for this command; the dataset and the camera client
    # load scipy, trimesh, cv2 and pydantic-settings (~0.6 s)
    import zenoh
    from tqdm import tqdm

    from posefuse.clients.camera import publish, scene_messages
    from posefuse.evaluation.dataset import load_dataset
    from posefuse.service.settings import wait_for_subscribers, zenoh_config

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
            t0_ns=args.t0_ns,
        )
    )
    with zenoh.open(zenoh_config(settings)) as session:
        # wait (at most --warmup s) until every key has its subscriber: messages put
        # before that would be lost
        missing = wait_for_subscribers(session, [key for _, key, _ in messages], args.warmup)
        if missing:
            print(f"no subscriber of {missing[0]} after {args.warmup:g} s: publishing anyway")
        with tqdm(total=len(messages), desc="publish", unit="msg") as bar:
            n = publish(session, messages, realtime=True, progress=lambda _k: bar.update(1))
        time.sleep(0.5)
    print(f"published {n} messages of scene {args.scene} on {settings.cell}/@v1/cam/{args.camera}")
    return 0


def _cmd_objects(args: argparse.Namespace) -> int:
    from posefuse.clients.query import objects_http, objects_zenoh, table  # lazy: scipy (~0.25 s)

    if args.zenoh:  # lazy: zenoh (native) and pydantic-settings (~0.1 s) only for --zenoh
        import zenoh

        from posefuse.service.settings import zenoh_config

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


def _cmd_demo(args: argparse.Namespace) -> int:
    from posefuse.service.demo import run_demo  # lazy: scipy, cv2 (~0.3 s)

    settings = _settings(args)
    recording = args.recording
    if args.parts is not None and recording is None:
        recording = Path(args.parts) / "demo.mcap"
        if not recording.is_file():
            raise PosefuseError(f"{recording}: missing; `posefuse onboard` writes it")
    recording = recording or DEFAULT_RECORDING
    settings = claim_http_port(settings)
    if not args.listen:  # a free loopback port: the demo needs no network and no other service
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        settings = settings.model_copy(update={"listen": [f"tcp/127.0.0.1:{port}"]})
    run_demo(recording, settings, keep_serving=args.serve)
    # the daemon has stopped and its Zenoh session is closed: leave as serve does, without the
    # interpreter's finalization, where Zenoh's native threads can abort the process
    _leave(0)
    return 0  # not reached


def register(subparsers) -> None:
    p = add_command(
        subparsers,
        "serve",
        "run the estimator daemon on Zenoh with its HTTP API",
        "Every option overrides one of the daemon's settings (environment variables POSEFUSE_*, "
        "then the JSON file named by POSEFUSE_CONFIG, then the defaults; docs/protocol.md).",
    )
    _add_transport_args(p)
    add_parts_arg(p)
    p.add_argument(
        "--http-host",
        help="address of the HTTP API ("
        + settings_default("POSEFUSE_HTTP_HOST", "127.0.0.1")
        + ")",
    )
    p.add_argument(
        "--http-port",
        type=int,
        help="port of the HTTP API, 0 for any free one ("
        + settings_default("POSEFUSE_HTTP_PORT", "8000")
        + ")",
    )
    p.add_argument(
        "--catalog",
        help="BOP catalog folder of the parts ("
        + settings_default("POSEFUSE_CATALOG", "the shipped catalogs/robi_like")
        + ")",
    )
    p.add_argument(
        "--model",
        help="ONNX model of the front end ("
        + settings_default("POSEFUSE_MODEL", "the shipped models/robi_like.onnx")
        + ")",
    )
    p.add_argument(
        "--state-dir",
        help="keep snapshots of the tracks here and restore them at start ("
        + settings_default("POSEFUSE_STATE_DIR", "none: state is lost with the process")
        + ")",
    )
    p.set_defaults(func=_cmd_serve)

    p = add_command(
        subparsers,
        "publish",
        "publish a BOP scene as a camera would (info, JPEG images, poses)",
    )
    _add_transport_args(p)
    p.add_argument("--dataset", required=True, help="BOP dataset folder")
    p.add_argument("--split", default="test", help="BOP split folder of the dataset")
    p.add_argument("--scene", type=int, default=0, help="scene id")
    p.add_argument("--views", type=int, default=0, help="only the first N views (0: all)")
    p.add_argument("--rate", type=float, default=2.0, help="images per second")
    p.add_argument("--camera", default="cam0", help="camera id in the keys")
    p.add_argument("--seed", type=int, default=0, help="seed of the pose timing jitter")
    p.add_argument(
        "--t0-ns", type=int, default=1_000_000_000_000, help="stamp of the first image (ns)"
    )
    p.add_argument(
        "--warmup",
        type=float,
        default=10.0,
        help="seconds to wait at most for a subscriber before the first message",
    )
    p.set_defaults(func=_cmd_publish)

    p = add_command(subparsers, "objects", "the current poses of a running daemon")
    _add_transport_args(p)
    p.add_argument("--url", default="http://127.0.0.1:8000", help="the daemon's HTTP API")
    p.add_argument(
        "--zenoh", action="store_true", help="ask over Zenoh (a get on the state key) not HTTP"
    )
    p.add_argument("--json", action="store_true", help="print JSON instead of the table")
    p.add_argument(
        "--warmup", type=float, default=0.5, help="--zenoh: seconds to connect before asking"
    )
    p.set_defaults(func=_cmd_objects)

    p = add_command(
        subparsers,
        "demo",
        "replay the demo recording through the daemon and score it",
        "Starts a Zenoh peer on loopback, the daemon and its HTTP API in this process, replays "
        "the recording in lockstep and prints each scene's estimates with their errors against "
        "the ground truth it holds.",
    )
    _add_transport_args(p, listen_default="default: a free port on 127.0.0.1")
    p.add_argument(
        "--recording",
        help="a recording made by make-demo (default: DIR/demo.mcap with --parts, else the "
        "shipped recordings/demo.mcap)",
    )
    add_parts_arg(p)
    p.add_argument(
        "--http-port",
        type=int,
        help="port of the HTTP API, 0 for any free one ("
        + settings_default("POSEFUSE_HTTP_PORT", "8000")
        + ")",
    )
    p.add_argument(
        "--serve", type=float, default=0.0, help="keep the API up this many seconds afterwards"
    )
    p.set_defaults(func=_cmd_demo)
