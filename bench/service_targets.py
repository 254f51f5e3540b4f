"""The service's speed targets, measured end to end: latency and throughput of ``posefuse serve``.

python -m posefuse.bench.service_targets --few DIR:SCENE --many DIR:SCENE [--seconds 20]
    [--parts DIR]

Starts ``posefuse serve`` as its own process on loopback and publishes, from this process, the
views of a scene (1280x720 JPEG, camera info and poses, as cameras do) over and over with
increasing stamps:

- latency, for the ``--few`` scene (about 8 objects in view) and the ``--many`` one (about
  30): wall time from putting an image to receiving the first ObjectEstimate stamped with it,
  at 2 Hz, p50 and p95;
- throughput: one camera at 10 Hz with each scene, then 4 cameras at 2 Hz each (each its own
  id and view order) with the ``--few`` one, ``--seconds`` each: the fraction of images
  processed (from ``/stats``);
- the deferred verification (on unless ``POSEFUSE_VERIFY=0``): in the 10 Hz runs, the wall time
  from putting the first image a track's estimate changed with (published unverified) to
  receiving its verified estimate, p50 and p95, and the tracks still waiting at the end.

Targets (2 cores): p50 <= 90 ms with ~8 objects, <= 250 ms with ~30; image -> verified pose p95
<= 400 ms with ~8 objects and <= 1.5 s with ~30 at 10 Hz; >= 95% processed at 10 Hz from one
camera and at 4 x 2 Hz. Memory at twice the rate: ``bench.service_soak``.
"""

from __future__ import annotations

import argparse
import json
import time
import urllib.request

import msgpack
import numpy as np

from posefuse.bench.service_latency import FirstUpdates, _get, peer_config, start_daemon

CELL = "bench"


def _scene_messages(spec: str) -> tuple[list, int]:
    """[(camera, T_world_cam, image message dict)] of a 'DIR:SCENE' spec and its objects/view."""
    from posefuse.evaluation.dataset import load_dataset
    from posefuse.service.codec import encode_image

    path, _, scene_id = spec.rpartition(":")
    scene = load_dataset(path).scene(int(scene_id))
    views = [scene.view(i) for i in scene.im_ids]
    out = []
    for v in views:
        msg = msgpack.unpackb(encode_image(0, "cam0", scene.load_rgb(v.im_id), "jpeg"))
        out.append((v.camera, v.T_world_cam, msg))
    return out, int(np.mean([len(v.gts) for v in views]))


class VerifiedLatency:
    """Subscriber callback: per object, the put time of the first image since its last verified
    estimate whose unverified estimate arrived, and, when the verified one arrives, the wall
    time between (ms)."""

    def __init__(self, put_time: dict[int, float]):
        self.put_time = put_time
        self.waiting: dict[str, float] = {}
        self.latencies_ms: list[float] = []

    def __call__(self, sample) -> None:
        msg = msgpack.unpackb(sample.payload.to_bytes())
        oid = msg["object_id"]
        if msg.get("verified"):
            since = self.waiting.pop(oid, None)
            if since is not None:
                self.latencies_ms.append(1000 * (time.perf_counter() - since))
        elif msg["stamp_ns"] in self.put_time:
            self.waiting.setdefault(oid, self.put_time[msg["stamp_ns"]])

    def clear(self) -> None:
        self.waiting.clear()
        self.latencies_ms.clear()


class Publisher:
    """Puts frames of several cameras on one session; records put times by stamp."""

    def __init__(self, session):
        self.session = session
        self.stamp = 1_000_000_000_000
        self.put_time: dict[int, float] = {}

    def send(self, cam: str, view) -> None:
        from posefuse.service.codec import encode_camera_info, encode_camera_pose

        camera, T_world_cam, msg = view
        self.stamp += 10_000_000
        s = self.stamp
        root = f"{CELL}/@v1/cam/{cam}"
        self.session.put(f"{root}/info", encode_camera_info(s, cam, camera))
        self.session.put(f"{root}/pose", encode_camera_pose(s - 1000, cam, T_world_cam))
        msg = dict(msg, stamp_ns=s, camera_id=cam)
        self.put_time[s] = time.perf_counter()
        self.session.put(f"{root}/image", msgpack.packb(msg, use_bin_type=True))
        self.session.put(f"{root}/pose", encode_camera_pose(s + 1000, cam, T_world_cam))


