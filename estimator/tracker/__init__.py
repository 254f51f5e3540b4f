"""The frame's walk through the method: :class:`MultiViewEstimator` takes one view's
detections, associates them and fuses the translations (``estimator.translation``), measures
and fuses the rotations (``estimator.rotation``), verifies and refines
(``estimator.verification``) and publishes the estimates.

- ``estimator.py``: the update, step by step, and the estimator's public API;
- ``tracks.py``: what a track holds, and its bookkeeping (found, grow, split, merge, drop);
- ``pose_stage.py``: rotation measurement, verification and refinement of a track;
- ``published.py``: the estimate a track publishes;
- ``snapshot.py``: the tracks as data, and back;
- ``config.py``: the settings of every step.
"""

from posefuse.estimator.tracker.config import TrackerConfig
from posefuse.estimator.tracker.estimator import (
    Frame,
    MultiViewEstimator,
    UpdateReport,
    ViewDetections,
    predicted_center,
    validate_pose,
)
from posefuse.estimator.tracker.pose_stage import PoseStage
from posefuse.estimator.tracker.published import (
    ROTATION_UNKNOWN_VAR,
    AlternativeTurn,
    ObjectEstimate,
    RotationHypothesis,
    published_estimate,
)
from posefuse.estimator.tracker.tracks import (
    CONFIRMED,
    TENTATIVE,
    DetectionRef,
    PendingView,
    Track,
    TrackBook,
    ViewRef,
)

__all__ = [
    "CONFIRMED",
    "ROTATION_UNKNOWN_VAR",
    "TENTATIVE",
    "DetectionRef",
    "Frame",
    "MultiViewEstimator",
    "AlternativeTurn",
    "ObjectEstimate",
    "PendingView",
    "PoseStage",
    "RotationHypothesis",
    "Track",
    "TrackBook",
    "TrackerConfig",
    "UpdateReport",
    "ViewDetections",
    "ViewRef",
    "predicted_center",
    "published_estimate",
    "validate_pose",
]
