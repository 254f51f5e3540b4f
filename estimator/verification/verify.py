"""Verification of a track's rotation hypotheses against every view it has.

Each view's LINE-2D match (:mod:`estimator.rotation.matching`) is judged alone. A chrome screw seen
end-on looks the same head first or tip first, and the max-mixture then holds both, often with
the wrong one ahead. Other views see the difference plainly. Verification asks them all.

The hypotheses are the mixture's leading components and their *near-symmetric variants*: the
turns that map the part almost, but not quite, onto itself (:func:`near_symmetries`: half turns
about the object's axes, and the smallest turn about an axis that nearly repeats the part, like a
gear's tooth), whether or not the catalog calls them symmetries. Every hypothesis, at the
track's translation, is scored in every kept view (:func:`score_hypotheses`) by the directional
chamfer of its projected edges (:mod:`estimator.verification.model_edges`) against the view's
image edges, plus the chamfer of its occluding contour against the boundary of the front end's
mask (:mod:`estimator.verification.edge_maps`). The lowest total cost leads. The costs also
re-weight the components: a component's weight is multiplied by ``exp(-V (cost - best) /
temperature)`` over its V views, so a view that is plainly wrong costs a mode its lead, and
weights stay a distribution.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from posefuse.estimator.core.geometry import rotation_angle, so3_exp
from posefuse.estimator.rotation.mixture import closest_equivalents
from posefuse.estimator.verification import kernels
from posefuse.estimator.verification.edge_maps import EdgeConfig, EdgeView, sample_maps
from posefuse.estimator.verification.lead import lead_hypothesis, reweight
from posefuse.estimator.verification.model_edges import (
    ModelEdges,
    pose_edges,
    project_shown,
    silhouette_misses,
)
from posefuse.estimator.verification.turns import TurnJudgeConfig, surface_moves

__all__ = [
    "ScoreCache",
    "VerificationConfig",
    "alternative_turns",
    "agrees",
    "Verdict",
    "cached_scores",
    "hypotheses",
    "is_new_viewpoint",
    "lead_hypothesis",
    "near_symmetries",
    "near_symmetry_turns",
    "refinement_reach_deg",
    "reweight",
    "score_hypotheses",
    "verify",
]


@dataclass(frozen=True)
class VerificationConfig:
    enabled: bool = True
    edges: EdgeConfig = EdgeConfig()
    max_views: int = 6  # views kept per track (the most recent), memory ~150 kB each
    # a view is kept, and the track verified again, only when it sees the part from a new
    # viewpoint: its direction from the part at least this far from every kept view's, or its
    # distance this much nearer or farther (a camera at rest adds nothing the kept views lack)
    keyframe_deg: float = 5.0
    keyframe_distance_frac: float = 0.15
    max_components: int = 5  # the leading components are verified, with their variants
    crease_weight: float = 0.5  # weight of the creases' chamfer against the contour's
    mask_weight: float = 1.5  # weight of the mask-boundary chamfer against the contour's
    # weight of the share of the mask's points that the hypothesis' silhouette leaves uncovered
    # (the part shows there, so its silhouette must cover it; where the silhouette spills over
    # the mask, another part may hide it, and nothing is said); 0: not scored
    coverage_weight: float = 1.0  # chosen on the tuning sets (docs/verification.md)
    # a view that shows less edge than min_points samples at the finest spacing (d / 80: 0.15 d
    # of edge) says nothing (cost 1); ModelEdges.samples_for turns it into the model's samples
    min_points: int = 12
    temperature: float = 0.05  # of the re-weighting, in units of mean truncated cost
    near_frac: float = 0.06  # a turn is near-symmetric when the surface moves this little (d)
    max_variants: int = 4
    # a settled track is neither verified nor refined again for a new view that agrees with
    # its refined pose: in the view the pose costs at most this much more than the best of the
    # hypotheses a verification would ask about, and the translation has moved less than
    # settled_translation_frac of the diameter since the refinement took it as its prior
    # (None: verified and refined at every new view; see the tracker's _settled)
    settled_margin: float | None = 0.05  # chosen on the tuning sets (docs/verification.md)
    settled_translation_frac: float = 0.05
    # a verification without new views whose winner holds the last refinement in its basin
    # keeps that refinement instead of refining again (the tracker's _verify)
    reuse_refinement: bool = True
    # every n-th edge sample is scored (ModelEdges.subset); a view too short of edge to say
    # anything is judged by its length of edge (min_points), whatever the sampling
    sample_stride: int = 1
    # the winner is published as ambiguous when one of its near-symmetric turns is this likely
    # against it, exp(-V (cost - best) / temperature) (:func:`alternative_turns`); the turn is
    # then published beside it and the rotation covariance widened to cover it. Chosen on the
    # tuning sets (procedural mixed 4242 and robi 4343 with the network, the five meshes of
    # ../shared/objects rendered with seed 6161 with the oracle; docs/verification.md)
    ambiguous_odds: float = 0.05
    # a winner whose refined pose still costs more than this (a biased centre can make the
    # wrong basin score best at the track's translation) is challenged: the best hypothesis of
    # another basin is refined too, and leads where its refined pose costs less by at least
    # the temperature (None: never challenged). Chosen on the tuning sets
    # (docs/lab/2026-12-05-verification-challenge-and-cost-drop.md)
    challenge_cost: float | None = 0.6
    # a confirmed track whose verified pose still costs more than this in its kept views (the
    # cost challenge_cost reads) is published as tentative: no pose of the part fits what the
    # views show there (a track founded between parts, or holding two parts' centres). None:
    # every confirmed track is published as confirmed. Chosen on the tuning sets
    # (docs/lab/2026-12-06-verification-poor-fit-tentative.md)
    max_fit: float | None = 1.4
    # a hypothesis more than flip_deg from the mixture's favourite leads only over at least
    # flip_min_views views that agree on it by flip_z standard errors; else the favourite leads
    # and the flip is published beside it (estimator.verification.lead; None: the lowest mean
    # cost leads). Chosen on the tuning sets
    # (docs/lab/2026-12-06-verification-flips-need-agreeing-views.md)
    flip_z: float | None = 1.0
    flip_min_views: int = 3
    flip_deg: float = 90.0
    # the chamfer sums by the compiled kernel (estimator.verification.kernels), or by the numpy
    # code it replaced (the reference, equal to rounding)
    compiled: bool = True
    # the turns of a part's near-symmetric groups that it does not ask about (a gear's teeth)
    # are judged after the refinement by the edges that tell them apart
    # (estimator.verification.turns); off, they are all published as open
    turns: TurnJudgeConfig = TurnJudgeConfig()

    def __post_init__(self) -> None:
        if (
            self.sample_stride < 1
            or self.max_views < 1
            or (self.challenge_cost is not None and self.challenge_cost < 0)
            or (self.max_fit is not None and not self.max_fit > 0)
            or (self.flip_z is not None and not self.flip_z >= 0)
            or self.flip_min_views < 2
            or not 0 < self.flip_deg <= 180
        ):
            raise ValueError(f"invalid verification config: {self}")


@dataclass(eq=False)
class ScoreCache:
    """Per kept view (by stamp): the translation, the hypotheses (K, 3, 3) and their costs (K,)
    of the last verification. A view's cost of a hypothesis is reused while the hypothesis is
    within ``rotation_tol_deg`` of a scored one and the translation within ``translation_frac``
    of the diameter: a new view then costs one view's scoring, not all of them again."""

    entries: dict = field(default_factory=dict)
    rotation_tol_deg: float = 1.0
    translation_frac: float = 0.01


