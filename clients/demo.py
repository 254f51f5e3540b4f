"""Writing the demo recording: bin scenes of a BOP dataset as a cell's camera publishes them
(:func:`clients.camera.scene_messages`), with the ground truth stored beside; the format is
described in :mod:`service.demo`, which replays and scores it."""

from __future__ import annotations

from pathlib import Path

from posefuse.clients.camera import scene_messages
from posefuse.service.codec import encode_groundtruth, encode_reset
from posefuse.service.demo import groundtruth_key
from posefuse.service.foxglove import FoxgloveMirror
from posefuse.service.keys import Keys
from posefuse.service.recording import Recorder

SCENE_GAP_NS = 10_000_000_000  # 10 s of stamp time between scenes


def make_recording(
    dataset,
    scene_ids,
    out: str | Path,
    cell: str = "posefuse",
    rate_hz: float = 2.0,
    seed: int = 0,
    catalog=None,
) -> Path:
    """Write the demo recording of ``scene_ids`` of a BOP dataset, with Foxglove channels (the
    meshes of ``catalog`` show the ground truth)."""
    keys = Keys(cell)
    t0 = 1_000_000_000_000
    metadata = {"cell": cell, "scenes": " ".join(map(str, scene_ids))}
    mirror = FoxgloveMirror(cell, catalog)
    with Recorder(out, metadata=metadata, mirror=mirror) as rec:
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
