"""Daemon and camera client as separate processes over loopback Zenoh, with the HTTP API.

Pose updates arrive over Zenoh and over HTTP; reset works over both (and shows on the SSE
stream); the daemon's estimates equal an offline run of the same messages through the same
worker function.
"""

import json
import os
import subprocess
import sys
import threading
import time
import urllib.request

import msgpack
import numpy as np
from loopback import free_port, get_json

from clients.camera import scene_messages
from estimator.dataset import load_dataset
from estimator.tracker import MultiViewEstimator
from service.codec import estimate_to_dict
from service.resources import DEFAULT_MODEL
from service.worker import EstimatorWorker

N_VIEWS = 4


def _post(url, body):
    req = urllib.request.Request(
        url,
        data=json.dumps(body).encode(),
        method="POST",
        headers={"Content-Type": "application/json"},
    )
    with urllib.request.urlopen(req, timeout=5) as r:
        return json.loads(r.read())


def _offline(dataset, messages):
    """The same messages through the daemon's decoder, synchroniser and worker, in order."""
    from estimator.frontend.network import NetworkFrontend
    from service.replay import replay_offline

    network = NetworkFrontend(DEFAULT_MODEL, dataset.catalog)
    worker = EstimatorWorker(
        MultiViewEstimator(dataset.catalog),
        lambda image, stamp: network.detect(image, stamp_seed=stamp),
    )
    replay_offline(messages, worker, "itest")
    return {e.object_id: estimate_to_dict(e) for e in worker.snapshot()}


def test_daemon_and_camera_over_loopback(full_res_dataset, default_banks, tmp_path):
    import zenoh

    zport, hport = free_port(), free_port()
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    daemon = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "cli",
            "serve",
            "--listen",
            f"tcp/127.0.0.1:{zport}",
            "--http-port",
            str(hport),
            "--cell",
            "itest",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
    )
    base = f"http://127.0.0.1:{hport}"
    try:
        deadline = time.time() + 180
        while True:
            try:
                if get_json(f"{base}/readyz", 1)["status"] == "ready":
                    break
            except OSError:
                pass
            if daemon.poll() is not None or time.time() > deadline:
                raise AssertionError(f"daemon did not start:\n{daemon.stdout.read()}")
            time.sleep(0.5)

        conf = zenoh.Config()
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{zport}"]))
        updates = []
        with zenoh.open(conf) as session:
            sub = session.declare_subscriber(
                "itest/@v1/objects/*",
                lambda s: updates.append(msgpack.unpackb(s.payload.to_bytes())),
            )
            publisher = subprocess.run(
                [
                    sys.executable,
                    "-m",
                    "cli",
                    "publish",
                    "--dataset",
                    str(full_res_dataset),
                    "--scene",
                    "0",
                    "--rate",
                    "4",
                    "--cell",
                    "itest",
                    "--connect",
                    f"tcp/127.0.0.1:{zport}",
                    "--listen",
                    f"tcp/127.0.0.1:{free_port()}",
                ],
                capture_output=True,
                text=True,
                timeout=120,
                env=env,
            )
            assert publisher.returncode == 0, publisher.stderr
            deadline = time.time() + 60
            while get_json(f"{base}/stats")["frames_processed"] < N_VIEWS:
                assert time.time() < deadline, get_json(f"{base}/stats")
                time.sleep(0.5)
            time.sleep(0.5)
            stats = get_json(f"{base}/stats")
            assert stats["frames_received"] == N_VIEWS and stats["decode_errors"] == {}
            objects = {o["object_id"]: o for o in get_json(f"{base}/objects")}
            assert objects, "no objects estimated"
            # the last update received over Zenoh for each object is its current estimate
            last = {u["object_id"]: u for u in updates}
            for oid, o in objects.items():
                assert oid in last and last[oid]["t"] == o["t"]
            # the same estimates as an offline run of the same messages
            messages = list(scene_messages(load_dataset(full_res_dataset), 0, "itest", "cam0", 4.0))
            offline = _offline(load_dataset(full_res_dataset), messages)
            assert set(offline) == set(objects)
            for oid, o in objects.items():
                np.testing.assert_allclose(o["t"], offline[oid]["t"], atol=1e-9)
                np.testing.assert_allclose(o["q"], offline[oid]["q"], atol=1e-9)
                assert o["status"] == offline[oid]["status"]
            # state over Zenoh
            replies = list(session.get("itest/@v1/estimator/state", timeout=5))
            state = msgpack.unpackb(replies[0].ok.payload.to_bytes())
            assert {o["object_id"] for o in state["objects"]} == set(objects)
            # next-best-view over Zenoh and HTTP: the default hemisphere, the same ranking
            replies = list(session.get("itest/@v1/estimator/nbv", timeout=10))
            nbv = msgpack.unpackb(replies[0].ok.payload.to_bytes())
            assert nbv["v"] == 1 and nbv["candidates"] == 50 and len(nbv["ranked"]) == 10
            scores = [r["score"] for r in nbv["ranked"]]
            assert scores == sorted(scores, reverse=True)
            over_http = _post(f"{base}/nbv", {})
            assert [r["index"] for r in over_http["ranked"]] == [r["index"] for r in nbv["ranked"]]
            assert set(get_json(f"{base}/stats")["objects_needing_views"]) <= set(objects)
            # reset one object over Zenoh, seen on the SSE stream; then all over HTTP
            events = []

            def listen():
                with urllib.request.urlopen(f"{base}/events?max_events=1", timeout=20) as r:
                    events.append(r.read().decode())

            listener = threading.Thread(target=listen)
            listener.start()
            time.sleep(1.0)
            first = sorted(objects)[0]
            replies = list(
                session.get(
                    "itest/@v1/estimator/reset",
                    payload=msgpack.packb({"v": 1, "object_id": first}),
                    timeout=5,
                )
            )
            assert msgpack.unpackb(replies[0].ok.payload.to_bytes())["removed"] == 1
            listener.join(timeout=20)
            assert events and "event: reset" in events[0] and first in events[0]
            assert first not in {o["object_id"] for o in get_json(f"{base}/objects")}
            assert _post(f"{base}/reset", {})["removed"] == len(objects) - 1
            assert get_json(f"{base}/objects") == []
            sub.undeclare()
    finally:
        daemon.terminate()
        try:
            daemon.wait(timeout=20)
        except subprocess.TimeoutExpired:
            daemon.kill()