def cached_scores(
    edges: ModelEdges,
    views: list[EdgeView],
    R_world_obj: np.ndarray,
    t_world_obj: np.ndarray,
    config: VerificationConfig,
    cache: ScoreCache,
) -> np.ndarray:
    """(H, V) :func:`score_hypotheses`, reusing ``cache`` where it holds (see ScoreCache); the
    cache is updated and keeps only the views given."""
    H, V = len(R_world_obj), len(views)
    out = np.empty((H, V))
    todo = np.ones((H, V), bool)
    tol = np.deg2rad(cache.rotation_tol_deg)
    for v, view in enumerate(views):
        entry = cache.entries.get(view.stamp_ns)
        if entry is not None and np.linalg.norm(entry[0] - t_world_obj) <= (
            cache.translation_frac * edges.diameter
        ):
            angle = rotation_angle(
                np.einsum("hij,klj->hkil", R_world_obj, entry[1])
            )  # (H, K): R_h R_k^T
            k = np.argmin(angle, axis=1)
            hit = angle[np.arange(H), k] < tol
            out[hit, v] = entry[2][k[hit]]
            todo[:, v] = ~hit
    # what is left, scored in one batch: the hypotheses any view needs, in the views that need
    # any (a hypothesis' cost in a view depends on nothing else, so the superset is exact)
    rows, cols = np.flatnonzero(todo.any(axis=1)), np.flatnonzero(todo.any(axis=0))
    if len(rows):
        scored = score_hypotheses(
            edges, [views[v] for v in cols], R_world_obj[rows], t_world_obj, config
        )
        r, c = np.nonzero(todo[np.ix_(rows, cols)])
        out[rows[r], cols[c]] = scored[r, c]
    for v, view in enumerate(views):
        if view.stamp_ns not in cache.entries or todo[:, v].any():
            cache.entries[view.stamp_ns] = (
                np.array(t_world_obj, float),
                R_world_obj.copy(),
                out[:, v].copy(),
            )
    kept = {view.stamp_ns for view in views}
    for stamp in [s for s in cache.entries if s not in kept]:
        del cache.entries[stamp]
    return out


