"""The HTTP API through TestClient, over a daemon whose worker saw a synthetic sequence."""

import json

import pytest
from fastapi.testclient import TestClient

from posefuse.estimator.tracker import MultiViewEstimator
from posefuse.service.api import create_app
from posefuse.service.daemon import Daemon
from posefuse.service.settings import Settings
from posefuse.service.sync import SyncedFrame
from posefuse.service.worker import EstimatorWorker
from posefuse.sim.scenes import SceneSpec
from posefuse.sim.sequences import make_sequence


@pytest.fixture()
def daemon(robi_catalog):
    seq = make_sequence(robi_catalog, 5, SceneSpec(n_views=4))
    by_stamp = {v.frame.stamp_ns: v.detections for v in seq.views}
    worker = EstimatorWorker(MultiViewEstimator(robi_catalog), lambda image, stamp: by_stamp[stamp])
    d = Daemon(Settings(), worker)
    for v in seq.views:
        f = v.frame
        worker.process(SyncedFrame("cam0", f.stamp_ns, None, f.camera, f.T_world_cam))
    return d


def test_health_ready_objects(daemon):
    client = TestClient(create_app(daemon))
    assert client.get("/healthz").json() == {"status": "ok"}
    assert client.get("/readyz").status_code == 503
    daemon.ready.set()
    assert client.get("/readyz").status_code == 200
    objects = client.get("/objects").json()
    assert len(objects) >= 3
    one = objects[0]
    assert set(one) >= {"object_id", "t", "q", "cov", "confidence", "n_views", "status"}
    assert len(one["cov"]) == 36 and len(one["q"]) == 4
    assert client.get(f"/objects/{one['object_id']}").json()["t"] == one["t"]
    assert client.get("/objects/nope-999").status_code == 404


def test_reset_and_stats(daemon):
    client = TestClient(create_app(daemon))
    objects = client.get("/objects").json()
    first = objects[0]["object_id"]
    assert client.post("/reset", json={"object_id": first}).json() == {"removed": 1}
    assert client.post("/reset", json={"object_id": first}).status_code == 404
    assert client.post("/reset", json={"class_id": 1, "object_id": "x"}).status_code == 422
    assert client.post("/reset", json={"class_id": 99}).status_code == 404
    n_left = len(client.get("/objects").json())
    assert client.post("/reset").json() == {"removed": n_left}
    assert client.get("/objects").json() == []
    stats = client.get("/stats").json()
    assert stats["frames_processed"] == 4 and "latency" in stats and "decode_errors" in stats


def test_events_stream(daemon):
    client = TestClient(create_app(daemon))
    q = daemon.subscribe()
    daemon.unsubscribe(q)
    # one reset event queued before the stream reads it
    with client.stream("GET", "/events", params={"max_events": 1}) as response:
        daemon.reset()
        body = "".join(response.iter_text())
    assert "event: reset" in body
    data = json.loads(body.split("data: ")[1].strip())
    assert data["reset"]["removed"] >= 1


def test_openapi_has_examples(daemon):
    spec = TestClient(create_app(daemon)).get("/openapi.json").json()
    assert "/objects/{object_id}" in spec["paths"]
    assert "examples" in json.dumps(spec["components"]["schemas"]["ObjectEstimateModel"])


def test_docs_page_loads_its_assets_locally_not_from_a_cdn(daemon):
    client = TestClient(create_app(daemon))
    page = client.get("/docs")
    assert page.status_code == 200
    assert "cdn" not in page.text.lower()
    for asset in ("/docs-assets/swagger-ui-bundle.js", "/docs-assets/swagger-ui.css"):
        assert asset in page.text
        got = client.get(asset)
        assert got.status_code == 200 and len(got.content) > 1000


def test_a_class_id_written_as_4_0_is_class_4(daemon):
    """JSON Schema's integer includes 4.0; the API takes it as the class it names."""
    client = TestClient(create_app(daemon))
    r = client.post(
        "/reset", content='{"class_id": 4.0}', headers={"content-type": "application/json"}
    )
    assert r.status_code == 200, r.text


@pytest.mark.parametrize(
    "body",
    [
        '{"class_id": NaN}',
        '{"class_id": Infinity}',
        '{"class_id": -Infinity}',
        '{"class_id": 1e400}',
        '{"class_id": true}',
        '{"class_id": 1.5}',
        '{"class_id": "1"}',
        '{"class_id": 0}',
        '{"object_id": ""}',
        '{"object_id": 5}',
        '{"clas_id": 1}',
        "[1, 2]",
    ],
)
def test_bad_reset_bodies_are_422_and_change_nothing(daemon, body):
    client = TestClient(create_app(daemon))
    before = client.get("/objects").json()
    r = client.post("/reset", content=body, headers={"content-type": "application/json"})
    assert r.status_code == 422, r.text
    assert isinstance(r.json()["detail"], list) and r.json()["detail"][0]["msg"]
    assert client.get("/objects").json() == before


