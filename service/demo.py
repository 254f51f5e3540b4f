"""The demo recording: bin scenes of the procedural catalog as a cell would publish them, with
the ground truth stored beside, and the scoring of estimates against it.

A recording holds, per scene: the camera messages of :func:`clients.camera.scene_messages`, a
reset request on ``{cell}/@v1/estimator/reset`` before the scene (the scenes share the world
frame, so the estimator forgets the previous bin), and the scene's true object poses on
``{cell}/@v1/groundtruth/{scene_id}``.
"""

from __future__ import annotations

from pathlib import Path

import msgpack
import numpy as np

from clients.camera import scene_messages
from service.codec import encode_reset
from service.keys import Keys
from service.recording import Recorder

SCENE_GAP_NS = 10_000_000_000  # 10 s of stamp time between scenes


def groundtruth_key(cell: str, scene_id: int) -> str:
    return f"{Keys(cell).root}/groundtruth/{scene_id}"


def encode_groundtruth(scene_id: int, instances: list[tuple[int, np.ndarray]]) -> bytes:
    return msgpack.packb(
        {
            "v": 1,
            "scene_id": scene_id,
            "objects": [
                {"obj_id": int(o), "T_world_obj": [float(x) for x in T.reshape(-1)]}
                for o, T in instances
            ],
        },
        use_bin_type=True,
    )


def decode_groundtruth(payload: bytes) -> list[tuple[int, np.ndarray]]:
    msg = msgpack.unpackb(payload, raw=False)
    return [
        (int(o["obj_id"]), np.array(o["T_world_obj"], float).reshape(4, 4)) for o in msg["objects"]
    ]


def make_recording(
    dataset, scene_ids, out: str | Path, cell: str = "posefuse", rate_hz: float = 2.0, seed: int = 0
) -> Path:
    """Write the demo recording of ``scene_ids`` of a BOP dataset."""
    keys = Keys(cell)
    t0 = 1_000_000_000_000
    with Recorder(out, metadata={"cell": cell, "scenes": " ".join(map(str, scene_ids))}) as rec:
        for n, scene_id in enumerate(scene_ids):
            start = t0 + n * SCENE_GAP_NS
            rec.write(keys.reset, encode_reset(), start - 1)
            view = dataset.scene(scene_id).view(dataset.scene(scene_id).im_ids[0])
            truth = [(g.obj_id, view.T_world_cam @ g.T_cam_obj) for g in view.gts]
            rec.write(groundtruth_key(cell, scene_id), encode_groundtruth(scene_id, truth), start)
            for offset, key, payload in scene_messages(
                dataset, scene_id, cell, "cam0", rate_hz, t0_ns=start, seed=seed
            ):
                rec.write(key, payload, start + int(offset * 1e9))
    return Path(out)
