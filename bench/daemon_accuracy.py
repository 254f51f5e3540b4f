"""What the daemon publishes, scored: ADD-sym of ``posefuse serve``'s final estimates after 4 and 8
views of held-out scenes, fed live at a camera's rate, against the same frames fed offline.

python -m posefuse.bench.daemon_accuracy --dataset DIR [--scenes 0 1 ...] [--rate 10]
    [--first-stamp-s S] [--offline-only] [--check-every C] [--bin dataset|none]

For each scene and each checkpoint (4 and 8 views), the daemon is reset and sent the scene's
first views at ``--rate`` Hz, as a camera sends them (camera info, poses around each image,
raw RGB images, stamps 100 ms apart). Once every image is handled and no track waits for
its verification, ``/objects`` is read and scored as ``run-dataset`` scores (ADD-sym < 0.1 d,
visib > 0.75, confirmed estimates, in the checkpoint's view).

The reference is the daemon's own worker in this process (``EstimatorWorker.process``: every
waiting verification after each frame, which equals verifying in the update, bit for bit) on
the same frames with the same stamps, so the two differ only in when the verification ran.
The network's voting is seeded by each image's pixels, so the reference gives ``posefuse
run-dataset --frontend network``'s figures on the same scenes. ``--check-every C`` runs the
reference's verifications only after every C-th frame and the last, as a daemon that falls
behind does: what the timing of the checks alone does to the final poses. Where the dataset
records its bin (``posefuse synth``'s ``synth.json``), both are told it as a cell would
(``POSEFUSE_BIN_KNOWN`` and the ``POSEFUSE_NBV_BIN_*`` settings), as ``run-dataset`` uses it;
``--bin none`` tells neither.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
from scipy.spatial.transform import Rotation

from posefuse.bench.service_latency import _get, peer_config, start_daemon
from posefuse.bench.service_targets import _reset
from posefuse.estimator.core.errors import PosefuseError

CELL = "bench"
CHECKPOINTS = (4, 8)


def _pose_results(estimates: list[dict], view, scene_id: int):
    """The confirmed estimates (wire maps) as PoseResults in the view's camera frame."""
    from posefuse.evaluation.scores import PoseResult

    out = []
    for e in estimates:
        if not e["hypotheses"] or e["status"] != "confirmed":
            continue
        T_world_obj = np.eye(4)
        T_world_obj[:3, :3] = Rotation.from_quat(e["q"]).as_matrix()
        T_world_obj[:3, 3] = e["t"]
        out.append(
            PoseResult(
                scene_id,
                view.im_id,
                int(e["class_id"]),
                float(e["confidence"]),
                view.T_cam_world @ T_world_obj,
            )
        )
    return out


def _frames(dataset, scene_id: int, base_stamp: int):
    """(stamp_ns, view, image (H, W, 3) uint8 RGB) of a scene's views, stamps 100 ms apart."""
    scene = dataset.scene(scene_id)
    for k, im_id in enumerate(scene.im_ids):
        yield base_stamp + k * 100_000_000, scene.view(im_id), scene.load_rgb(im_id)


def bin_settings(region) -> dict:
    """The daemon's settings (Settings field -> value) that tell it the bin ``region`` (a
    BinRegion, or None: none); ValueError for a bin turned in the world frame, which the
    settings cannot say (they place a bin by its floor centre)."""
    if region is None:
        return {}
    T = region.T_world_bin
    if not np.allclose(T[:3, :3], np.eye(3)):
        raise ValueError(
            "the dataset's bin is turned in the world frame; the settings place a bin by its "
            "floor centre only"
        )
    return {
        "bin_known": True,
        "nbv_bin_center": tuple(T[:3, 3].tolist()),
        "nbv_bin_size": tuple(region.size),
        "nbv_bin_wall_height": float(region.wall_height),
    }


def as_environment(settings: dict) -> dict[str, str]:
    """Settings as the ``POSEFUSE_*`` environment variables of a daemon's process."""
    return {f"POSEFUSE_{k.upper()}": json.dumps(v) for k, v in settings.items()}