@pytest.mark.parametrize("route", ["/reset", "/nbv"])
@pytest.mark.parametrize(
    "body", [b"not json", b'{"class_id": 1', b"{'class_id': 1}", b'{"object_id": "\xff\xfe"}']
)
def test_bodies_that_are_not_utf8_json_are_400_as_documented(daemon, route, body):
    client = TestClient(create_app(daemon))
    before = client.get("/objects").json()
    r = client.post(route, content=body, headers={"content-type": "application/json"})
    assert r.status_code == 400, r.text
    assert isinstance(r.json()["detail"], str) and r.json()["detail"]
    assert client.get("/objects").json() == before
    spec = client.get("/openapi.json").json()
    assert "400" in spec["paths"][route]["post"]["responses"]


def test_body_size_limit(daemon):
    client = TestClient(create_app(daemon))
    big = b'{"object_id": "' + b"x" * 200_000 + b'"}'
    r = client.post("/reset", content=big, headers={"content-type": "application/json"})
    assert r.status_code == 413 and "x" * 100 not in r.text

    def chunks():  # no Content-Length: the limit applies while the body streams in
        for _ in range(100):
            yield b"x" * 10_000

    r = client.post("/reset", content=chunks(), headers={"content-type": "application/json"})
    assert r.status_code == 413
    assert len(client.get("/objects").json()) >= 3


def test_api_token_guards_mutating_routes(daemon):
    from posefuse.service.settings import Settings

    daemon.settings = Settings(api_token="s3cret-token", protect_events=True)
    client = TestClient(create_app(daemon))
    n = len(client.get("/objects").json())  # reading needs no token
    assert n >= 3
    assert client.post("/reset").status_code == 401
    wrong = {"Authorization": "Bearer nope"}
    assert client.post("/reset", headers=wrong).status_code == 401
    assert client.get("/events", params={"max_events": 1}).status_code == 401
    assert len(client.get("/objects").json()) == n
    events = daemon.stats_dict()["events"]
    assert events["reset_unauthorized"] == 2  # counted as the Zenoh reset query's are
    assert events["http_unauthorized"] == 3  # /events too
    good = {"Authorization": "Bearer s3cret-token"}
    assert client.post("/reset", headers=good).json() == {"removed": n}
    assert daemon.stats_dict()["events"]["reset_unauthorized"] == 2
    spec = client.get("/openapi.json").json()
    assert "401" in spec["paths"]["/reset"]["post"]["responses"]


def test_every_status_code_a_route_gives_is_documented(daemon):
    spec = TestClient(create_app(daemon)).get("/openapi.json").json()
    reset = spec["paths"]["/reset"]["post"]["responses"]
    assert {"200", "404", "413", "422"} <= set(reset)
    assert "404" in spec["paths"]["/objects/{object_id}"]["get"]["responses"]
    assert "503" in spec["paths"]["/readyz"]["get"]["responses"]
    events = spec["paths"]["/events"]["get"]["responses"]["200"]["content"]
    assert list(events) == ["text/event-stream"]


def test_next_best_view(daemon):
    from posefuse.estimator.nbv import default_candidates
    from posefuse.sim.scenes import REALSENSE_1280x720 as CAM

    client = TestClient(create_app(daemon))
    # no camera info yet: candidates need their intrinsics
    assert client.post("/nbv", json={}).status_code == 409
    cam = {"K": CAM.K.reshape(9).tolist(), "width": CAM.width, "height": CAM.height}
    poses = [c.T_world_cam.reshape(16).tolist() for c in default_candidates(CAM)]
    body = {"candidates": [{"T_world_cam": T, **cam} for T in poses], "top_k": 5}
    reply = client.post("/nbv", json=body)
    assert reply.status_code == 200, reply.text
    reply = reply.json()
    assert reply["candidates"] == len(poses) and len(reply["ranked"]) == 5
    scores = [r["score"] for r in reply["ranked"]]
    assert scores == sorted(scores, reverse=True) and scores[0] > 0
    known = {o["object_id"] for o in client.get("/objects").json()}
    best = reply["ranked"][0]
    assert best["T_world_cam"] == poses[best["index"]]
    named = {o["object_id"] for o in best["objects"]}
    # parts seen in one view only are named after their detection
    assert named and {o for o in named if not o.startswith("held/")} <= known
    # a pose that is not rigid, a field that is not known
    bad = {"candidates": [{"T_world_cam": [2.0] * 16, **cam}]}
    assert client.post("/nbv", json=bad).status_code == 422
    assert client.post("/nbv", json={"candidates": [], "top_k": 1}).status_code == 422
    assert client.post("/nbv", json={"nope": 1}).status_code == 422
    needing = client.get("/stats").json()["objects_needing_views"]
    assert set(needing) <= known
