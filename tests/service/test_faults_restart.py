"""Faults that are a process: the daemon killed with SIGKILL and started again (its tracks come
back from the state folder, its cameras are asked for their info), and the Zenoh router killed
and started again under a daemon and a camera that are its clients (loss is counted by sequence
numbers, and good frames are processed once the router is back)."""

import time

from loopback import (
    SECOND,
    FakeCamera,
    ServeProcess,
    free_port,
    start_router,
    wait_until,
    zenoh_peer,
)

from posefuse.clients.camera import InfoServer, scene_messages
from posefuse.evaluation.dataset import load_dataset

RSS_BOUND_MB = 1024


def _put_all(session, messages, info_server, daemon, pause=0.02):
    """Publish in order, as a camera the daemon keeps up with: after each pose, the next
    message waits until every image sent so far was handled (at most 1 s)."""
    base = daemon.stats()["frames_handled"]
    images = 0
    for _, key, payload in messages:
        if key.endswith("/info"):
            info_server.publish(key, payload)
        session.put(key, payload)
        images += key.endswith("/image")
        if key.endswith("/pose"):
            deadline = time.time() + 1.0
            while daemon.stats()["frames_handled"] - base < images and time.time() < deadline:
                time.sleep(0.02)
        time.sleep(pause)


def test_kill_9_and_restart_restores_the_tracks(full_res_dataset, tmp_path):
    state_dir = tmp_path / "state"
    env = {"POSEFUSE_STATE_INTERVAL_S": "0.5"}
    args = ("--cell", "restart", "--state-dir", str(state_dir))
    messages = list(scene_messages(load_dataset(full_res_dataset), 0, "restart", "cam0", 4.0))
    n_images = sum(k.endswith("/image") for _, k, _ in messages)
    daemon = ServeProcess(*args, env=env)
    try:
        with zenoh_peer(daemon.endpoint) as session:
            time.sleep(0.5)
            info_server = InfoServer(session)  # answers info requests, as a camera does
            _put_all(session, messages, info_server, daemon)
            # every frame fused, and every track verified (the deferred step), so that the
            # estimates read now are those of the snapshots that follow
            wait_until(
                lambda: (
                    (s := daemon.stats())["frames_processed"] == n_images
                    and s["verification"]["waiting"] == 0
                ),
                120,
                context=daemon.stats,
            )
            before = {o["object_id"]: o for o in daemon.objects()}
            confirmed = {k for k, o in before.items() if o["status"] == "confirmed"}
            assert confirmed, before
            saved = daemon.stats()["events"].get("state_saved", 0)
            wait_until(lambda: daemon.stats()["events"].get("state_saved", 0) > saved + 1, 10)
            daemon.kill()

            daemon = ServeProcess(*args, env=env, timeout=180)
            # its listen port is new: connect the camera to it
            with zenoh_peer(daemon.endpoint) as session2:
                time.sleep(0.5)
                info_server2 = InfoServer(session2)
                for key, payload in info_server.latest.items():
                    info_server2.publish(key, payload)  # known, not re-sent
                after = {o["object_id"]: o for o in daemon.objects()}
                assert daemon.stats()["restored_objects"] == len(before)
                assert confirmed <= set(after)
                for oid in confirmed:
                    assert after[oid]["t"] == before[oid]["t"]
                    assert after[oid]["status"] == "confirmed"
                # the camera goes on without sending its info again: the daemon asks for it
                again = [m for m in messages if not m[1].endswith("/info")]
                _put_all(session2, again, info_server2, daemon)
                wait_until(lambda: daemon.stats()["frames_processed"] == n_images, 120)
                stats = daemon.stats()
                assert stats["events"]["info_requests"] >= 1
                assert stats["events"]["info_replies"] >= 1
                grown = {o["object_id"]: o["n_views"] for o in daemon.objects()}
                assert any(grown.get(oid, 0) > before[oid]["n_views"] for oid in confirmed)
                assert daemon.rss_mb() < RSS_BOUND_MB
                info_server2.close()
            info_server.close()
    finally:
        daemon.stop()


def _client_session(endpoint: str):
    import json

    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    return zenoh.open(conf)


def test_router_kill_and_restart(tmp_path):
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    router = start_router(port)
    daemon = ServeProcess("--cell", "routed", "--mode", "client", "--connect", endpoint)
    try:
        with _client_session(endpoint) as session:
            time.sleep(0.5)
            cam = FakeCamera(session, "routed", "cam0")
            cam.info()
            cam.frames(10 * SECOND, 3, daemon=daemon)
            wait_until(lambda: daemon.stats()["frames_processed"] == 3, 60)
            router.kill()
            router.wait()
            cam.frames(20 * SECOND, 3)  # nobody to route them: lost
            time.sleep(0.5)
            router = start_router(port)
            stamp = 30 * SECOND
            deadline = time.time() + 60
            while daemon.stats()["frames_processed"] < 4:  # until both clients are back
                assert time.time() < deadline, daemon.stats()
                cam.info()
                cam.frame(stamp)
                stamp += SECOND // 10
                time.sleep(0.5)
            stats = daemon.stats()
            cam0 = stats["cameras"]["cam0"]
            sent = cam.seq
            assert cam0["images"] + cam0["lost"].get("image", 0) == sent
            assert cam0["lost"].get("image", 0) >= 3
            assert daemon.rss_mb() < RSS_BOUND_MB
    finally:
        daemon.stop()
        router.kill()
        router.wait()
