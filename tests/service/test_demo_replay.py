"""The demo recording: offline replay equals the committed expected estimates; replays are
byte-identical."""

import json
from pathlib import Path

import numpy as np
import pytest

from posefuse.estimator.core.objects import load_catalog
from posefuse.estimator.tracker import MultiViewEstimator
from posefuse.evaluation.eval_points import eval_points
from posefuse.evaluation.pose_error import eval_symmetries
from posefuse.service.foxglove import FoxgloveMirror
from posefuse.service.recording import Recorder, read_messages
from posefuse.service.replay import replay_offline, write_estimates_json
from posefuse.service.resources import DEFAULT_CATALOG, DEFAULT_MODEL, DEFAULT_RECORDING
from posefuse.service.settings import Settings
from posefuse.service.worker import EstimatorWorker, make_detector, tracker_config

EXPECTED = Path(DEFAULT_RECORDING).with_suffix(".expected.json")
# the shipped front end the expected file was made with (sha256 of models/robi_like.onnx, its
# crop model and its card, in that order): another model gives other estimates; its replay is
# still held to the ground-truth floor below
EXPECTED_MODEL_SHA256 = "e1f669bc6ae8d99077a0d75b2a948388c722bc2aebadd93e3e07941f03559567"
# the front end's detections (class, center u, v) of the recording's first frames on the
# machine that wrote the expected file: where this machine's network computes them otherwise
# (onnxruntime's kernels differ with the CPU's features), the discrete choices downstream
# (template ties, mixture pruning) can differ too, and the expected file cannot be matched
EXPECTED_FRONTEND = EXPECTED.with_name(EXPECTED.stem + "_frontend.json")
FRONTEND_FRAMES = 3
# share of confirmed estimates within ADD-sym 0.1 d of a true part: 29 of 29 in the expected
# file; a replay below half of its confirmed estimates right is broken
FLOOR = 0.5
MIN_CORRECT = 12


def _truth() -> list[list[tuple[int, np.ndarray]]]:
    """Each segment's true parts (obj_id, T_world_obj), from the recording's own ground truth:
    a segment ends at each reset, as the replay's do."""
    from posefuse.service.codec import decode_groundtruth

    segments, current = [], None
    for m in read_messages(DEFAULT_RECORDING):
        if "/groundtruth/" in m.key:
            current = decode_groundtruth(m.payload)
        elif m.key.endswith("/estimator/reset") and current is not None:
            segments.append(current)
            current = None
    if current is not None:
        segments.append(current)
    return segments


def frontend_fingerprint() -> list[list[list[float]]]:
    """Per frame, the first FRONTEND_FRAMES images' detections as [obj_id, u, v], as the daemon
    computes them (the shipped model, its default threads, the image's own seed)."""
    from posefuse.estimator.frontend.network import NetworkFrontend
    from posefuse.service.codec import decoders

    decode = decoders()["image"]
    network = NetworkFrontend(
        DEFAULT_MODEL, load_catalog(DEFAULT_CATALOG), threads=Settings().onnx_threads
    )
    frames = []
    for m in read_messages(DEFAULT_RECORDING):
        if m.key.endswith("/image"):
            msg = decode(m.payload)
            dets = network.detect(msg.image)
            frames.append([[float(d.obj_id), *map(float, d.center_uv)] for d in dets])
            if len(frames) == FRONTEND_FRAMES:
                break
    return frames


def _same_frontend() -> bool:
    """Whether this machine's front end gives the expected file's machine's detections (to
    1e-4 px) on the first frames."""
    want = json.loads(EXPECTED_FRONTEND.read_text())
    got = frontend_fingerprint()
    return len(got) == len(want) and all(
        len(g) == len(w) and np.allclose(g, w, rtol=0, atol=1e-4)
        for g, w in zip(got, want, strict=True)
    )