def offline(
    dataset,
    scene_ids,
    stamps: dict[tuple[int, int], int],
    check_every: int = 1,
    overrides: dict | None = None,
) -> dict[int, list]:
    """The reference: per checkpoint, PoseResults of the daemon's worker run in this process on
    the scene's first views (stamps from ``stamps[(scene_id, checkpoint)]``), every waiting
    verification run after every ``check_every``-th frame and after the last; ``overrides``:
    the daemon's settings that differ from the defaults (:func:`bin_settings`)."""
    if check_every < 1:
        raise ValueError(f"check_every: must be at least 1, got {check_every}")
    from posefuse.estimator.core.objects import load_catalog
    from posefuse.estimator.tracker import MultiViewEstimator
    from posefuse.service.codec import estimate_to_dict
    from posefuse.service.settings import Settings
    from posefuse.service.sync import SyncedFrame
    from posefuse.service.worker import EstimatorWorker, make_detector, tracker_config

    settings = Settings(**(overrides or {}))
    catalog = load_catalog(settings.catalog)
    detect = make_detector(settings, catalog)
    results: dict[int, list] = {n: [] for n in CHECKPOINTS}
    for scene_id in scene_ids:
        for n in CHECKPOINTS:
            worker = EstimatorWorker(MultiViewEstimator(catalog, tracker_config(settings)), detect)
            frames = list(_frames(dataset, scene_id, stamps[(scene_id, n)]))[:n]
            for k, (stamp, view, image) in enumerate(frames):
                frame = SyncedFrame("cam0", stamp, image, view.camera, view.T_world_cam)
                worker.fuse(frame, worker.detections(frame))
                if (k + 1) % check_every == 0 or k == len(frames) - 1:
                    while worker.check_next() is not None:
                        pass
            estimates = [estimate_to_dict(e) for e in worker.snapshot()]
            results[n] += _pose_results(estimates, frames[-1][1], scene_id)
    return results


def _send(session, stamp: int, view, image) -> None:
    """One frame as a camera sends it: its info, a pose each side of the image, the image."""
    from posefuse.service.codec import encode_camera_info, encode_camera_pose, encode_image

    root = f"{CELL}/@v1/cam/cam0"
    session.put(f"{root}/info", encode_camera_info(stamp, "cam0", view.camera))
    session.put(f"{root}/pose", encode_camera_pose(stamp - 1000, "cam0", view.T_world_cam))
    session.put(f"{root}/image", encode_image(stamp, "cam0", image, "rgb8"))
    session.put(f"{root}/pose", encode_camera_pose(stamp + 1000, "cam0", view.T_world_cam))


def live(
    dataset,
    scene_ids,
    stamps: dict[tuple[int, int], int],
    rate: float,
    overrides: dict | None = None,
) -> tuple[dict, dict]:
    """Per checkpoint, PoseResults of a ``posefuse serve`` fed at ``rate`` Hz (``overrides``:
    its settings that differ from the defaults, :func:`bin_settings`); and how long the
    verification went on after the last image (s), per checkpoint."""
    import zenoh

    results: dict[int, list] = {n: [] for n in CHECKPOINTS}
    drain: dict[int, list[float]] = {n: [] for n in CHECKPOINTS}
    dropped = dict.fromkeys(CHECKPOINTS, 0)
    daemon, zport, base = start_daemon(CELL, env=as_environment(overrides or {}))
    try:
        with zenoh.open(peer_config(zport)) as session:
            time.sleep(1.0)
            for scene_id in scene_ids:
                for n in CHECKPOINTS:
                    frames = list(_frames(dataset, scene_id, stamps[(scene_id, n)]))
                    _reset(base)
                    before = _get(f"{base}/stats")
                    handled0 = before["frames_handled"]
                    start = time.perf_counter()
                    for k, (stamp, view, image) in enumerate(frames[:n]):
                        delay = start + k / rate - time.perf_counter()
                        if delay > 0:
                            time.sleep(delay)
                        _send(session, stamp, view, image)
                    sent_at = time.perf_counter()
                    deadline = sent_at + 120
                    while time.perf_counter() < deadline:
                        stats = _get(f"{base}/stats")
                        if (
                            stats["frames_handled"] - handled0 >= n
                            and stats["verification"]["waiting"] == 0
                        ):
                            break
                        time.sleep(0.02)
                    drain[n].append(time.perf_counter() - sent_at)
                    if stats["frames_handled"] - handled0 < n:
                        raise RuntimeError(f"scene {scene_id}: the daemon handled too few frames")
                    processed = stats["frames_processed"] - before["frames_processed"]
                    dropped[n] += n - processed
                    if processed < n:
                        print(f"scene {scene_id}, {n} views: {n - processed} frames dropped")
                    estimates = _get(f"{base}/objects")
                    results[n] += _pose_results(estimates, frames[n - 1][1], scene_id)
                print(f"scene {scene_id}: done", flush=True)
    finally:
        daemon.terminate()
        daemon.wait(timeout=30)
    for n in CHECKPOINTS:
        print(f"{n} views: {dropped[n]} of {n * len(scene_ids)} frames dropped live")
    return results, drain


