"""The demo: a recording of bin scenes with their ground truth, replayed through the daemon and
scored against it.

A demo recording (written by :func:`clients.demo.make_recording`) holds, per scene: the camera
messages a cell's camera publishes, a reset request on ``{cell}/@v1/estimator/reset`` before the
scene (the scenes share the world frame, so the estimator forgets the previous bin), and the
scene's true object poses on ``{cell}/@v1/groundtruth/{scene_id}``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from posefuse.service.codec import decode_groundtruth
from posefuse.service.keys import Keys


def groundtruth_key(cell: str, scene_id: int) -> str:
    return f"{Keys(cell).root}/groundtruth/{scene_id}"


def score_segment(
    estimates: list[dict], truth: list[tuple[int, np.ndarray]], catalog, threshold: float = 0.1
) -> list[dict]:
    """Each confirmed estimate with its ADD-sym and MSSD errors (metres) to the closest unmatched
    true part of its class (by ADD-sym, greedy in order of confidence); ``correct`` when the
    ADD-sym is below threshold x diameter, ``correct_mssd`` when the MSSD is. An estimate with no
    rotation yet (one view) or no part of its class left gets errors of ``None``."""
    from scipy.spatial.transform import Rotation

    from posefuse.evaluation.scores import pose_error

    rows = []
    free = set(range(len(truth)))
    for e in sorted(estimates, key=lambda e: -e["confidence"]):
        if e["status"] != "confirmed":
            continue
        model = catalog[e["class_id"]]
        T = np.eye(4)
        T[:3, :3] = Rotation.from_quat(e["q"]).as_matrix()
        T[:3, 3] = e["t"]
        best, best_err = None, np.inf
        for k in free:
            if truth[k][0] != e["class_id"] or not e["hypotheses"]:
                continue
            err = pose_error(model, T, truth[k][1], "add_sym")
            if err < best_err:
                best, best_err = k, err
        mssd = pose_error(model, T, truth[best][1], "mssd") if best is not None else None
        correct = best is not None and best_err < threshold * model.diameter
        if correct:
            free.discard(best)
        rows.append(
            {
                "object_id": e["object_id"],
                "class": model.name,
                "n_views": e["n_views"],
                "confidence": e["confidence"],
                "diameter_mm": model.diameter * 1000,
                "add_sym_mm": None if best is None else best_err * 1000,
                "mssd_mm": None if mssd is None else mssd * 1000,
                "correct": bool(correct),
                "correct_mssd": bool(mssd is not None and mssd < threshold * model.diameter),
            }
        )
    return rows


def _mm(x: float | None) -> str:
    return "-" if x is None else f"{x:.1f}"


def run_demo(
    recording: str | Path, settings, show_progress: bool = True, keep_serving: float = 0.0
) -> list[tuple[int | None, list[dict]]]:
    """Daemon + API + a Zenoh replay of the recording in lockstep, on loopback; prints a table.

    Returns the estimates held at the end of each scene: [(scene_id, [ObjectEstimate dict])].
    """
    import threading
    import time

    import uvicorn
    import zenoh
    from tqdm import tqdm

    from posefuse.estimator.core.objects import load_catalog
    from posefuse.estimator.tracker import MultiViewEstimator
    from posefuse.service.api import begin_closing, create_app
    from posefuse.service.codec import decode_reset, estimate_to_dict
    from posefuse.service.daemon import Daemon
    from posefuse.service.recording import read_messages
    from posefuse.service.settings import put_camera_message, wait_for_subscribers, zenoh_config
    from posefuse.service.worker import EstimatorWorker, make_detector, tracker_config

    catalog = load_catalog(settings.catalog)
    estimator = MultiViewEstimator(catalog, tracker_config(settings))
    start = time.perf_counter()
    built = []
    estimator.prepare_templates(progress=lambda name, seconds, cached: built.append(not cached))
    # the rest of what a class needs before its first frame, and the verification's compiled
    # kernels (numba: 7 s on 2 cores the first time after an install, then from its cache)
    estimator.warm_up()
    print(
        f"[1/3] templates of {len(catalog)} parts: {sum(built)} built, "
        f"{len(built) - sum(built)} from the cache; the estimator ready in "
        f"{time.perf_counter() - start:.1f} s",
        flush=True,
    )
    daemon = Daemon(settings, EstimatorWorker(estimator, make_detector(settings, catalog)))
    daemon_thread = threading.Thread(target=daemon.run, daemon=True)
    daemon_thread.start()
    if not daemon.ready.wait(30):
        raise RuntimeError("the daemon's Zenoh session did not open within 30 s")
    server = uvicorn.Server(
        uvicorn.Config(
            create_app(daemon),
            host=settings.http_host,
            port=settings.http_port,
            log_level="warning",
        )
    )
    server_thread = threading.Thread(target=server.run, daemon=True)
    server_thread.start()
    url = f"http://{settings.http_host}:{settings.http_port}"
    print(
        f"[2/3] daemon of cell {settings.cell!r}: zenoh {settings.mode} listening on "
        f"{' '.join(settings.listen)}; HTTP {url}",
        flush=True,
    )
    keys = Keys(settings.cell)
    messages = list(read_messages(recording))
    truth: dict[int, list] = {}
    segments: list[tuple[int | None, list[dict]]] = []
    scene = None
    n_images = sum(m.key.endswith("/image") for m in messages)
    sent: dict[str, int] = {}

    def handled() -> int:
        return daemon.frames_handled()

    def verified() -> None:
        """Wait (30 s at most) for the verification of the tracks the frames changed, as a
        daemon given time does it between frames."""
        deadline = time.monotonic() + 30
        while daemon.worker.checks_waiting() and time.monotonic() < deadline:
            time.sleep(0.005)

    client_conf = zenoh_config(
        settings.model_copy(update={"listen": [], "mode": "peer", "connect": settings.listen})
    )
    print(
        f"[3/3] replaying {n_images} frames of {Path(recording).name} through Zenoh, each "
        "processed and verified before the next",
        flush=True,
    )
    with zenoh.open(client_conf) as session:
        # every key the replay puts has its subscriber before the first put (a loaded machine
        # may take seconds to bring the link up; a message put before it is lost)
        replayed = [m.key for m in messages if m.key != keys.reset and "/groundtruth/" not in m.key]
        missing = wait_for_subscribers(session, replayed, timeout_s=60)
        if missing:
            raise TimeoutError(f"no subscriber of {missing[0]} after 60 s")
        bar = tqdm(total=n_images, desc="replay", unit="frame", disable=not show_progress)
        for m in messages:
            if m.key == keys.reset:
                if scene is not None:
                    verified()
                    segments.append(
                        (scene, [estimate_to_dict(e) for e in daemon.worker.snapshot()])
                    )
                request = decode_reset(m.payload)
                daemon.reset(request.class_id, request.object_id)
                continue
            if "/groundtruth/" in m.key:
                scene = int(m.key.rsplit("/", 1)[1])
                truth[scene] = decode_groundtruth(m.payload)
                continue
            put_camera_message(session, m.key, m.payload)
            sent[m.key] = sent.get(m.key, 0) + 1
            if m.key.endswith("/image"):
                bar.update(1)
                continue
            # lockstep: once this message has arrived, wait until every image sent so far has
            # been processed (or dropped), unless one still waits for a later pose
            deadline = time.monotonic() + 30
            while daemon.stats.received.get(m.key, 0) < sent[m.key]:
                if time.monotonic() > deadline:
                    raise TimeoutError(f"the daemon did not receive {m.key}")
                time.sleep(0.002)
            images = sum(v for k, v in sent.items() if k.endswith("/image"))
            stuck_since = None
            while handled() < images and time.monotonic() < deadline:
                if daemon.sync.pending():
                    stuck_since = stuck_since or time.monotonic()
                    if time.monotonic() - stuck_since > 0.2:
                        break
                else:
                    stuck_since = None
                time.sleep(0.002)
            verified()  # and verified before the next: the offline replay's estimates
        deadline = time.monotonic() + 30
        while daemon.sync.pending() and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.2)
        verified()
        bar.close()
        segments.append((scene, [estimate_to_dict(e) for e in daemon.worker.snapshot()]))
    rows_all, n_parts = [], 0
    for scene_id, estimates in segments:
        rows = score_segment(estimates, truth.get(scene_id, []), catalog)
        n_parts += len(truth.get(scene_id, []))
        print(
            f"\nscene {scene_id}: {len(truth.get(scene_id, []))} parts in the bin, "
            f"{len(rows)} confirmed estimates"
        )
        print(
            f"{'object_id':<18} {'class':<13} {'views':>5} {'conf':>5} {'d mm':>6} "
            f"{'ADD-sym mm':>10} {'MSSD mm':>8}  ok"
        )
        for r in rows:
            print(
                f"{r['object_id']:<18} {r['class']:<13} {r['n_views']:>5} "
                f"{r['confidence']:>5.2f} {r['diameter_mm']:>6.1f} {_mm(r['add_sym_mm']):>10} "
                f"{_mm(r['mssd_mm']):>8}  {'yes' if r['correct'] else 'no'}"
            )
        rows_all += rows
    correct = sum(r["correct"] for r in rows_all)
    correct_mssd = sum(r["correct_mssd"] for r in rows_all)
    print(
        "\nd: the part's diameter. ADD-sym: mean distance of the model points to the closest "
        "symmetric equivalent of the true pose; MSSD: the same with the largest distance; "
        "ok: ADD-sym < 0.1 d. '-': no rotation yet (its depth not yet known to 5%) or no true "
        "part of the class left."
    )
    print(
        f"{correct} of {len(rows_all)} confirmed estimates within ADD-sym 0.1 d of a true part "
        f"({correct_mssd} within MSSD 0.1 d); {n_parts} parts were in the bins; "
        f"stats: {daemon.stats_dict()['frames_processed']} frames processed"
    )
    if keep_serving:
        print(
            f"the API answers at {url}/objects, {url}/stats and {url}/docs for {keep_serving:g} s"
        )
        time.sleep(keep_serving)
    else:
        print(
            f"(run `posefuse demo --serve 600` to keep the daemon and its API up; `posefuse "
            f"objects --zenoh --connect {settings.listen[0]}` then asks it over Zenoh)"
        )
    begin_closing(server.config.app)
    server.should_exit = True
    daemon.stop()
    daemon_thread.join(timeout=10)
    # both threads ended before the interpreter exits: a daemon thread still running native
    # code at finalization is cut mid-unwind ("FATAL: exception not rethrown", exit 134)
    server_thread.join(timeout=10)
    return segments