@dataclass(frozen=True, eq=False)
class Verdict:
    """The outcome of one verification.

    R_world_obj: (H, 3, 3) the hypotheses; component: (H,) the mixture component of each;
    variant: (H,) index into the variants (0: the component itself); cost: (H,) mean over views
    of the truncated chamfer cost (:func:`score_hypotheses`); per_view: (H, V); weights: (C,) the
    components' weights after re-weighting; best: index of the leading hypothesis; overruled:
    the flip with a lower mean cost that the views did not agree on (:func:`lead_hypothesis`),
    -1 when the lowest mean cost leads.
    """

    R_world_obj: np.ndarray
    component: np.ndarray
    variant: np.ndarray
    cost: np.ndarray
    per_view: np.ndarray
    weights: np.ndarray
    best: int
    overruled: int = -1


def alternative_turns(
    verdict: Verdict, temperature: float, near_deg: float = 10.0
) -> tuple[np.ndarray, np.ndarray]:
    """The winner's near-symmetric turns, and how likely the views find each against it.

    The winner's alternatives are the hypotheses of its own component turned by the other
    variants (:func:`hypotheses`), and the flip the views could not agree on when the winner
    was kept against it (``verdict.overruled``). An alternative's cost is the lowest of the
    hypotheses within ``near_deg`` of it (another component may lie there too), and its odds
    against the winner are ``exp(-V (cost - best) / temperature)`` over the V views, the
    re-weighting's own factor: 1 when the views cannot tell the two apart, near 0 when they
    plainly can.

    Returns:
        turns: (A, 3, 3) object-frame rotations, the alternative being ``R_winner @ turn``;
        odds: (A,) in [0, 1].
    """
    b = verdict.best
    others = np.flatnonzero(verdict.component == verdict.component[b])
    if verdict.overruled >= 0 and verdict.overruled not in others:
        others = np.append(others, verdict.overruled)
    others = others[others != b]
    if len(others) == 0:
        return np.zeros((0, 3, 3)), np.zeros(0)
    R_b = verdict.R_world_obj[b]
    alternatives = verdict.R_world_obj[others]  # (A, 3, 3)
    # the angle between every alternative and every hypothesis, (A, H)
    relative = np.einsum("aji,hjk->ahik", alternatives, verdict.R_world_obj)
    angle = rotation_angle(relative.reshape(-1, 3, 3)).reshape(len(others), -1)
    near = angle <= np.deg2rad(near_deg)
    cost = np.where(near, verdict.cost[None], np.inf).min(axis=1)
    gap = np.maximum(cost - verdict.cost[b], 0.0)
    odds = np.exp(-verdict.per_view.shape[1] * gap / temperature)
    return np.einsum("ji,ajk->aik", R_b, alternatives), odds


