"""End-to-end service benchmark: latency, the highest input rate kept up with, bounded memory.

python -m posefuse.bench.service_latency --dataset DIR [--frames 40] [--rates 1 2 4 8] [--soak 120]

Starts ``posefuse serve`` as its own process on loopback, and from this process publishes the
views of one scene (1280x720 JPEG, with camera info and poses) over and over with increasing
stamps:

- latency: wall time from putting an image to receiving the first ObjectEstimate stamped with
  it, at a low rate (1 Hz), p50 and p95;
- throughput: at each rate, the fraction of images the daemon processed (from ``/stats``); the
  highest rate with at least 95% processed is the rate it keeps up with;
- memory: at twice that rate for ``--soak`` seconds, the daemon's resident memory every 5 s.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import time
import urllib.request

import msgpack
import numpy as np

from posefuse.evaluation.dataset import load_dataset
from posefuse.service.codec import encode_camera_info, encode_camera_pose, encode_image


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _get(url: str) -> dict:
    with urllib.request.urlopen(url, timeout=5) as r:
        return json.loads(r.read())


def _rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def start_daemon(
    cell: str, parts: str | None = None, env: dict[str, str] | None = None
) -> tuple[subprocess.Popen, int, str]:
    """``posefuse serve`` of ``cell`` on free loopback ports (with the part set ``parts`` of
    ``posefuse onboard``, or the shipped catalog; ``env``: more ``POSEFUSE_*`` settings), once
    ready: (process, Zenoh port, HTTP base URL)."""
    zport, hport = _free_port(), _free_port()
    daemon = subprocess.Popen(
        [sys.executable, "-m", "posefuse.cli", "serve", "--listen", f"tcp/127.0.0.1:{zport}"]
        + ["--http-port", str(hport), "--cell", cell]
        + (["--parts", parts] if parts else []),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        env={**os.environ, **(env or {}), "PYTHONUNBUFFERED": "1"},
    )
    base = f"http://127.0.0.1:{hport}"
    for _ in range(600):
        try:
            if _get(f"{base}/readyz")["status"] == "ready":
                break
        except OSError:
            time.sleep(0.5)
    return daemon, zport, base


def peer_config(zport: int):
    """A Zenoh peer configuration connected to the daemon's port (no scouting)."""
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{zport}"]))
    return conf


class FirstUpdates(dict):
    """Subscriber callback: stamp_ns -> wall time (perf_counter) of the first ObjectEstimate
    received with that stamp."""

    def __call__(self, sample) -> None:
        stamp = msgpack.unpackb(sample.payload.to_bytes())["stamp_ns"]
        self.setdefault(stamp, time.perf_counter())


def main(argv: list[str] | None = None) -> int:
    import zenoh

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", required=True)
    parser.add_argument("--scene", type=int, default=0)
    parser.add_argument("--frames", type=int, default=30, help="frames per rate")
    parser.add_argument("--rates", type=float, nargs="+", default=[1, 2, 4, 8, 16])
    parser.add_argument("--soak", type=float, default=120.0, help="seconds at twice the rate")
    args = parser.parse_args(argv)

    ds = load_dataset(args.dataset)
    scene = ds.scene(args.scene)
    views = [scene.view(i) for i in scene.im_ids]
    images = [encode_image(0, "cam0", scene.load_rgb(v.im_id), "jpeg") for v in views]
    n_objects = len(views[0].gts)
    daemon, zport, base = start_daemon("bench")
    try:
        conf = peer_config(zport)
        first_update = FirstUpdates()
        with zenoh.open(conf) as session:
            session.declare_subscriber("bench/@v1/objects/*", first_update)
            time.sleep(1.0)
            stamp = [1_000_000_000_000]
            put_time: dict[int, float] = {}

            def send(k: int) -> None:
                view = views[k % len(views)]
                stamp[0] += 10_000_000
                s = stamp[0]
                session.put("bench/@v1/cam/cam0/info", encode_camera_info(s, "cam0", view.camera))
                session.put(
                    "bench/@v1/cam/cam0/pose",
                    encode_camera_pose(s - 1000, "cam0", view.T_world_cam),
                )
                msg = msgpack.unpackb(images[k % len(views)])
                msg["stamp_ns"] = s
                put_time[s] = time.perf_counter()
                session.put("bench/@v1/cam/cam0/image", msgpack.packb(msg, use_bin_type=True))
                session.put(
                    "bench/@v1/cam/cam0/pose",
                    encode_camera_pose(s + 1000, "cam0", view.T_world_cam),
                )

            def run(rate: float, n: int) -> dict:
                before = _get(f"{base}/stats")
                start = time.perf_counter()
                for k in range(n):
                    delay = start + k / rate - time.perf_counter()
                    if delay > 0:
                        time.sleep(delay)
                    send(k)
                time.sleep(3.0)
                after = _get(f"{base}/stats")
                received = after["frames_received"] - before["frames_received"]
                processed = after["frames_processed"] - before["frames_processed"]
                return {
                    "rate": rate,
                    "sent": n,
                    "received": received,
                    "processed": processed,
                    "fraction": processed / n,
                }

            # latency at 1 Hz
            first_update.clear()
            put_time.clear()
            run(1.0, min(args.frames, 20))
            lat = [1000 * (first_update[s] - t) for s, t in put_time.items() if s in first_update]
            print(
                f"daemon: posefuse serve, 1280x720 JPEG, {n_objects} objects per view, "
                f"{len(views)} views of {args.dataset} scene {args.scene} replayed"
            )
            print(
                f"latency image put -> first pose update (1 Hz, {len(lat)} frames): "
                f"p50 {np.percentile(lat, 50):.0f} ms, p95 {np.percentile(lat, 95):.0f} ms"
            )
            kept = 0.0
            for rate in args.rates:
                r = run(rate, args.frames)
                print(
                    f"rate {rate:g} Hz: sent {r['sent']}, received {r['received']}, "
                    f"processed {r['processed']} ({100 * r['fraction']:.0f}%)"
                )
                if r["fraction"] >= 0.95:
                    kept = rate
            print(f"highest rate kept up with (>= 95% processed): {kept:g} Hz")
            soak_rate = 2 * max(kept, 1.0)
            rss = [_rss_mb(daemon.pid)]
            t_end = time.perf_counter() + args.soak
            k = 0
            next_sample = time.perf_counter() + 5
            start = time.perf_counter()
            while time.perf_counter() < t_end:
                delay = start + k / soak_rate - time.perf_counter()
                if delay > 0:
                    time.sleep(delay)
                send(k)
                k += 1
                if time.perf_counter() >= next_sample:
                    rss.append(_rss_mb(daemon.pid))
                    next_sample += 5
            stats = _get(f"{base}/stats")
            print(
                f"soak {args.soak:.0f} s at {soak_rate:g} Hz ({k} frames): daemon RSS "
                f"start {rss[0]:.0f} MB, max {max(rss):.0f} MB, end {rss[-1]:.0f} MB; "
                f"dropped {stats['frames_dropped']}"
            )
    finally:
        daemon.terminate()
        daemon.wait(timeout=20)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