def _score(segments: list[list[dict]]) -> tuple[int, int, float]:
    """(correct, confirmed): ADD-sym (the function
    checked against bop_toolkit) of each confirmed estimate to the closest unmatched true part of
    its class, greedy by confidence, one-to-one."""
    from scipy.spatial.transform import Rotation

    from posefuse.evaluation import pose_error

    catalog = load_catalog(DEFAULT_CATALOG)
    truth = _truth()
    assert len(truth) == len(segments) == 3
    correct = confirmed = 0
    for estimates, parts in zip(segments, truth, strict=True):
        free = set(range(len(parts)))
        for e in sorted(estimates, key=lambda e: -e["confidence"]):
            if e["status"] != "confirmed":
                continue
            confirmed += 1
            model = catalog[e["class_id"]]
            T = np.eye(4)
            T[:3, :3] = Rotation.from_quat(e["q"]).as_matrix()
            T[:3, 3] = e["t"]
            errors = {
                k: pose_error.add_sym(T, parts[k][1], eval_points(model), eval_symmetries(model))
                for k in free
                if parts[k][0] == e["class_id"]
            }
            if errors and min(errors.values()) < 0.1 * model.diameter:
                correct += 1
                free.discard(min(errors, key=errors.get))
    return correct, confirmed


def _assert_above_the_floor(segments):
    correct, confirmed = _score(segments)
    assert correct >= MIN_CORRECT and correct >= FLOOR * confirmed, (correct, confirmed)


def test_the_expected_file_is_right_against_the_recordings_truth():
    _assert_above_the_floor(json.loads(EXPECTED.read_text())["segments"])


def test_random_rotations_fall_below_the_floor():
    """The floor means something: the expected estimates with random rotations fail it."""
    from scipy.spatial.transform import Rotation

    segments = json.loads(EXPECTED.read_text())["segments"]
    rng = np.random.default_rng(0)
    broken = [
        [{**e, "q": list(Rotation.random(random_state=rng).as_quat())} for e in seg]
        for seg in segments
    ]
    with pytest.raises(AssertionError):
        _assert_above_the_floor(broken)


def _replay(default_banks, mcap_out=None):
    catalog = load_catalog(DEFAULT_CATALOG)
    settings = Settings(model=DEFAULT_MODEL, catalog=DEFAULT_CATALOG)
    config = tracker_config(settings)  # as the daemon has it
    worker = EstimatorWorker(
        MultiViewEstimator(catalog, config, banks=default_banks), make_detector(settings, catalog)
    )
    messages = [(m.log_time_ns, m.key, m.payload) for m in read_messages(DEFAULT_RECORDING)]
    if mcap_out is None:
        return replay_offline(messages, worker)
    with Recorder(mcap_out, mirror=FoxgloveMirror("posefuse", catalog)) as recorder:
        return replay_offline(messages, worker, recorder=recorder)