def is_new_viewpoint(
    kept_T_cam_world: np.ndarray,
    T_cam_world: np.ndarray,
    t_world_obj: np.ndarray,
    min_angle_deg: float,
    min_distance_frac: float,
) -> bool:
    """Whether a view sees the part from a viewpoint none of the kept views has.

    Args:
        kept_T_cam_world: (V, 4, 4) the kept views' camera poses (V may be 0).
        T_cam_world: (4, 4) the new view's.
        t_world_obj: (3,) the part's position.
        min_angle_deg: the least angle, at the part, between the new camera's direction and a
            kept one's for the new view to differ from it.
        min_distance_frac: or the least relative change of the camera's distance.
    Returns:
        True when no kept view lies within both bounds of the new one.
    """
    kept = np.asarray(kept_T_cam_world, float).reshape(-1, 4, 4)
    if not len(kept):
        return True

    def offsets(T):  # (..., 3) camera centres minus the part's position, world frame
        R, t = T[..., :3, :3], T[..., :3, 3]
        return -np.einsum("...ji,...j->...i", R, t) - t_world_obj

    d_new, d_kept = offsets(np.asarray(T_cam_world, float)), offsets(kept)
    r_new, r_kept = np.linalg.norm(d_new), np.linalg.norm(d_kept, axis=1)
    cos = (d_kept @ d_new) / np.maximum(r_kept * r_new, 1e-12)
    near_direction = cos > np.cos(np.deg2rad(min_angle_deg))
    near_distance = np.abs(np.log(r_new / np.maximum(r_kept, 1e-12))) < np.log1p(min_distance_frac)
    return not bool(np.any(near_direction & near_distance))


def near_symmetries(
    points: np.ndarray,
    diameter: float,
    symmetries: np.ndarray,
    continuous_axes: np.ndarray,
    near_frac: float = 0.06,
    max_variants: int = 4,
) -> np.ndarray:
    """Object-frame turns under which the part looks almost, not exactly, the same.

    Candidates: the half turns about the object's x, y and z axes, and about each axis the
    smallest turn ``2 pi / n`` (n = 3..12, so at least 30 degrees: smaller turns are within the
    mixture's gate and the refinement's reach) that moves the surface samples by at most
    ``near_frac`` of the diameter (95th percentile of the distance to the nearest sample). Half
    turns are kept whatever they score: flipping a part end over end is the confusion LINE-2D
    makes. A candidate equivalent (within 2 degrees) to a symmetry, to the identity, or to an
    earlier candidate is dropped.

    Args:
        points: (N, 3) surface samples, object frame. symmetries: (S, 3, 3) object-frame
        symmetry rotations with the identity first. continuous_axes: (A, 3) unit axes.
    Returns:
        (M, 3, 3) rotations, M <= max_variants, the identity excluded.
    """
    cands: list[tuple[float, np.ndarray]] = []
    for axis in np.eye(3):
        cands.append((-1.0, so3_exp(np.pi * axis)))  # half turns first, whatever they score
        turns = np.stack([so3_exp(2 * np.pi / n * axis) for n in range(3, 13)])
        moves = surface_moves(points, diameter, turns)
        near = np.flatnonzero(moves <= near_frac)
        if len(near):  # the first n that nearly repeats the part
            cands.append((float(moves[near[0]]), turns[near[0]]))
    cands.sort(key=lambda c: c[0])
    kept: list[np.ndarray] = []
    for _, R in cands:
        known = [np.eye(3)] + kept
        for ref in known:
            # R is redundant if R = ref @ S for a symmetry S, i.e. R's equivalent near ref
            _, angle = closest_equivalents(R[None], ref, symmetries, continuous_axes)
            if angle[0] < np.deg2rad(2.0):
                break
        else:
            kept.append(R)
        if len(kept) >= max_variants:
            break
    return np.array(kept).reshape(-1, 3, 3)