def _reset(base: str) -> None:
    req = urllib.request.Request(f"{base}/reset", data=b"{}", method="POST")
    req.add_header("Content-Type", "application/json")
    urllib.request.urlopen(req, timeout=5).read()


def main(argv: list[str] | None = None) -> int:
    import zenoh

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--few", required=True, help="DIR:SCENE with about 8 objects in view")
    parser.add_argument("--many", required=True, help="DIR:SCENE with about 30 objects")
    parser.add_argument("--seconds", type=float, default=20.0, help="per throughput run")
    parser.add_argument("--latency-frames", type=int, default=40)
    parser.add_argument("--json", help="write the results here too")
    parser.add_argument(
        "--parts",
        help="serve this part set of `posefuse onboard` (default: the shipped catalog); the "
        "scenes must be renders of its parts",
    )
    args = parser.parse_args(argv)

    scenes = {"few": _scene_messages(args.few), "many": _scene_messages(args.many)}
    daemon, zport, base = start_daemon(CELL, args.parts)
    results: dict = {}
    try:
        conf = peer_config(zport)
        first_update = FirstUpdates()
        with zenoh.open(conf) as session:
            session.declare_subscriber(f"{CELL}/@v1/objects/*", first_update)
            pub = Publisher(session)
            verified = VerifiedLatency(pub.put_time)
            session.declare_subscriber(f"{CELL}/@v1/objects/*", verified)
            time.sleep(1.0)

            def run(cameras: int, rate: float, n: int, views) -> dict:
                before = _get(f"{base}/stats")
                start = time.perf_counter()
                for k in range(n):
                    for c in range(cameras):
                        delay = start + (k + c / cameras) / rate - time.perf_counter()
                        if delay > 0:
                            time.sleep(delay)
                        pub.send(f"cam{c}", views[(k + 3 * c) % len(views)])
                time.sleep(3.0)
                after = _get(f"{base}/stats")
                processed = after["frames_processed"] - before["frames_processed"]
                return {"sent": n * cameras, "processed": processed}

            for name, (views, n_obj) in scenes.items():
                _reset(base)
                first_update.clear()
                pub.put_time.clear()
                run(1, 2.0, args.latency_frames, views)
                lat = [
                    1000 * (first_update[s] - t)
                    for s, t in pub.put_time.items()
                    if s in first_update
                ]
                results[f"latency_{name}"] = {
                    "objects_per_view": n_obj,
                    "frames": len(lat),
                    "p50_ms": float(np.percentile(lat, 50)),
                    "p95_ms": float(np.percentile(lat, 95)),
                }
                print(
                    f"latency, {n_obj} objects per view ({len(lat)} frames at 2 Hz): "
                    f"p50 {np.percentile(lat, 50):.0f} ms, p95 {np.percentile(lat, 95):.0f} ms",
                    flush=True,
                )
            for name, cameras, rate in (("few", 1, 10.0), ("many", 1, 10.0), ("few", 4, 2.0)):
                views, n_obj = scenes[name]
                _reset(base)
                verified.clear()
                pub.put_time.clear()
                r = run(cameras, rate, int(args.seconds * rate), views)
                r["fraction"] = r["processed"] / r["sent"]
                lat = verified.latencies_ms
                r["verified"] = {
                    "updates": len(lat),
                    "p50_ms": float(np.percentile(lat, 50)) if lat else None,
                    "p95_ms": float(np.percentile(lat, 95)) if lat else None,
                    "waiting_at_end": _get(f"{base}/stats")["verification"]["waiting"],
                }
                results[f"throughput_{name}_{cameras}x{rate:g}Hz"] = r
                v = r["verified"]
                after = (
                    f"; image -> verified pose p50 {v['p50_ms']:.0f} ms, p95 {v['p95_ms']:.0f} ms "
                    f"({v['updates']} verified updates, {v['waiting_at_end']} still waiting)"
                    if lat
                    else "; no verified estimate"
                )
                print(
                    f"{cameras} camera(s) at {rate:g} Hz, {n_obj} objects per view "
                    f"({args.seconds:.0f} s): sent {r['sent']}, processed {r['processed']} "
                    f"({100 * r['fraction']:.1f}%){after}",
                    flush=True,
                )
    finally:
        daemon.terminate()
        daemon.wait(timeout=20)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
