"""The published estimate of a track: its pose, 6x6 covariance, rotation hypotheses and
confidence, as the service sends them (docs/protocol.md, ``ObjectEstimate``).

Before any rotation is measured a track publishes its translation with an unknown rotation
(the identity, with the variance of an angle uniform on [-pi, pi]). With a mixture, the
mixture's best component leads; after a verification the verified hypothesis leads, and with an
accepted refinement its full pose and covariance are published (``verified``, unless a deferred
verification waits for views fused since). A verified winner whose near-symmetric turns the
views cannot tell from it (:func:`~estimator.verification.verify.alternative_turns`) is
published as ambiguous: the turns beside it with their odds, and its rotation covariance widened
to cover each of them. A confirmed track whose verified pose fits its kept views worse than
``VerificationConfig.max_fit`` (``Track.fit``) is published as tentative: no pose of the part
fits what the views show there, so it is no part to reach for (a track founded between parts,
or holding two parts' centres). So is a confirmed track whose centre lies outside the bin the
parts lie in, where the cell knows it (``TrackerConfig.bin``), by more than its allowance: in
a pile, detections of different parts meet under the floor.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from posefuse.estimator.core.bin_region import BinRegion
from posefuse.estimator.core.geometry import so3_log
from posefuse.estimator.tracker.tracks import CONFIRMED, TENTATIVE, Track
from posefuse.estimator.verification.verify import VerificationConfig, alternative_turns

ROTATION_UNKNOWN_VAR = np.pi**2 / 3  # variance of a rotation angle uniform on [-pi, pi]


@dataclass(frozen=True, eq=False)
class RotationHypothesis:
    """One mode of an object's rotation: q [x, y, z, w] in the world frame, its weight, and the
    number of views that support it."""

    q: np.ndarray  # (4,)
    weight: float
    n: int


@dataclass(frozen=True, eq=False)
class AlternativeTurn:
    """A near-symmetric turn of the published rotation that the views cannot rule out: q
    [x, y, z, w] the alternative rotation in the world frame, odds in [0, 1] its likelihood
    against the published one (1: the views cannot tell them apart)."""

    q: np.ndarray  # (4,)
    odds: float


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
    # [0, 1]: the leading hypothesis's weight x its mean template similarity x the track's
    # support (support_factor); ranks estimates, not the chance a pose is right
    confidence: float
    hypotheses: tuple[RotationHypothesis, ...]
    n_views: int
    status: str
    frame_id: str = "world"
    # the pose is the one the track's kept views agree on (verified across them, and refined
    # when the refinement was accepted), for the views fused so far; False while a deferred
    # verification waits, and always without verification
    verified: bool = False
    # the near-symmetric turns of the rotation the views cannot rule out, most likely first
    # (odds >= VerificationConfig.ambiguous_odds), and the largest odds of any turn (0: none
    # asked, or every one ruled out plainly)
    alternatives: tuple[AlternativeTurn, ...] = ()
    ambiguity: float = 0.0

    @property
    def ambiguous(self) -> bool:
        """A near-symmetric turn of the rotation is as good as published, to the views."""
        return len(self.alternatives) > 0

    @property
    def t_world_obj(self) -> np.ndarray:
        return self.T_world_obj[:3, 3]


def published_estimate(
    track: Track,
    stamp_ns: int,
    class_name: str,
    verification: VerificationConfig | None = None,
    unasked: np.ndarray | None = None,
    bin_allowance: tuple[BinRegion, float] | None = None,
) -> ObjectEstimate:
    """What the track publishes at ``stamp_ns`` (see the module docstring); ``verification``
    gives the odds from which a turn is published as an alternative (default: the default
    config's). ``unasked`` (K, 3, 3) are object-frame turns of the part the verification does
    not ask the views about (``PoseStage.unasked``: a gear's teeth): where the track's turn
    judgement (``Track.turns``, :mod:`estimator.verification.turns`) says which of them the
    views show, the pose is turned to it and the others are published with their odds; without
    one, each is published with odds 1, since nothing rules it out. ``bin_allowance``: the bin
    the parts lie in, where the cell knows it, and how far (metres) a centre may lie outside it
    (``TrackerConfig.bin``, ``bin_margin_frac`` of the part's diameter); a confirmed track
    whose published centre lies farther out is published tentative, as no part is there."""
    verification = verification or VerificationConfig()
    T = np.eye(4)
    T[:3, 3] = track.estimate.t_world_obj
    cov = np.zeros((6, 6))
    cov[:3, :3] = track.estimate.cov
    cov[3:, 3:] = np.eye(3) * ROTATION_UNKNOWN_VAR
    confidence = 0.0
    hypotheses: tuple[RotationHypothesis, ...] = ()
    best = track.mixture.best() if track.mixture is not None else None
    verified = False
    alternatives: tuple[AlternativeTurn, ...] = ()
    ambiguity = 0.0
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
            turns, odds = alternative_turns(verdict, verification.temperature)
            judged = track.turns
            if judged is not None:
                # the turn the views show leads; the verification's turns are of the pose
                # before it, so they are taken to the judged pose
                T[:3, :3] = R_components[lead] = T[:3, :3] @ judged.turn
                turns = np.einsum("ji,ajk->aik", judged.turn, turns)
                turns = np.concatenate([turns, judged.alternatives])
                odds = np.concatenate([odds, judged.odds])
            elif unasked is not None and len(unasked):
                turns = np.concatenate([turns, unasked])
                odds = np.concatenate([odds, np.ones(len(unasked))])
            ambiguity = float(odds.max()) if len(odds) else 0.0
            alternatives, cov[3:, 3:] = _alternatives(
                T[:3, :3], turns, odds, verification.ambiguous_odds, cov[3:, 3:]
            )
        quats = Rotation.from_matrix(R_components).as_quat()
        hypotheses = tuple(
            RotationHypothesis(q, float(w), c.n)
            for c, w, q in zip(components, weights, quats, strict=True)
        )
        mean_similarity = best.confidence / best.n
        confidence = float(
            weights[components.index(best)] * mean_similarity * support_factor(track)
        )
    status = track.status
    if (
        status == CONFIRMED
        and verification.max_fit is not None
        and track.fit is not None
        and track.fit > verification.max_fit
    ):
        # no pose of the part fits what its views show there: not a part to reach for
        status = TENTATIVE
    if status == CONFIRMED and bin_allowance is not None:
        region, margin = bin_allowance
        if float(region.distance_outside(T[:3, 3])) > margin:
            # under the bin's floor (detections of different parts that meet there) or beyond
            # a wall: no part lies there
            status = TENTATIVE
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
        status=status,
        verified=verified,
        alternatives=alternatives,
        ambiguity=ambiguity,
    )


# the power of the track's support in its confidence, chosen on the tuning sets (4242, 4343,
# 4444, 4445; docs/lab/2026-12-05-confidence-with-support.md): 1 and 2 ranked the estimates of
# piles less well, and every power left mixed bins as they were
SUPPORT_POWER = 0.5


def support_factor(track: Track) -> float:
    """The share of the views that predicted the track in view that detected it, to the power
    SUPPORT_POWER: a track of no part, founded on stray detections between parts, is
    predicted in view again and again and seldom seen; a part is seen where it shows."""
    seen, missed = max(track.views_seen, 0), max(track.missed_views, 0)
    if seen + missed == 0:
        return 1.0
    return (seen / (seen + missed)) ** SUPPORT_POWER


def _alternatives(
    R_world_obj: np.ndarray,
    turns: np.ndarray,
    odds: np.ndarray,
    min_odds: float,
    cov_rot: np.ndarray,
) -> tuple[tuple[AlternativeTurn, ...], np.ndarray]:
    """The turns (A, 3, 3) with odds (A,) of at least ``min_odds``, most likely first, as
    published alternatives of R_world_obj (3, 3), and the rotation covariance (3, 3) widened to
    cover each: ``phi phi^T / 4`` added for the world-frame rotation vector ``phi`` that takes
    the pose to the alternative, which puts it two standard deviations away along ``phi``."""
    keep = [int(a) for a in np.argsort(-odds, kind="stable") if odds[a] >= min_odds]
    if not keep:
        return (), cov_rot
    cov_rot = cov_rot.copy()
    out = []
    for a in keep:
        R_alt = R_world_obj @ turns[a]
        phi = so3_log(R_alt @ R_world_obj.T)  # left perturbation, world frame
        cov_rot += np.outer(phi, phi) / 4.0
        out.append(AlternativeTurn(Rotation.from_matrix(R_alt).as_quat(), float(odds[a])))
    return tuple(out), cov_rot
