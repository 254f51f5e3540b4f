"""Where the time of one frame goes, stage by stage, in the daemon's own code path.

python -m posefuse.bench.profile_frame --dataset DIR --scene N [--scene M ...] [--repeat 3]

For each scene, its views (1280x720, JPEG-encoded as a camera would send them) go through
what the daemon does with a frame: decode, network, voting, then the estimator (association,
translation, founding/merging, re-crop, template scoring, mixture, the RoI of each view kept
and its edge maps, verification across views and refinement), encode of every updated
estimate and a Zenoh put of each on a session of its own. The stages inside the estimator are
timed by wrapping the functions that implement them (``estimator.tracker`` and
``estimator.rotation.matching`` names), so the profile measures the code as it runs in the service.
Each scene is run ``--repeat`` times with a fresh estimator; the table gives the mean time per
frame of every stage and the median and p95 of the whole frame, then how many views were kept
with their edge maps, how many verifications and refinements ran (counts do not depend on the
machine's speed: a verification beyond the views kept is one the mixture's change asked for).
"""

from __future__ import annotations

import argparse
import contextlib
import time
from collections import Counter, defaultdict

import numpy as np

STAGES = (
    "decode",
    "network",
    "voting",
    "association",
    "translation",
    "founding+merging",
    "re-crop",
    "template scoring",
    "mixture",
    "edge RoIs",
    "edge maps",
    "settled checks",
    "verification",
    "refinement",
    "turn judge",
    "challenge",
    "estimator (rest)",
    "encode",
    "publish",
)


class StageTimer:
    """Accumulates the wall time and the number of calls of wrapped functions per stage
    (outermost calls only)."""

    def __init__(self):
        self.seconds: dict[str, float] = defaultdict(float)
        self.calls: dict[str, int] = defaultdict(int)
        self.accepted = 0  # refinements accepted (the others kept the verified pose)
        self.refused: Counter = Counter()  # the others, by Refinement.refused
        self._depth = 0

    def wrap(self, fn, stage: str):
        def timed(*args, **kwargs):
            if self._depth:
                return fn(*args, **kwargs)
            self._depth += 1
            self.calls[stage] += 1
            start = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                self.seconds[stage] += time.perf_counter() - start
                self._depth -= 1

        return timed

    @contextlib.contextmanager
    def stage(self, name: str):
        start = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] += time.perf_counter() - start


@contextlib.contextmanager
def instrumented(timer: StageTimer):
    """Wrap the estimator's stage functions with ``timer`` for the duration of the block."""
    import posefuse.estimator.rotation.matching as rotation
    import posefuse.estimator.tracker.estimator as walk
    import posefuse.estimator.tracker.pose_stage as tracker
    import posefuse.estimator.tracker.tracks as tracks
    import posefuse.estimator.verification.turns as turns
    from posefuse.estimator.rotation.mixture import RotationMixture

    patches = [
        (walk, "cost_matrix", "association"),
        (walk, "assign", "association"),
        (tracks, "estimate_translation", "translation"),
        (tracks, "marginalize_oldest", "translation"),
        (walk, "choose_pairs", "founding+merging"),
        (tracks, "triangulate_pair", "founding+merging"),
        (tracks, "merge_pairs", "founding+merging"),
        (tracks, "outlier_views", "founding+merging"),
        (rotation, "crop_roi", "re-crop"),
        (rotation.RotationMatcher, "scores", "template scoring"),
        (rotation, "select_hypotheses", "template scoring"),
        (RotationMixture, "add", "mixture"),
        (tracker, "edge_roi", "edge RoIs"),
        (tracker, "edge_maps", "edge maps"),
        (tracker, "agrees", "settled checks"),
        (tracker, "verify", "verification"),
        (tracker, "refine_pose", "refinement"),
        (turns, "judge_turns", "turn judge"),
        # the challenge's scorings and, inside it, its challenger's refinement (timed here,
        # counted among the refinements below)
        (tracker.PoseStage, "_challenge", "challenge"),
    ]
    saved = [(owner, name, getattr(owner, name)) for owner, name, _ in patches]
    try:
        for owner, name, stage in patches:
            setattr(owner, name, timer.wrap(getattr(owner, name), stage))
        timed_refine = tracker.refine_pose

        def refine_counted(*args, **kwargs):
            out = timed_refine(*args, **kwargs)
            timer.accepted += bool(out.accepted)
            if not out.accepted:
                timer.refused[out.refused] += 1
            return out

        tracker.refine_pose = refine_counted
        yield
    finally:
        for owner, name, fn in saved:
            setattr(owner, name, fn)