def main(argv: list[str] | None = None) -> int:
    from posefuse.evaluation.dataset import load_dataset
    from posefuse.evaluation.scores import evaluate

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", required=True)
    parser.add_argument("--scenes", type=int, nargs="*", help="default: all")
    parser.add_argument("--rate", type=float, default=10.0, help="frames per second, live")
    parser.add_argument("--json", help="write the results here too")
    parser.add_argument(
        "--first-stamp-s",
        type=int,
        help="the first run's stamp, seconds since the epoch (default: a minute and a few runs "
        "before now)",
    )
    parser.add_argument(
        "--offline-only", action="store_true", help="the reference alone, no daemon"
    )
    parser.add_argument(
        "--check-every",
        type=int,
        default=1,
        metavar="C",
        help="the reference verifies after every C-th frame and the last (default 1: every frame)",
    )
    parser.add_argument(
        "--bin",
        choices=("dataset", "none"),
        default="dataset",
        help="tell both the bin the dataset records (as run-dataset does), or none",
    )
    args = parser.parse_args(argv)
    if args.check_every < 1:
        parser.error(f"--check-every: must be at least 1, got {args.check_every}")

    dataset = load_dataset(args.dataset)
    scene_ids = tuple(args.scenes) if args.scenes else dataset.scene_ids
    # each run its own stamps, later than the last (a camera's stamps never go back), all in
    # the past (the daemon refuses stamps ahead of its clock)
    runs = [(s, n) for s in scene_ids for n in CHECKPOINTS]
    first_s = args.first_stamp_s
    if first_s is None:
        first_s = time.time_ns() // 1_000_000_000 - 2 * len(runs) - 60
    t0 = first_s * 1_000_000_000
    stamps = {run: t0 + 2_000_000_000 * k for k, run in enumerate(runs)}
    targets = {n: [(s, dataset.scene(s).im_ids[n - 1]) for s in scene_ids] for n in CHECKPOINTS}
    try:
        settings = bin_settings(dataset.bin if args.bin == "dataset" else None)
    except (ValueError, PosefuseError) as exc:
        parser.error(f"--bin dataset: {exc}")
    got = {"offline": offline(dataset, scene_ids, stamps, args.check_every, settings)}
    drain = {}
    if not args.offline_only:
        got["live"], drain = live(dataset, scene_ids, stamps, args.rate, settings)
    summary: dict = {
        "dataset": args.dataset,
        "scenes": list(scene_ids),
        "rate_hz": args.rate,
        "check_every": args.check_every,
    }
    for name, results in got.items():
        for n in CHECKPOINTS:
            total = evaluate(dataset, results[n], targets=targets[n]).total
            summary[f"{name}_{n}"] = {
                "add_sym": total.rate(),
                "found": total.found["add_sym"],
                "instances": total.n_instances,
                "mssd": total.rate("mssd"),
                "ar_mssd": total.ar_mssd,
                "precision": total.precision(),
            }
    live_at = "" if args.offline_only else f", live at {args.rate:g} Hz"
    print(f"{args.dataset}, {len(scene_ids)} scenes, first stamp {first_s} s{live_at}:")
    print("| | 4 views | 8 views |")
    print("|---|---|---|")
    for name in got:
        cells = " | ".join(
            f"{100 * summary[f'{name}_{n}']['add_sym']:.1f}% "
            f"({summary[f'{name}_{n}']['found']}/{summary[f'{name}_{n}']['instances']})"
            for n in CHECKPOINTS
        )
        print(f"| {name} | {cells} |")
    for n in drain:
        d = np.array(drain[n])
        summary[f"drain_{n}_s"] = {"median": float(np.median(d)), "max": float(d.max())}
        print(
            f"{n} views: verification done {np.median(d):.2f} s (median), {d.max():.2f} s (max) "
            "after the last image was sent"
        )
    if args.json:
        with open(args.json, "w") as f:
            json.dump(summary, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
