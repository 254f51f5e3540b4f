"""Refinement of a track's full pose over all its views at once (D2CO, Imperoli & Pretto 2015).

Starting from the verified hypothesis (:mod:`estimator.verification.verify`), the pose
``(R_world_obj, t_world_obj)`` is refined by Levenberg-Marquardt on the directional chamfer of
the model's projected edges (:mod:`estimator.verification.model_edges`) in every kept view, plus
the chamfer of its occluding contour to the front end's mask boundary
(:mod:`estimator.verification.edge_maps`). The cameras are known. Residuals
are the distances read from the maps (RoI pixels), with Huber weights; samples at the truncation (no
edge near: occluded, or clutter-free background) carry no gradient and leave the fit. The
translation Gaussian of the track is a prior, and the leading mixture component's covariance a prior
on the rotation, so a direction the edges do not constrain (the axis of a screw) stays where the
mixture put it, with the mixture's uncertainty.

Perturbations: ``t <- t + dt``, ``R <- exp(dphi) R`` (a left perturbation in the world frame),
so the 6x6 covariance, the inverse of the Gauss-Newton information at the solution, is in the
order x, y, z, rot_x, rot_y, rot_z the daemon publishes. Each view counts at most
``points_per_view`` samples' worth of information (neighbouring samples of one edge are not
independent measurements), and the covariance published adds a floor
(``floor_translation_frac``, ``floor_rotation_deg``) for the error the views share, which no
number of views averages out.

The refinement is local: it starts from one hypothesis and keeps to its basin, so symmetric
equivalents stay apart as in the mixture. A result that did not lower the cost, turned farther
than ``accept_deg``, or moved farther than ``accept_frac`` of the diameter from its start, is not
accepted, unless the move is within ``accept_frac_max`` and likely under the translation prior
(``accept_chi2``): a track unsure of its depth may move farther than one seen from many views.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from posefuse.estimator.core.geometry import rotation_angle, so3_exp, so3_log
from posefuse.estimator.verification import kernels
from posefuse.estimator.verification.edge_maps import EdgeView, sample_maps
from posefuse.estimator.verification.model_edges import ModelEdges, pose_edges, project_shown

__all__ = [
    "EdgeScoring",
    "PoseGuess",
    "PosePrior",
    "RefineConfig",
    "Refinement",
    "accepts_translation",
    "refine_pose",
]


@dataclass(frozen=True)
class RefineConfig:
    enabled: bool = True
    iterations: int = 8
    sigma_px: float = 1.5  # std of one edge sample's distance, RoI pixels
    huber_px: float = 2.0
    points_per_view: float = 40.0  # at most this many samples' information per view
    rotation_floor_deg: float = 3.0  # the rotation prior's std is at least this
    # a turn farther than this from the start is refused, to keep the refinement in its basin.
    # The tracker narrows it per part to half the part's smallest near-symmetric turn
    # (verification.refinement_reach_deg): 90 degrees, half a flip, for the catalog's parts. A
    # template match in a pile can be 15 to 30 degrees off in its own basin, and the bound of
    # 15 degrees it had refused the refinements that brought it back
    # (docs/lab/2026-12-04-verification-refinement-basin.md)
    accept_deg: float = 90.0
    accept_frac: float = 0.1  # of the diameter
    # a translation that moved farther than accept_frac, up to accept_frac_max, is accepted
    # where the translation prior finds the move likely: its squared Mahalanobis distance under
    # the prior's covariance at most accept_chi2 (a two-view track, unsure of its depth, may
    # move farther than one seen from eight views); None: never. Chosen on the tuning sets
    # (docs/lab/2026-12-03-verification-translation-prior-allows.md)
    accept_frac_max: float | None = 0.3
    accept_chi2: float = 11.34  # chi2 with 3 degrees of freedom at p = 0.99
    # ... or where the views plainly prefer it: the cost fell by at least this share of the
    # start's (None: never). A track's translation prior can be sure of a centre the front end
    # biased, and then refuses the move the edges of every view ask for. Chosen on the tuning
    # sets (docs/lab/2026-12-05-verification-challenge-and-cost-drop.md)
    accept_cost_drop: float | None = 0.35
    # the published covariance is the inverse of the information at the solution plus a floor
    # (standard deviations per axis): what the views share, the model's edges against the
    # image's and the maps' own bias, does not average out over views, while the information
    # grows with every view. Without it the covariance said a tenth to a hundredth of the
    # errors' variance on the tuning sets (docs/verification.md, "An honest covariance")
    floor_translation_frac: float = 0.01  # of the diameter
    floor_rotation_deg: float = 1.5
    damping: float = 1e-3
    # converged when a step turns by less than this and moves by less than this share of d
    step_tol_deg: float = 0.05
    step_tol_frac: float = 0.001
    cost_tol: float = 0.002  # or when a step lowers the cost by less than this fraction
    # stop as soon as the translation has moved farther than accept_frac from the start: the
    # result would be refused unless the prior pulled it back, which changed no score on the
    # tuning and held-out sets (docs/verification.md)
    stop_when_refused: bool = True
    # every n-th edge sample is read (ModelEdges.subset), each standing for n samples of the
    # full sampling: a view counts at most points_per_view samples' information either way
    sample_stride: int = 1
    # the data term by the compiled kernel (estimator.verification.kernels), or by the numpy
    # code it replaced (the reference, equal to rounding)
    compiled: bool = True

    def __post_init__(self) -> None:
        if (
            self.sample_stride < 1
            or self.iterations < 1
            or (self.accept_frac_max is not None and self.accept_frac_max < self.accept_frac)
            or self.floor_translation_frac < 0
            or self.floor_rotation_deg < 0
            or (self.accept_cost_drop is not None and not 0.0 < self.accept_cost_drop <= 1.0)
        ):
            raise ValueError(f"invalid refinement config: {self}")


@dataclass(frozen=True, eq=False)
class Refinement:
    """R_world_obj: (3, 3); t_world_obj: (3,) metres; cov: (6, 6) over (t, rotation) as in the
    module docstring; cost_start / cost: the objective before and after; accepted: False when
    the result was refused (then R, t are the start and cov the priors'); refused: why, the
    first of "cost" (not lowered), "rotation" (turned past accept_deg) and "translation" (moved
    past what the bounds allow), "" when accepted."""

    R_world_obj: np.ndarray
    t_world_obj: np.ndarray
    cov: np.ndarray
    cost_start: float
    cost: float
    iterations: int
    accepted: bool
    refused: str = ""


def _robust(d: np.ndarray, k: float) -> tuple[np.ndarray, np.ndarray]:
    """Huber's rho(d) (as a squared residual) and its IRLS weight."""
    rho = np.where(d <= k, d * d, 2 * k * d - k * k)
    w = np.where(d <= k, 1.0, k / np.maximum(d, 1e-12))
    return rho, w


@dataclass(frozen=True, eq=False)
class _ViewStack:
    """The kept views as arrays, built once per refinement.

    R_cw: (V, 3, 3), t_cw: (V, 3) T_cam_world; K: (V, 3, 3) RoI intrinsics; maps: (V * bins +
    V, L, L) uint8, every view's directional chamfer maps, then its mask-boundary map (the
    truncation where it has none); has_mask: (V,) bool.
    """

    R_cw: np.ndarray
    t_cw: np.ndarray
    K: np.ndarray
    maps: np.ndarray
    has_mask: np.ndarray

    @classmethod
    def of(cls, views: list[EdgeView]) -> _ViewStack:
        T = np.array([v.T_cam_world for v in views])
        empty = np.full(views[0].dcdt.shape[1:], 255, np.uint8)
        masks = [v.mask_dt if v.mask_dt is not None else empty for v in views]
        maps = np.concatenate([np.concatenate([v.dcdt for v in views]), np.stack(masks)])
        has_mask = np.array([v.mask_dt is not None for v in views])
        return cls(T[:, :3, :3], T[:, :3, 3], np.array([v.K_roi for v in views]), maps, has_mask)


@dataclass(frozen=True, eq=False)
class _Reads:
    """The maps read at one pose for one or more sample sets, every sample once.

    R: (3, 3) R_world_obj; t_cam: (V, 3) the pose's translation in each camera; view, sample:
    (n,) of each read; mask: (n,) bool, a read of the mask-boundary map (else of the directional
    chamfer); d: (n,) pixels; grad: (n, 2) d d / d (u, v). The chamfer reads come first, in
    (view, sample) order, then the mask reads in the same order: a set's reads, taken out in
    order, are those reading that set alone would make.
    """

    R: np.ndarray
    t_cam: np.ndarray
    view: np.ndarray
    sample: np.ndarray
    mask: np.ndarray
    d: np.ndarray
    grad: np.ndarray


def _read(
    edges: ModelEdges,
    stack: _ViewStack,
    R: np.ndarray,
    t: np.ndarray,
    shown: np.ndarray,
    on_contour: np.ndarray,
    truncate: float,
    bins: int,
    mask_weight: float,
) -> _Reads:
    """Read at (R, t) the directional chamfer of the ``shown`` samples (V, P) bool and the mask
    boundary's distance of those ``on_contour`` (V, P) bool, all views in one call."""
    V = len(stack.R_cw)
    R_cam = stack.R_cw @ R  # (V, 3, 3)
    t_cam = stack.R_cw @ t + stack.t_cw  # (V, 3)
    view, sample, uv, angle = project_shown(edges, shown, R_cam, t_cam, stack.K)
    b = np.floor(angle / (np.pi / bins) + 0.5).astype(np.intp) % bins
    if mask_weight > 0:
        masked = np.flatnonzero(on_contour[view, sample] & stack.has_mask[view])
    else:
        masked = np.zeros(0, np.intp)
    read = np.concatenate([np.arange(len(view)), masked]).astype(np.intp)
    channel = np.concatenate([view * bins + b, V * bins + view[masked]])
    d, grad = sample_maps(stack.maps, channel, uv[read], truncate)
    is_mask = np.zeros(len(read), bool)
    is_mask[len(view) :] = True
    return _Reads(R, t_cam, view[read], sample[read], is_mask, d, grad)


def _data_term(
    edges: ModelEdges,
    stack: _ViewStack,
    reads: _Reads,
    sets: tuple[np.ndarray, np.ndarray],
    truncate: float,
    crease_weight: float,
    mask_weight: float,
    config: RefineConfig,
    want_jacobian: bool = True,
) -> tuple[float, np.ndarray, np.ndarray]:
    """The data term's cost, information H (6, 6) and gradient g (6,) of the samples ``sets``
    (contour, crease), each (V, P) bool, from ``reads`` that hold them (:func:`_read`)."""
    V = len(stack.R_cw)
    on_contour, crease = sets
    c = on_contour[reads.view, reads.sample]
    use = np.flatnonzero(np.where(reads.mask, c, c | crease[reads.view, reads.sample]))
    view = reads.view[use]
    term = np.where(reads.mask[use], 2, np.where(c[use], 0, 1))
    d, grad = reads.d[use], reads.grad[use]
    group = view * 3 + term  # (view, term) of each read
    n = np.bincount(group, minlength=3 * V)
    term_weight = np.array([1.0, crease_weight, mask_weight])[term]
    # each sample read stands for sample_stride of the full sampling, up to points_per_view
    # samples' worth per view and term
    scale = (
        term_weight
        * np.minimum(config.sample_stride, config.points_per_view / n[group])
        / config.sigma_px**2
    )
    rho, w = _robust(np.minimum(d, truncate), config.huber_px)
    cost = float(np.sum(scale * rho))
    H, g = np.zeros((6, 6)), np.zeros(6)
    live = np.flatnonzero(d < truncate * 0.999)
    if not want_jacobian or len(live) == 0:
        return cost, H, g
    # the live reads grouped by view (the order of the rows does not change H or g), so that
    # each view's camera and intrinsics apply to its rows in one product
    live = live[np.argsort(view[live], kind="stable")]
    v_l, s_l = view[live], reads.sample[use[live]]
    bounds = np.searchsorted(v_l, np.arange(V + 1))
    a = edges.points[s_l] @ reads.R.T  # (n, 3) R p: the sample turned, before the translation
    # per view, the gradient pulled back through the RoI intrinsics (d distance / d (x/z, y/z)),
    # then through the projection, d (x/z, y/z) / d p = [[1/z, 0, -x/z^2], [0, 1/z, -y/z^2]]
    # (projection.project_jacobian at K = I, written out), then to the world frame: d p_cam /
    # d (dt, dphi) = R_cw [I, -hat(R p)], so g_w = R_cw^T grad_p gives the row [g_w, (R p) x g_w]
    J = np.empty((len(live), 6))
    for v in np.flatnonzero(np.diff(bounds)):
        rows = slice(bounds[v], bounds[v + 1])
        p_cam = a[rows] @ stack.R_cw[v].T + reads.t_cam[v]
        e = grad[live[rows]] @ stack.K[v, :2, :2]
        inv_z = 1.0 / p_cam[:, 2]
        grad_p = np.empty_like(p_cam)
        grad_p[:, 0] = e[:, 0] * inv_z
        grad_p[:, 1] = e[:, 1] * inv_z
        grad_p[:, 2] = -(e[:, 0] * p_cam[:, 0] + e[:, 1] * p_cam[:, 1]) * inv_z * inv_z
        J[rows, :3] = grad_p @ stack.R_cw[v]
    g_w = J[:, :3]
    J[:, 3] = a[:, 1] * g_w[:, 2] - a[:, 2] * g_w[:, 1]
    J[:, 4] = a[:, 2] * g_w[:, 0] - a[:, 0] * g_w[:, 2]
    J[:, 5] = a[:, 0] * g_w[:, 1] - a[:, 1] * g_w[:, 0]
    wl = w[live] * scale[live]
    H = (J * wl[:, None]).T @ J
    g = J.T @ (wl * d[live])
    return cost, H, g


def _showing(
    edges: ModelEdges, stack: _ViewStack, R: np.ndarray, t: np.ndarray, compiled: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """The samples showing at (R, t) in every view: (contour, crease), each (V, P) bool."""
    R_cam = stack.R_cw @ R
    t_cam = stack.R_cw @ t + stack.t_cw
    _, _, active, contour = pose_edges(edges, R_cam, t_cam, compiled)
    return contour, active & ~contour


def _linearize(
    edges: ModelEdges,
    stack: _ViewStack,
    R: np.ndarray,
    t: np.ndarray,
    truncate: float,
    bins: int,
    crease_weight: float,
    mask_weight: float,
    config: RefineConfig,
    want_jacobian: bool = True,
    sets: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[float, np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """The data term's cost, information H (6, 6) and gradient g (6,) at (R, t), and the
    samples used: (contour, crease), each (V, P) bool. Given ``sets``, those samples are used
    instead of the ones showing at (R, t): within one step the objective then compares like
    with like. All views' samples are read in one call."""
    if sets is None:
        sets = _showing(edges, stack, R, t, config.compiled)
    scoring = EdgeScoring(truncate, bins, crease_weight, mask_weight)
    cost, H, g = _data(edges, stack, R, t, sets, scoring, config, want_jacobian)
    return cost, H, g, sets


def _data(
    edges: ModelEdges,
    stack: _ViewStack,
    R: np.ndarray,
    t: np.ndarray,
    sets: tuple[np.ndarray, np.ndarray],
    scoring: EdgeScoring,
    config: RefineConfig,
    want_jacobian: bool = True,
    reads: _Reads | None = None,
) -> tuple[float, np.ndarray, np.ndarray]:
    """The data term's cost, information H (6, 6) and gradient g (6,) at (R, t) of the samples
    ``sets`` (contour, crease), by the compiled kernel (``config.compiled``) or by numpy from
    ``reads`` that hold them (None: read now)."""
    if config.compiled:
        f64, flag = kernels.as_f64, kernels.as_bool  # one layout: one compiled signature
        return kernels.data_term(
            f64(edges.points),
            f64(edges.directions),
            flag(sets[0]),
            flag(sets[1]),
            f64(R),
            f64(t),
            f64(stack.R_cw),
            f64(stack.t_cw),
            f64(stack.K),
            np.ascontiguousarray(stack.maps, np.uint8),
            flag(stack.has_mask),
            scoring.bins,
            float(scoring.truncate_px),
            float(scoring.crease_weight),
            float(scoring.mask_weight),
            config.sample_stride,
            float(config.points_per_view),
            float(config.sigma_px),
            float(config.huber_px),
            want_jacobian,
        )
    if reads is None:
        shown, contour = sets[0] | sets[1], sets[0]
        reads = _read(
            edges,
            stack,
            R,
            t,
            shown,
            contour,
            scoring.truncate_px,
            scoring.bins,
            scoring.mask_weight,
        )
    return _data_term(
        edges,
        stack,
        reads,
        sets,
        scoring.truncate_px,
        scoring.crease_weight,
        scoring.mask_weight,
        config,
        want_jacobian,
    )


def accepts_translation(
    moved: np.ndarray,
    info_t: np.ndarray,
    diameter: float,
    config: RefineConfig,
    cost_drop: float | None = None,
) -> bool:
    """Whether a refinement whose translation moved by ``moved`` (3,) metres from its start is
    accepted: within ``accept_frac`` of the diameter, or within ``accept_frac_max`` where the
    translation prior, of information ``info_t`` (3, 3) 1/m^2, finds the move likely (squared
    Mahalanobis distance at most ``accept_chi2``) or the views plainly prefer it (``cost_drop``,
    the share of the start's cost the refinement took off, at least ``accept_cost_drop``)."""
    distance = float(np.linalg.norm(moved))
    if distance <= config.accept_frac * diameter:
        return True
    if config.accept_frac_max is None or distance > config.accept_frac_max * diameter:
        return False
    if float(moved @ info_t @ moved) <= config.accept_chi2:
        return True
    return (
        config.accept_cost_drop is not None
        and cost_drop is not None
        and cost_drop >= config.accept_cost_drop
    )


@dataclass(frozen=True, eq=False)
class PoseGuess:
    """A full pose to start from: R_world_obj (3, 3), t_world_obj (3,) metres."""

    R_world_obj: np.ndarray
    t_world_obj: np.ndarray


@dataclass(frozen=True, eq=False)
class PosePrior:
    """What the refinement is pulled back to: the translation Gaussian of the track (t_world_obj
    (3,) metres, cov_t (3, 3) m^2) and the rotation's covariance about the start (cov_R (3, 3)
    rad^2, a left perturbation in the world frame, floored at ``rotation_floor_deg``)."""

    t_world_obj: np.ndarray
    cov_t: np.ndarray
    cov_R: np.ndarray


@dataclass(frozen=True)
class EdgeScoring:
    """How the views were built and are scored: the chamfer's truncation (RoI pixels) and
    orientation bins (:class:`estimator.verification.edge_maps.EdgeConfig`), and the weights of
    the creases and of the mask's boundary against the contour
    (:class:`estimator.verification.verify.VerificationConfig`)."""

    truncate_px: float
    bins: int
    crease_weight: float
    mask_weight: float

    @classmethod
    def of(cls, verification) -> EdgeScoring:
        """The scoring of a ``VerificationConfig``."""
        return cls(
            verification.edges.truncate_px,
            verification.edges.bins,
            verification.crease_weight,
            verification.mask_weight,
        )


def refine_pose(
    edges: ModelEdges,
    views: list[EdgeView],
    start: PoseGuess,
    prior: PosePrior,
    scoring: EdgeScoring,
    config: RefineConfig,
    warm: PoseGuess | None = None,
) -> Refinement:
    """Levenberg-Marquardt on the chamfer over all views, with the priors of the module
    docstring.

    Args:
        start: where the rotation prior is centred and the iterations begin; prior: the
        translation prior and the rotation's covariance; scoring: as the views were built and
        are scored; warm: where to start instead of the start (the priors stay where they
        are), taken only where it costs less than the start.
    """
    R_start, t_start = start.R_world_obj, start.t_world_obj
    t_prior, cov_t_prior, cov_R_prior = prior.t_world_obj, prior.cov_t, prior.cov_R
    truncate_px, bins = scoring.truncate_px, scoring.bins
    mask_weight = scoring.mask_weight
    edges = edges.subset(config.sample_stride)
    floor = np.deg2rad(config.rotation_floor_deg) ** 2
    w_eig, V = np.linalg.eigh(0.5 * (cov_R_prior + cov_R_prior.T))
    info_R = V @ np.diag(1.0 / np.maximum(w_eig, floor)) @ V.T
    info_t = np.linalg.inv(cov_t_prior)

    stack = _ViewStack.of(views)

    def union_reads(R, t, *sets_list):
        """The numpy path's reads at (R, t) of every sample of ``sets_list`` (each (contour,
        crease)), in one pass; None compiled, where each objective reads what it scores."""
        if config.compiled:
            return None
        shown = np.logical_or.reduce([s_ for sets_ in sets_list for s_ in sets_])
        contour = np.logical_or.reduce([sets_[0] for sets_ in sets_list])
        return _read(edges, stack, R, t, shown, contour, truncate_px, bins, mask_weight)

    def objective(R, t, sets, reads=None, want_jacobian=True):
        """The cost, information and gradient at (R, t) of the samples ``sets``, data and
        priors, from ``reads`` that hold them (None: read them now; not used compiled)."""
        cost, H, g = _data(edges, stack, R, t, sets, scoring, config, want_jacobian, reads)
        r_t = t - t_prior
        r_R = so3_log(R @ R_start.T)
        cost += float(r_t @ info_t @ r_t + r_R @ info_R @ r_R)
        H[:3, :3] += info_t
        H[3:, 3:] += info_R
        g[:3] += info_t @ r_t
        g[3:] += info_R @ r_R
        return cost, H, g

    R, t = R_start.copy(), np.asarray(t_start, float).copy()
    sets = _showing(edges, stack, R, t, config.compiled)
    if warm is None:
        cost, H, g = objective(R, t, sets)
        cost_start = cost
    else:
        # a warm start (the last result of the same hypothesis), taken where it costs less. It
        # mostly does, so its Jacobian is taken at once and the start's only if the start wins
        R_w, t_w = np.asarray(warm.R_world_obj, float), np.asarray(warm.t_world_obj, float)
        sets_w = _showing(edges, stack, R_w, t_w, config.compiled)
        warm = objective(R_w, t_w, sets_w)
        reads = union_reads(R, t, sets)
        cost_start, _, _ = objective(R, t, sets, reads, want_jacobian=False)
        if warm[0] < cost_start:
            R, t, sets = R_w, t_w, sets_w
            cost, H, g = warm
        else:
            cost, H, g = objective(R, t, sets, reads)

    def translation_allowed(moved: np.ndarray, cost: float) -> bool:
        drop = 1.0 - cost / cost_start if cost_start > 0 else 0.0
        return accepts_translation(moved, info_t, edges.diameter, config, drop)

    step_tol_rad, step_tol_m = (
        np.deg2rad(config.step_tol_deg),
        config.step_tol_frac * edges.diameter,
    )
    lam = config.damping
    rejected = 0
    it = 0  # the iterations run, reported in the result
    for it in range(1, config.iterations + 1):  # noqa: B007 (read after the loop)
        A = H + lam * np.diag(np.diag(H))
        delta = -np.linalg.solve(A, g)
        small = np.linalg.norm(delta[3:]) < step_tol_rad and np.linalg.norm(delta[:3]) < step_tol_m
        R_new, t_new = so3_exp(delta[3:]) @ R, t + delta[:3]
        # the step is judged on the samples it was computed from, then the set is renewed. By
        # numpy both sets are read in one pass, the step mostly holding; compiled, each
        # objective reads its own, and the new set is made only for a step that holds
        sets_new = None if config.compiled else _showing(edges, stack, R_new, t_new, False)
        reads = None if config.compiled else union_reads(R_new, t_new, sets, sets_new)
        cost_same, _, _ = objective(R_new, t_new, sets, reads, want_jacobian=False)
        if cost_same < cost:
            before = cost
            if sets_new is None:
                sets_new = _showing(edges, stack, R_new, t_new, True)
            R, t, sets = R_new, t_new, sets_new
            cost, H, g = objective(R, t, sets, reads)
            lam = max(lam / 3, 1e-7)
            rejected = 0
            # converged: the step was below the tolerance, or lowered the cost by a fraction
            # the samples' renewal outweighs
            if small or before - cost < config.cost_tol * before:
                break
            # gone past what would be accepted: refused (the prior seldom pulls it back)
            if config.stop_when_refused and not translation_allowed(t - t_start, cost):
                break
        else:
            lam *= 5
            rejected += 1
            # the damped step no longer moves, or two in a row found no lower cost
            if small or rejected >= 2:
                break
    U, _, Vt = np.linalg.svd(R)
    R = U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt
    moved_deg = float(np.rad2deg(rotation_angle(R @ R_start.T)))
    refused = (
        "cost"
        if not cost < cost_start
        else "rotation"
        if moved_deg > config.accept_deg
        else ""
        if translation_allowed(t - t_start, cost)
        else "translation"
    )
    accepted = not refused
    cov = np.linalg.inv(0.5 * (H + H.T)) + np.diag(
        [(config.floor_translation_frac * edges.diameter) ** 2] * 3
        + [np.deg2rad(config.floor_rotation_deg) ** 2] * 3
    )
    if not accepted:
        R, t, cost = R_start.copy(), np.asarray(t_start, float).copy(), cost_start
        cov = np.zeros((6, 6))
        cov[:3, :3] = cov_t_prior
        cov[3:, 3:] = cov_R_prior
    return Refinement(R, t, 0.5 * (cov + cov.T), cost_start, cost, it, accepted, refused)