# the step's work, counted: views kept (edge maps), settled tracks checked against a new view,
# tracks verified, refinements; a verification beyond the views kept is one the "mixture
# changed" rule asked for, and a settled check that agreed is a verification saved
COUNTED = ("edge maps", "settled checks", "verification", "refinement", "turn judge")
# what the daemon's deferred check runs, off the frame's path (the RoIs stay on it)
STEP = (*COUNTED, "challenge")


def profile(
    dataset_dir: str,
    scene_ids: list[int],
    repeat: int,
    threads: int,
    config=None,
    model: str | None = None,
) -> dict:
    """Per-stage mean ms per frame and whole-frame median/p95 over the scenes' views, with the
    estimator's ``config`` (a TrackerConfig; default: its defaults) and the front end ``model``
    (an ONNX file; default: the shipped one)."""
    import zenoh

    from posefuse.estimator.frontend.network import NetworkFrontend, preprocess
    from posefuse.estimator.tracker import Frame, MultiViewEstimator
    from posefuse.evaluation.dataset import load_dataset
    from posefuse.service.codec import decoders, encode_estimate, encode_image
    from posefuse.service.resources import DEFAULT_MODEL

    ds = load_dataset(dataset_dir)
    network = NetworkFrontend(model or DEFAULT_MODEL, ds.catalog, threads=threads, spin=False)
    decode = decoders()["image"]
    estimator = MultiViewEstimator(ds.catalog, config)
    estimator.warm_up()  # as posefuse serve does before its first frame
    frames = []
    n_objects = []
    for sid in scene_ids:
        scene = ds.scene(sid)
        views = [scene.view(i) for i in scene.im_ids]
        n_objects += [len(v.gts) for v in views]
        frames.append(
            [(v, encode_image(v.im_id, "cam0", scene.load_rgb(v.im_id), "jpeg")) for v in views]
        )
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
    totals, per_stage, calls = [], defaultdict(list), defaultdict(int)
    accepted, refused = 0, Counter()
    with zenoh.open(conf) as session:
        network.detect(decode(frames[0][0][1]).image)  # warm-up
        for _ in range(repeat):
            for views in frames:
                estimator.reset()  # a new scene: no tracks, the warm caches kept
                for view, payload in views:
                    timer = StageTimer()
                    start = time.perf_counter()
                    with timer.stage("decode"):
                        image = decode(payload).image
                    with timer.stage("network"):
                        network.session.run(
                            None, {network.input_name: preprocess(image, network.card)}
                        )
                    # detect() runs the network again; its own share is taken off below
                    t0 = time.perf_counter()
                    detections = network.detect(image)
                    timer.seconds["voting"] += time.perf_counter() - t0 - timer.seconds["network"]
                    t_est = time.perf_counter()
                    with instrumented(timer):
                        updated = estimator.update(
                            Frame(view.im_id, view.camera, view.T_world_cam, image), detections
                        )
                    inner = sum(
                        timer.seconds[s]
                        for s in STAGES[3:15]  # association .. turn judge
                    )
                    timer.seconds["estimator (rest)"] += time.perf_counter() - t_est - inner
                    with timer.stage("encode"):
                        payloads = [(e.object_id, encode_estimate(e)) for e in updated]
                    with timer.stage("publish"):
                        for oid, data in payloads:
                            session.put(f"profile/@v1/objects/{oid}", data)
                    # the network ran twice above: the frame's time counts it once
                    totals.append(time.perf_counter() - start - timer.seconds["network"])
                    for s in STAGES:
                        per_stage[s].append(timer.seconds.get(s, 0.0))
                    for s, n in timer.calls.items():
                        calls[s] += n
                    accepted += timer.accepted
                    refused += timer.refused
    # the self-occlusion rays the tables cast over the whole run (viewpoints asked the first time)
    rays = sum(
        edges.occlusion.rays_cast
        for edges in estimator.poses.edges.values()
        if edges.occlusion is not None
    )
    return {
        "rays_cast": rays,
        "frames": len(totals),
        "objects_per_view": float(np.mean(n_objects)),
        "stages_ms": {s: 1000 * float(np.mean(v)) for s, v in per_stage.items()},
        "total_p50_ms": 1000 * float(np.median(totals)),
        "total_p95_ms": 1000 * float(np.percentile(totals, 95)),
        "calls": {s: calls[s] for s in COUNTED},
        "refinements_accepted": accepted,
        "refinements_refused": dict(refused),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", required=True, help="BOP dataset folder")
    parser.add_argument("--scene", type=int, action="append", required=True, help="scene id")
    parser.add_argument("--repeat", type=int, default=3, help="runs of each scene")
    parser.add_argument("--threads", type=int, default=2, help="onnxruntime threads")
    parser.add_argument(
        "--model",
        help="the front end's ONNX file (default: the shipped one), e.g. a part set's "
        "DIR/model/parts.onnx for a dataset of its parts",
    )
    parser.add_argument(
        "--verification",
        action="append",
        metavar="KEY=VALUE",
        help="a verification setting, as posefuse run-dataset takes it (repeat for several), "
        "e.g. keyframe_deg=0 to verify at every view",
    )
    parser.add_argument(
        "--numpy",
        action="store_true",
        help="the verification and refinement by the numpy code the compiled kernels replaced "
        "(estimator.verification.kernels), to compare",
    )
    args = parser.parse_args(argv)
    from dataclasses import replace

    from posefuse.cli.run import tracker_config, verification_settings

    config = tracker_config(verification=verification_settings(args.verification))
    if args.numpy:
        config = replace(
            config,
            verification=replace(config.verification, compiled=False),
            refinement=replace(config.refinement, compiled=False),
        )
    r = profile(args.dataset, args.scene, args.repeat, args.threads, config, args.model)
    print(
        f"{args.dataset} scenes {args.scene}: {r['frames']} frames, "
        f"{r['objects_per_view']:.1f} objects per view"
        + (", the step by numpy" if args.numpy else ", the step compiled")
    )
    print(f"{'stage':<20} {'ms/frame':>9}")
    for s in STAGES:
        print(f"{s:<20} {r['stages_ms'][s]:>9.1f}")
    step = sum(r["stages_ms"][s] for s in STEP)
    print(
        f"{'the step (deferred)':<20} {step:>9.1f}  (edge maps, settled checks, verification, "
        "refinement, turn judge, challenge: the daemon runs them between frames)"
    )
    print(f"{'frame p50':<20} {r['total_p50_ms']:>9.1f}")
    print(f"{'frame p95':<20} {r['total_p95_ms']:>9.1f}")
    n = r["calls"]
    # every refinement is counted accepted or refused; those not timed as the refinement stage
    # ran inside a challenge (its challenger's)
    refinements = r["refinements_accepted"] + sum(r["refinements_refused"].values())
    print(
        f"over {r['frames']} frames: {n['edge maps']} views kept (edge maps), "
        f"{n['settled checks']} settled checks, {n['verification']} verifications, "
        f"{refinements} refinements ({r['refinements_accepted']} accepted; "
        f"{refinements - n['refinement']} of them challengers'), "
        f"{n['turn judge']} turn judgements"
    )
    print(f"self-occlusion rays cast by the viewpoint tables: {r['rays_cast']}")
    refused = r["refinements_refused"]
    if refused:
        print("refused for: " + ", ".join(f"{k} {v}" for k, v in sorted(refused.items())))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
