"""Authenticated control and secured transport: the API token on Zenoh reset queries, a Zenoh
config file whose TLS listener and access-control rules the daemon keeps (docs/security.md runs
the same configurations)."""

import contextlib
import datetime
import ipaddress
import json
import threading

import msgpack
import pytest
from loopback import SECOND, FakeCamera, free_port, wait_until

from posefuse.estimator.tracker import MultiViewEstimator
from posefuse.service.daemon import Daemon
from posefuse.service.settings import Settings, zenoh_config
from posefuse.service.sync import SyncedFrame
from posefuse.service.worker import EstimatorWorker
from posefuse.sim.scenes import SceneSpec
from posefuse.sim.sequences import make_sequence

CELL = "sec"


def make_certificates(folder):
    """A throw-away CA and a server certificate for localhost / 127.0.0.1, as PEM files."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    def name(cn):
        return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)])

    now = datetime.datetime.now(datetime.UTC)
    valid = dict(
        not_valid_before=now - datetime.timedelta(hours=1),
        not_valid_after=now + datetime.timedelta(days=1),
    )
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca = (
        x509.CertificateBuilder(**valid)
        .subject_name(name("posefuse test CA"))
        .issuer_name(name("posefuse test CA"))
        .public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
        .sign(ca_key, hashes.SHA256())
    )
    key = ec.generate_private_key(ec.SECP256R1())
    san = [x509.DNSName("localhost"), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]
    cert = (
        x509.CertificateBuilder(**valid)
        .subject_name(name("localhost"))
        .issuer_name(ca.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .add_extension(x509.SubjectAlternativeName(san), critical=False)
        .sign(ca_key, hashes.SHA256())
    )
    pem = serialization.Encoding.PEM
    paths = {k: folder / f"{k}.pem" for k in ("ca", "cert", "key")}
    paths["ca"].write_bytes(ca.public_bytes(pem))
    paths["cert"].write_bytes(cert.public_bytes(pem))
    paths["key"].write_bytes(
        key.private_bytes(pem, serialization.PrivateFormat.PKCS8, serialization.NoEncryption())
    )
    return paths


@pytest.fixture(scope="module")
def tracked_worker_factory(robi_catalog):
    seq = make_sequence(robi_catalog, 5, SceneSpec(n_views=3))
    by_stamp = {v.frame.stamp_ns: v.detections for v in seq.views}

    def make():
        worker = EstimatorWorker(
            MultiViewEstimator(robi_catalog), lambda image, s: by_stamp.get(s, [])
        )
        for v in seq.views:
            f = v.frame
            worker.process(SyncedFrame("cam0", f.stamp_ns, None, f.camera, f.T_world_cam))
        return worker

    return make


@contextlib.contextmanager
def running(daemon: Daemon):
    thread = threading.Thread(target=daemon.run, daemon=True)
    thread.start()
    try:
        assert daemon.ready.wait(20), "the daemon's session did not open"
        yield daemon
    finally:
        daemon.stop()
        thread.join(timeout=10)


def _session(endpoint: str, **extra):
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", "[]")
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    for key, value in extra.items():
        conf.insert_json5(key, json.dumps(value))
    return zenoh.open(conf)


def _state_replies(session, timeout: float = 3):
    return [r.ok for r in session.get(f"{CELL}/@v1/estimator/state", timeout=timeout) if r.ok]


def _wait_linked(session, *input_keys: str):
    """Until the daemon answers a state query over ``session`` (the link is up and its
    queryables are known here) and every input key has a subscriber: after this, a query or a
    message that gets nowhere was refused, not early."""
    wait_until(lambda: _state_replies(session, 1), 30, what="the daemon's state queryable")
    for key in input_keys:
        publisher = session.declare_publisher(key)
        try:
            wait_until(
                lambda p=publisher: p.matching_status.matching, 30, what=f"a subscriber of {key}"
            )
        finally:
            publisher.undeclare()


def _reset(session, attachment=None):
    kwargs = {"payload": b"", "timeout": 3}
    if attachment is not None:
        kwargs["attachment"] = attachment
    replies = [r.ok for r in session.get(f"{CELL}/@v1/estimator/reset", **kwargs) if r.ok]
    return [msgpack.unpackb(r.payload.to_bytes()) for r in replies]


def test_a_config_files_listen_and_connect_are_kept_unless_given(tmp_path):
    path = tmp_path / "zenoh.json5"
    path.write_text(json.dumps({"mode": "peer", "listen": {"endpoints": ["tls/localhost:7448"]}}))
    kept = zenoh_config(Settings(zenoh_config=path))
    assert json.loads(kept.get_json("listen/endpoints")) == ["tls/localhost:7448"]
    given = zenoh_config(Settings(zenoh_config=path, listen=["tcp/127.0.0.1:7000"]))
    assert json.loads(given.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7000"]
    with pytest.raises(ValueError, match="not a file"):
        zenoh_config(Settings(zenoh_config=tmp_path / "missing.json5"))


def test_zenoh_reset_needs_the_api_token(tracked_worker_factory):
    port = free_port()
    settings = Settings(cell=CELL, listen=[f"tcp/127.0.0.1:{port}"], api_token="s3cret")
    daemon = Daemon(settings, tracked_worker_factory())
    n = len(daemon.worker.snapshot())
    assert n >= 3
    with running(daemon), _session(f"tcp/127.0.0.1:{port}") as session:
        _wait_linked(session)
        assert "unauthorized" in _reset(session)[0]["error"]
        assert "unauthorized" in _reset(session, b"wrong")[0]["error"]
        assert len(daemon.worker.snapshot()) == n
        assert _reset(session, b"s3cret") == [{"v": 1, "removed": n}]
        assert daemon.stats_dict()["events"]["reset_unauthorized"] == 2


def test_tls_listener_of_a_config_file_exchanges_a_frame(tmp_path, robi_catalog):
    certs = make_certificates(tmp_path)
    port = free_port()
    config = tmp_path / "zenoh-tls.json5"
    config.write_text(
        json.dumps(
            {
                "mode": "peer",
                "listen": {"endpoints": [f"tls/localhost:{port}"]},
                "scouting": {"multicast": {"enabled": False}},
                "transport": {
                    "link": {
                        "tls": {
                            "listen_certificate": str(certs["cert"]),
                            "listen_private_key": str(certs["key"]),
                        }
                    }
                },
            }
        )
    )
    worker = EstimatorWorker(MultiViewEstimator(robi_catalog), lambda image, s: [])
    daemon = Daemon(Settings(cell=CELL, zenoh_config=config), worker)
    tls_client = {"transport/link/tls/root_ca_certificate": str(certs["ca"])}
    with running(daemon), _session(f"tls/localhost:{port}", **tls_client) as session:
        cam = FakeCamera(session, CELL, "tls-cam")
        _wait_linked(session, cam.key("info"), cam.key("pose"), cam.key("image"))
        cam.info()
        cam.frame(5 * SECOND)
        wait_until(lambda: daemon.stats.processed == 1, 20, what="the frame over TLS")
        assert daemon.stats_dict()["cameras"]["tls-cam"]["processed"] == 1


def test_an_access_control_rule_denies_a_reset(tmp_path, tracked_worker_factory):
    port = free_port()
    config = tmp_path / "zenoh-acl.json5"
    config.write_text(
        json.dumps(
            {
                "mode": "peer",
                "listen": {"endpoints": [f"tcp/127.0.0.1:{port}"]},
                "scouting": {"multicast": {"enabled": False}},
                "access_control": {
                    "enabled": True,
                    "default_permission": "allow",
                    "rules": [
                        {
                            "id": "no-remote-reset",
                            "messages": ["query"],
                            "flows": ["ingress"],
                            "permission": "deny",
                            "key_exprs": [f"{CELL}/@v1/estimator/reset"],
                        }
                    ],
                    "subjects": [{"id": "tcp-peers", "link_protocols": ["tcp"]}],
                    "policies": [{"rules": ["no-remote-reset"], "subjects": ["tcp-peers"]}],
                },
            }
        )
    )
    daemon = Daemon(Settings(cell=CELL, zenoh_config=config), tracked_worker_factory())
    n = len(daemon.worker.snapshot())
    with running(daemon), _session(f"tcp/127.0.0.1:{port}") as session:
        # the link is up and the daemon answers this peer's queries (the state query is not
        # denied): an empty reply to the reset is the rule, not a link still coming up
        _wait_linked(session)
        assert _reset(session) == []  # denied: the query never reaches the daemon
        assert len(daemon.worker.snapshot()) == n
        assert not any("reset" in e for e in daemon.stats_dict()["events"])
        state = _state_replies(session)
        assert len(msgpack.unpackb(state[0].payload.to_bytes())["objects"]) == n
