"""The published estimate of a track: its pose, 6x6 covariance, rotation hypotheses and
confidence, as the service sends them (docs/protocol.md, ``ObjectEstimate``).

Before any rotation is measured a track publishes its translation with an unknown rotation
(the identity, with the variance of an angle uniform on [-pi, pi]). With a mixture, the
mixture's best component leads; after a verification the verified hypothesis leads, and with an
accepted refinement its full pose and covariance are published (``verified``, unless a deferred
verification waits for views fused since).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from posefuse.estimator.tracker.tracks import Track

ROTATION_UNKNOWN_VAR = np.pi**2 / 3  # variance of a rotation angle uniform on [-pi, pi]


@dataclass(frozen=True, eq=False)
class RotationHypothesis:
    """One mode of an object's rotation: q [x, y, z, w] in the world frame, its weight, and the
    number of views that support it."""

    q: np.ndarray  # (4,)
    weight: float
    n: int


@dataclass(frozen=True, eq=False)
class ObjectEstimate:
    """The state of one object track, as published (docs/protocol.md).

    T_world_obj: (4, 4) metres; cov: (6, 6) in the order x, y, z, rot_x, rot_y, rot_z (metres,
    radians; rotation as a left perturbation in the world frame).
    """

    stamp_ns: int
    object_id: str
    class_id: int
    class_name: str
    T_world_obj: np.ndarray
    cov: np.ndarray
    confidence: float
    hypotheses: tuple[RotationHypothesis, ...]
    n_views: int
    status: str
    frame_id: str = "world"
    # the pose is the one the track's kept views agree on (verified across them, and refined
    # when the refinement was accepted), for the views fused so far; False while a deferred
    # verification waits, and always without verification
    verified: bool = False

    @property
    def t_world_obj(self) -> np.ndarray:
        return self.T_world_obj[:3, 3]


def published_estimate(track: Track, stamp_ns: int, class_name: str) -> ObjectEstimate:
    """What the track publishes at ``stamp_ns`` (see the module docstring)."""
    T = np.eye(4)
    T[:3, 3] = track.estimate.t_world_obj
    cov = np.zeros((6, 6))
    cov[:3, :3] = track.estimate.cov
    cov[3:, 3:] = np.eye(3) * ROTATION_UNKNOWN_VAR
    confidence = 0.0
    hypotheses: tuple[RotationHypothesis, ...] = ()
    best = track.mixture.best() if track.mixture is not None else None
    verified = False
    if best is not None:
        T[:3, :3] = best.R_world_obj
        cov[3:, 3:] = best.cov
        weights = track.mixture.weights
        components = track.mixture.components
        R_components = np.array([c.R_world_obj for c in components])
        verdict = track.verdict
        if verdict is not None and len(verdict.weights) == len(components):
            # the verified hypothesis leads, with the refined pose when it was accepted
            lead = int(verdict.component[verdict.best])
            best = components[lead]
            weights = verdict.weights
            R_components[lead] = verdict.R_world_obj[verdict.best]
            T[:3, :3] = R_components[lead]
            cov[3:, 3:] = best.cov
            verified = track.check_since is None
            refined = track.refined
            if refined is not None and refined.accepted:
                T[:3, :3] = R_components[lead] = refined.R_world_obj
                T[:3, 3] = refined.t_world_obj
                cov = refined.cov.copy()
        quats = Rotation.from_matrix(R_components).as_quat()
        hypotheses = tuple(
            RotationHypothesis(q, float(w), c.n)
            for c, w, q in zip(components, weights, quats, strict=True)
        )
        mean_similarity = best.confidence / best.n
        confidence = float(weights[components.index(best)] * mean_similarity)
    return ObjectEstimate(
        stamp_ns=stamp_ns,
        object_id=track.object_id,
        class_id=track.obj_id,
        class_name=class_name,
        T_world_obj=T,
        cov=cov,
        confidence=confidence,
        hypotheses=hypotheses,
        n_views=track.views_seen,
        status=track.status,
        verified=verified,
    )