def near_symmetry_turns(
    axes: np.ndarray,
    orders: np.ndarray,
    symmetries: np.ndarray,
    continuous_axes: np.ndarray,
    known: np.ndarray | None = None,
    max_turns: int = 32,
) -> np.ndarray:
    """The turns of a part's near-symmetric groups (``ObjectModel.near_symmetries``, what its
    symmetry detection almost found): every ``2 pi k / n`` about each axis, up to the part's
    symmetries, without the identity and the ``known`` turns (M, 3, 3) (within 2 degrees).

    A gear of 28 teeth whose hub is only 2-fold has 13 such turns about its axis, the tooth
    counts a view may confuse; :func:`near_symmetries` (30 degrees and more) asks about none of
    them, and the views' costs between whole teeth differ by noise, not evidence
    (docs/lab/2026-12-05-real-meshes-decimation-and-ambiguity.md).

    Args:
        axes: (G, 3) unit axes, object frame; orders: (G,) n of each group.
        symmetries: (S, 3, 3) symmetry rotations with the identity first; continuous_axes:
        (A, 3).
    Returns:
        (K, 3, 3), K <= max_turns, smallest turns first.
    """
    candidates = []
    for axis, n in zip(
        np.asarray(axes, float).reshape(-1, 3), np.asarray(orders, int), strict=True
    ):
        for k in range(1, int(n)):
            angle = 2 * np.pi * k / n
            candidates.append((min(angle, 2 * np.pi - angle), so3_exp(angle * axis)))
    candidates.sort(key=lambda c: c[0])
    refs = [np.eye(3), *np.asarray(known if known is not None else [], float).reshape(-1, 3, 3)]
    kept: list[np.ndarray] = []
    for _, R in candidates:
        if any(
            closest_equivalents(R[None], ref, symmetries, continuous_axes)[1][0] < np.deg2rad(2.0)
            for ref in refs + kept
        ):
            continue
        kept.append(R)
        if len(kept) >= max_turns:
            break
    return np.array(kept).reshape(-1, 3, 3)


def refinement_reach_deg(
    variants: np.ndarray, symmetries: np.ndarray, continuous_axes: np.ndarray
) -> float:
    """How far a refinement may turn from its start and stay in its basin, degrees: half the
    smallest near-symmetric turn of the part (each taken to its symmetric equivalent nearest the
    identity), so that it never reaches halfway to a variant the verification tells apart; 90
    (half of a flip) where the part has none.

    Args:
        variants: (M, 3, 3) :func:`near_symmetries`; symmetries: (S, 3, 3) object-frame symmetry
        rotations with the identity first; continuous_axes: (A, 3) unit axes.
    """
    if len(variants) == 0:
        return 90.0
    turns = np.asarray(variants, float)
    _, angle = closest_equivalents(turns, np.eye(3), symmetries, continuous_axes)
    return float(min(90.0, 0.5 * np.rad2deg(angle.min())))


