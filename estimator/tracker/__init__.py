"""The frame's walk through the method: :class:`MultiViewEstimator` takes one view's
detections, associates and fuses the translations (``estimator.translation``), measures and
fuses the rotations (``estimator.rotation``), verifies and refines (``estimator.verification``)
and publishes the estimates."""

from posefuse.estimator.tracker.estimator import (  # noqa: F401
    CONFIRMED,
    ROTATION_UNKNOWN_VAR,
    TENTATIVE,
    Frame,
    MultiViewEstimator,
    ObjectEstimate,
    RotationHypothesis,
    Track,
    TrackerConfig,
    UpdateReport,
    predicted_center,
    validate_pose,
)