def test_offline_replay_matches_the_expected_file_and_is_repeatable(default_banks, tmp_path):
    """Byte-identical replays here, right against the recording's truth; equal to the expected
    file (1e-6) when the shipped model is the one it was made with."""
    import hashlib

    outputs, recordings = [], []
    for k in range(3):
        result = _replay(default_banks, tmp_path / f"r{k}.mcap")
        path = write_estimates_json(tmp_path / f"r{k}.json", result.published, result.segments)
        outputs.append(path.read_bytes())
        recordings.append((tmp_path / f"r{k}.mcap").read_bytes())
    assert outputs[0] == outputs[1] == outputs[2]
    assert recordings[0] == recordings[1] == recordings[2]
    got = json.loads(outputs[0])
    _assert_above_the_floor(got["segments"])
    model = Path(DEFAULT_MODEL)
    h = hashlib.sha256()
    for f in (model, model.with_name(model.stem + "_crop.onnx"), model.with_suffix(".json")):
        h.update(f.read_bytes() if f.is_file() else b"")
    shipped = h.hexdigest()
    if shipped != EXPECTED_MODEL_SHA256:
        pytest.skip(
            f"{EXPECTED} was made with another model than {DEFAULT_MODEL}: regenerate it with "
            "`posefuse replay recordings/demo.mcap --offline --out DIR` and its front end's "
            f"{EXPECTED_FRONTEND.name} with `python tests/service/test_demo_replay.py` (the replay "
            "met the floor)"
        )
    expected = json.loads(EXPECTED.read_text())
    if not _same_frontend():
        # another machine's network: hold the replay to the expected file's score instead
        correct, confirmed = _score(got["segments"])[:2]
        want_correct, want_confirmed = _score(expected["segments"])[:2]
        assert abs(correct - want_correct) <= 3 and abs(confirmed - want_confirmed) <= 3, (
            f"{correct} of {confirmed} right, the expected file {want_correct} of {want_confirmed}"
        )
        pytest.skip(
            "this machine's front end differs from the expected file's in the last bits "
            f"({EXPECTED_FRONTEND.name}): scored against the truth only, {correct} of "
            f"{confirmed} right against the expected file's {want_correct} of {want_confirmed}"
        )
    assert len(got["updates"]) == len(expected["updates"])
    assert len(got["segments"]) == len(expected["segments"])
    for g_seg, e_seg in zip(got["segments"], expected["segments"], strict=True):
        assert [o["object_id"] for o in g_seg] == [o["object_id"] for o in e_seg]
        for g, e in zip(g_seg, e_seg, strict=True):
            assert (g["status"], g["n_views"], len(g["hypotheses"])) == (
                e["status"],
                e["n_views"],
                len(e["hypotheses"]),
            )
            # the expected file was written on another machine, whose floating point (BLAS, CPU
            # features) may differ in the last bits: compare at a physical tolerance, 1 um and
            # about 2 urad; byte-identity is checked above between replays on this machine
            np.testing.assert_allclose(g["t"], e["t"], atol=1e-6)
            np.testing.assert_allclose(g["q"], e["q"], atol=1e-6)


@pytest.mark.parametrize("cut", [0.3, 0.7])
def test_truncated_recording_gives_the_frames_before_the_damage(tmp_path, cut, default_banks):
    from posefuse.cli.main import main

    data = Path(DEFAULT_RECORDING).read_bytes()
    damaged = tmp_path / "cut.mcap"
    damaged.write_bytes(data[: int(len(data) * cut)])
    code = main(["replay", str(damaged), "--offline", "--out", str(tmp_path / "out")])
    assert code == 2
    doc = json.loads((tmp_path / "out" / "estimates.json").read_text())
    assert doc["updates"], "no estimates from the frames before the damage"


def test_live_lockstep_replay_over_zenoh_equals_offline(default_banks, capsys):
    """posefuse demo's path: daemon + API + replay through Zenoh on loopback, in lockstep."""
    import socket

    from posefuse.service.demo import run_demo

    ports = []
    for _ in range(2):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            ports.append(s.getsockname()[1])
    settings = Settings(
        model=DEFAULT_MODEL,
        catalog=DEFAULT_CATALOG,
        listen=[f"tcp/127.0.0.1:{ports[0]}"],
        http_port=ports[1],
    )
    segments = run_demo(DEFAULT_RECORDING, settings, show_progress=False)
    out = capsys.readouterr().out
    live_segments = [live for _, live in segments]
    correct, confirmed = _score(live_segments)
    # what it prints is what it got, and what it got is right against the truth
    assert f"{correct} of {confirmed} confirmed estimates within ADD-sym 0.1 d" in out, out[-500:]
    _assert_above_the_floor(live_segments)
    # the same estimates as the offline replay on this machine, to a physical tolerance
    offline = _replay(default_banks).segments
    assert len(live_segments) == len(offline)
    for live, off in zip(live_segments, offline, strict=True):
        assert [o["object_id"] for o in live] == [o["object_id"] for o in off]
        for a, b in zip(live, off, strict=True):
            assert a["status"] == b["status"] and a["n_views"] == b["n_views"]
            np.testing.assert_allclose(a["t"], b["t"], atol=1e-6)
            np.testing.assert_allclose(a["q"], b["q"], atol=1e-6)


if __name__ == "__main__":
    # the front end's fingerprint beside a regenerated expected file, on the same machine
    EXPECTED_FRONTEND.write_text(json.dumps(frontend_fingerprint()) + "\n")
    print(f"wrote {EXPECTED_FRONTEND}")