def score_hypotheses(
    edges: ModelEdges,
    views: list[EdgeView],
    R_world_obj: np.ndarray,
    t_world_obj: np.ndarray,
    config: VerificationConfig,
) -> np.ndarray:
    """(H, V) cost of each hypothesis in each view: the mean truncated directional chamfer of
    its occluding contour (in [0, 1]), plus ``crease_weight`` times that of its visible creases,
    plus ``mask_weight`` times the mean truncated distance of its contour to the mask's boundary
    (when the view has a mask). A term that shows less edge than ``min_points`` samples at the
    finest spacing (:meth:`ModelEdges.samples_for`) costs 1.

    Args:
        R_world_obj: (H, 3, 3). t_world_obj: (3,) or (H, 3) metres.
    """
    H, V = len(R_world_obj), len(views)
    if V == 0:
        return np.zeros((H, 0))
    edges = edges.subset(config.sample_stride)
    t_world_obj = np.broadcast_to(t_world_obj, (H, 3))
    R_cw = np.array([v.T_cam_world[:3, :3] for v in views])  # (V, 3, 3)
    t_cw = np.array([v.T_cam_world[:3, 3] for v in views])  # (V, 3)
    R_cam = np.einsum("vij,hjk->hvik", R_cw, R_world_obj).reshape(-1, 3, 3)
    t_cam = (np.einsum("vij,hj->hvi", R_cw, t_world_obj) + t_cw).reshape(-1, 3)
    K = np.broadcast_to(np.array([v.K_roi for v in views]), (H, V, 3, 3)).reshape(-1, 3, 3)
    _, _, active, contour = pose_edges(edges, R_cam, t_cam, config.compiled)
    ec = config.edges
    view_of = np.tile(np.arange(V), H)  # pose n = h * V + v
    with_mask = np.array([v.mask_dt is not None for v in views])
    use_mask = bool(with_mask.any()) and config.mask_weight > 0
    enough = edges.samples_for(config.min_points) - 1e-9
    dcdt = np.concatenate([v.dcdt for v in views])  # (V * bins, L, L)
    masks = np.stack([v.mask_dt if v.mask_dt is not None else v.dcdt[0] for v in views])
    if config.compiled:
        f64, flag = kernels.as_f64, kernels.as_bool  # one layout: one compiled signature
        sums, counts = kernels.chamfer_costs(
            f64(edges.points),
            f64(edges.directions),
            flag(active),
            flag(contour),
            f64(R_cam),
            f64(t_cam),
            f64(K),
            np.ascontiguousarray(view_of, np.int64),
            np.ascontiguousarray(dcdt, np.uint8),
            np.ascontiguousarray(masks, np.uint8),
            flag(with_mask & use_mask),
            ec.bins,
            float(ec.truncate_px),
        )
    else:
        sums, counts = _chamfer_sums_numpy(
            edges, active, contour, R_cam, t_cam, K, view_of, dcdt, masks, with_mask & use_mask, ec
        )

    def mean_or_one(total: np.ndarray, n: np.ndarray) -> np.ndarray:
        """(N,) per pose: the mean distance over its n samples, truncated to [0, 1]; 1 (no
        information) with fewer than ``min_points`` of them at the finest spacing."""
        return np.where(n >= enough, total / np.maximum(n, 1) / ec.truncate_px, 1.0)

    cost = mean_or_one(sums[:, 0], counts[:, 0]) + config.crease_weight * mean_or_one(
        sums[:, 1], counts[:, 1]
    )
    if use_mask:
        cost += config.mask_weight * with_mask[view_of] * mean_or_one(sums[:, 2], counts[:, 0])
    if config.coverage_weight > 0 and edges.mesh is not None:
        points = [v.mask_points if v.mask_points is not None else np.zeros((0, 2)) for v in views]
        cost += config.coverage_weight * silhouette_misses(edges.mesh, R_cam, t_cam, K, points * H)
    return cost.reshape(H, V)


