"""bench.daemon_accuracy's offline reference: the daemon's worker gives run-dataset's poses."""

import numpy as np

from posefuse.bench.daemon_accuracy import offline
from posefuse.estimator.frontend.network import NetworkFrontend
from posefuse.estimator.tracker import TrackerConfig
from posefuse.evaluation.dataset import load_dataset
from posefuse.evaluation.run_dataset import LabelledNetworkFrontend, run_dataset
from posefuse.service.resources import DEFAULT_MODEL


def _sorted_poses(results) -> np.ndarray:
    """(n, 13): obj_id then T_cam_obj's top three rows, sorted row by row."""
    rows = np.array([[r.obj_id, *r.T_cam_obj[:3].ravel()] for r in results])
    return rows[np.lexsort(rows.T[::-1])]


def test_the_daemons_worker_publishes_what_run_dataset_scores(full_res_dataset, robi_catalog):
    """The same four rendered views through the daemon's worker (deferred verification, every
    waiting check after each frame, stamps of 2026) and through ``run-dataset``'s loop (the
    network's detections, verification in the update): the same confirmed poses, to the
    wire's rounding. A seed that followed the stamp, or a check that ran differently, fails."""
    dataset = load_dataset(full_res_dataset)
    scene_id = dataset.scene_ids[0]
    n = len(dataset.scene(scene_id).im_ids)
    daemon = offline(dataset, (scene_id,), {(scene_id, 4): 1_780_000_000 * 10**9, (scene_id, 8): 0})
    frontend = NetworkFrontend(DEFAULT_MODEL, robi_catalog)
    network = LabelledNetworkFrontend(dataset, frontend)
    config = TrackerConfig().with_card(frontend.card.verification)  # as run-dataset's
    reference = run_dataset(
        dataset, network, config, checkpoints=(n,), show_progress=False, rotation=True
    ).results[n]
    assert n == 4 and len(reference) >= 4
    got, want = _sorted_poses(daemon[4]), _sorted_poses(reference)
    assert got.shape == want.shape
    np.testing.assert_allclose(got, want, atol=1e-9)
    # the "8 views" run holds the same four frames, stamped from 0: the same poses
    np.testing.assert_allclose(_sorted_poses(daemon[8]), got, atol=1e-12)