def _chamfer_sums_numpy(
    edges: ModelEdges,
    active: np.ndarray,
    contour: np.ndarray,
    R_cam: np.ndarray,
    t_cam: np.ndarray,
    K: np.ndarray,
    view_of: np.ndarray,
    dcdt: np.ndarray,
    masks: np.ndarray,
    has_mask: np.ndarray,
    ec: EdgeConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`estimator.verification.kernels.chamfer_costs` by numpy, its reference (the same
    arguments and results): only the samples that show are projected and read."""
    N = len(R_cam)
    pose, sample, uv, angle = project_shown(edges, active, R_cam, t_cam, K)
    on_contour = contour[pose, sample]
    view = view_of[pose]
    b = np.floor(angle / (np.pi / ec.bins) + 0.5).astype(np.intp) % ec.bins
    d, _ = sample_maps(dcdt, view * ec.bins + b, uv, ec.truncate_px, False)
    sums, counts = np.zeros((N, 3)), np.zeros((N, 2))
    for k, use in enumerate((on_contour, ~on_contour)):
        counts[:, k] = np.bincount(pose, weights=use, minlength=N)
        sums[:, k] = np.bincount(pose, weights=d * use, minlength=N)
    with_mask = on_contour & has_mask[view]
    if with_mask.any():
        dm, _ = sample_maps(masks, view, uv, ec.truncate_px, False)
        sums[:, 2] = np.bincount(pose, weights=dm * with_mask, minlength=N)
    return sums, counts


def hypotheses(
    components_R: np.ndarray,
    component_weights: np.ndarray,
    variants: np.ndarray,
    config: VerificationConfig,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The hypotheses a verification asks about: the ``max_components`` heaviest components,
    each as it is and turned by every variant.

    Args:
        components_R: (C, 3, 3) R_world_obj; component_weights: (C,); variants: (M, 3, 3).
    Returns:
        R_world_obj (H, 3, 3); component (H,) index into the components; variant (H,), 0 for the
        component itself, m + 1 for variant m.
    """
    lead = np.argsort(-np.asarray(component_weights), kind="stable")[: config.max_components]
    turns = np.concatenate([np.eye(3)[None], variants])  # (1 + M, 3, 3)
    R_h = np.einsum("cij,mjk->cmik", components_R[lead], turns).reshape(-1, 3, 3)
    return R_h, np.repeat(lead, len(turns)), np.tile(np.arange(len(turns)), len(lead))


def agrees(
    edges: ModelEdges,
    new_views: list[EdgeView],
    R_world_obj: np.ndarray,
    t_world_obj: np.ndarray,
    others_R: np.ndarray,
    margin: float,
    config: VerificationConfig,
) -> bool:
    """Whether each new view agrees with a pose: in it the pose costs at most ``margin`` more
    than the best of ``others_R`` (at the pose's translation). The comparison stays within each
    view, since what a view's costs are depends on what it sees; a view that cannot tell the
    hypotheses apart agrees with any of them.

    Args:
        new_views: the views to ask; R_world_obj: (3, 3); t_world_obj: (3,) metres;
        others_R: (H, 3, 3), the hypotheses a verification would score (:func:`hypotheses`).
    """
    if not new_views or len(others_R) == 0:
        return bool(new_views)
    poses = np.concatenate([np.asarray(R_world_obj, float)[None], others_R])
    cost = score_hypotheses(edges, new_views, poses, t_world_obj, config)  # (1 + H, V)
    return bool(np.all(cost[0] <= cost[1:].min(axis=0) + margin))


def verify(
    edges: ModelEdges,
    views: list[EdgeView],
    components_R: np.ndarray,
    component_weights: np.ndarray,
    variants: np.ndarray,
    t_world_obj: np.ndarray,
    config: VerificationConfig,
    cache: ScoreCache | None = None,
) -> Verdict | None:
    """Score the leading components and their variants in every view (see the module docstring).

    Args:
        components_R: (C, 3, 3) R_world_obj of the mixture's components; component_weights:
        (C,) their weights; variants: (M, 3, 3) object-frame turns (:func:`near_symmetries`);
        t_world_obj: (3,); cache: per-view costs of earlier calls to reuse (ScoreCache), or
        None to score everything.
    Returns:
        None without views or components.
    """
    C = len(components_R)
    if C == 0 or not views:
        return None
    R_h, comp, var = hypotheses(components_R, component_weights, variants, config)
    if cache is None:
        per_view = score_hypotheses(edges, views, R_h, t_world_obj, config)
    else:
        per_view = cached_scores(edges, views, R_h, t_world_obj, config, cache)
    cost = per_view.mean(axis=1)
    flips = {k: getattr(config, k) for k in ("flip_z", "flip_min_views", "flip_deg")}
    best = lead_hypothesis(per_view, R_h, comp, var, component_weights, **flips)
    weights = reweight(cost, comp, component_weights, len(views), config.temperature)
    lowest = int(np.argmin(cost))
    overruled = lowest if lowest != best else -1
    return Verdict(R_h, comp, var, cost, per_view, weights, best, overruled)
