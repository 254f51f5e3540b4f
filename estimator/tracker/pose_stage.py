"""The pose stage of a track: once its translation is known well enough, each waiting view's
rotation is measured against the class's templates and fused in the track's mixture
(:mod:`estimator.rotation`); views from new viewpoints keep their edge maps, and the leading
hypotheses are verified across them and the winner's full pose refined
(:mod:`estimator.verification`).

:class:`PoseStage` owns what this needs per class, made on first use and shared by every track
of the class: the rotation matcher (its template bank built or loaded), the model's edge
samples, its near-symmetric turns and the refinement's settings; and the images of the last
few frames, which views still waiting for their rotation read.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from posefuse.estimator.core.geometry import rotation_angle
from posefuse.estimator.core.objects import Catalog
from posefuse.estimator.rotation.matching import RotationMatcher
from posefuse.estimator.rotation.mixture import RotationMixture
from posefuse.estimator.rotation.templates import (
    TemplateBank,
    build_template_bank,
    build_template_banks,
)
from posefuse.estimator.tracker.config import TrackerConfig
from posefuse.estimator.tracker.tracks import Track
from posefuse.estimator.translation.gaussian import MIN_DEPTH
from posefuse.estimator.verification import turns as turn_judge
from posefuse.estimator.verification.edge_maps import EdgeRoi, EdgeView, edge_maps, edge_roi
from posefuse.estimator.verification.model_edges import ModelEdges, model_edges
from posefuse.estimator.verification.refinement import (
    EdgeScoring,
    PoseGuess,
    PosePrior,
    RefineConfig,
    accepts_translation,
    refine_pose,
)
from posefuse.estimator.verification.verify import (
    agrees,
    hypotheses,
    is_new_viewpoint,
    near_symmetries,
    near_symmetry_turns,
    refinement_reach_deg,
    reweight,
    score_hypotheses,
    verify,
)


class PoseStage:
    """Rotation measurement, verification and refinement of tracks (see the module
    docstring). Deterministic: the same calls in the same order give the same poses."""

    def __init__(
        self,
        catalog: Catalog,
        config: TrackerConfig,
        banks: dict[int, TemplateBank] | None = None,
        template_cache_dir: str | None = None,
        show_progress: bool = False,
        matchers: dict | None = None,
    ):
        self.catalog = catalog
        self.config = config
        self.matchers = {k: RotationMatcher(b, config.rotation) for k, b in (banks or {}).items()}
        self.matchers.update(matchers or {})
        self.template_cache_dir = template_cache_dir
        self.show_progress = show_progress
        self.images: dict[int, np.ndarray] = {}  # stamp_ns -> image, the last few frames
        self.edges: dict[int, ModelEdges] = {}  # per class, for verification
        self.variants: dict[int, np.ndarray] = {}  # per class, near-symmetric turns (M, 3, 3)
        # per class, the turns of its catalog's near-symmetric groups that the verification
        # does not ask about (K, 3, 3): published as the pose's alternatives
        self.unasked: dict[int, np.ndarray] = {}
        # per class, the refinement's settings with its turn bounded by the class's basin
        self.refine_configs: dict[int, RefineConfig] = {}
        # per class, the edge samples that tell its unasked turns apart (None: no such turns,
        # or the judge is off; estimator.verification.turns)
        self.distinct: dict[int, ModelEdges | None] = {}

    # ---- per class, made once --------------------------------------------------------------

    def banks(self) -> dict[int, TemplateBank]:
        """The template banks built or loaded so far (to share with other estimators)."""
        return {k: m.bank for k, m in self.matchers.items()}

    def prepare_templates(self, workers: int = 2, progress=None) -> None:
        """Load or build every class's template bank now, building missing ones in ``workers``
        processes (see :func:`estimator.rotation.templates.build_template_banks`)."""
        todo = [self.catalog[k] for k in self.catalog if k not in self.matchers]
        banks = build_template_banks(
            todo, self.config.templates, self.template_cache_dir, workers, progress
        )
        for obj_id, bank in banks.items():
            self.matchers[obj_id] = RotationMatcher(bank, self.config.rotation)

    def matcher(self, obj_id: int) -> RotationMatcher:
        """The rotation matcher of a class (its template bank built or loaded on first use)."""
        if obj_id not in self.matchers:
            bank = build_template_bank(
                self.catalog[obj_id],
                self.config.templates,
                self.template_cache_dir,
                show_progress=self.show_progress,
            )
            self.matchers[obj_id] = RotationMatcher(bank, self.config.rotation)
        return self.matchers[obj_id]

    def refinement_config(self, obj_id: int) -> RefineConfig:
        """The refinement's settings for a class: the tracker's, its turn bounded by the part's
        basin (:func:`estimator.verification.verify.refinement_reach_deg`)."""
        self.model_edges(obj_id)
        return self.refine_configs[obj_id]

    def model_edges(self, obj_id: int) -> tuple[ModelEdges, np.ndarray]:
        """The class's edge samples and near-symmetric turns (M, 3, 3), and with them the
        refinement's settings for the class (:meth:`refinement_config`); made on first use."""
        if obj_id not in self.edges:
            model = self.catalog[obj_id]
            cfg = self.config.verification
            self.edges[obj_id] = model_edges(model.mesh, model.diameter, cfg.edges)
            sym = np.concatenate([np.eye(3)[None], model.symmetries_discrete[:, :3, :3]])
            axes = np.array([c.axis for c in model.symmetries_continuous]).reshape(-1, 3)
            self.variants[obj_id] = near_symmetries(
                model.points, model.diameter, sym, axes, cfg.near_frac, cfg.max_variants
            )
            near = model.near_symmetries
            variants = self.variants[obj_id]
            judged = np.zeros(len(variants), bool)
            if cfg.turns.variants_frac > 0 and len(variants):
                judged = (
                    turn_judge.surface_moves(model.points, model.diameter, variants)
                    <= cfg.turns.variants_frac
                )
            self.unasked[obj_id] = np.concatenate(
                [
                    near_symmetry_turns(
                        np.array([g.axis for g in near]).reshape(-1, 3),
                        np.array([g.order for g in near], int),
                        sym,
                        axes,
                        variants[~judged],
                    ),
                    variants[judged],
                ]
            )
            self.distinct[obj_id] = (
                turn_judge.distinct_edges(
                    model.mesh, model.diameter, self.unasked[obj_id], cfg.edges, cfg.turns
                )
                if cfg.turns.enabled and len(self.unasked[obj_id])
                else None
            )
            reach = refinement_reach_deg(self.variants[obj_id], sym, axes)
            rcfg = self.config.refinement
            self.refine_configs[obj_id] = replace(rcfg, accept_deg=min(rcfg.accept_deg, reach))
        return self.edges[obj_id], self.variants[obj_id]

    # ---- per frame -------------------------------------------------------------------------

    def keep_image(self, stamp_ns: int, image: np.ndarray) -> None:
        """Keep a frame's image (H, W, 3) for the views that wait for their rotation; the
        oldest received beyond ``max_pending_views`` are forgotten."""
        self.images[stamp_ns] = image
        for stale in list(self.images)[: -self.config.max_pending_views]:
            del self.images[stale]

    def translation_known(self, track: Track, T_cam_world: np.ndarray) -> bool:
        """Whether the track's depth in this camera is known to ``rotation_max_depth_rel_std``."""
        t = track.estimate.t_world_obj
        p = T_cam_world[:3, :3] @ t + T_cam_world[:3, 3]
        if p[2] <= MIN_DEPTH:
            return False
        ray_world = T_cam_world[:3, :3].T @ (p / np.linalg.norm(p))
        depth_std = np.sqrt(ray_world @ track.estimate.cov @ ray_world)
        return depth_std / p[2] <= self.config.rotation_max_depth_rel_std

    def measure_rotations(self, track: Track, serial: int = 0) -> None:
        """Measure the rotation in the track's waiting views, once its translation allows; keep
        the edge maps of new viewpoints, and verify when they add to what the track shows: now,
        or, with ``deferred_verification``, when :meth:`check_due` is called (the track waits
        from view ``serial``)."""
        if not track.pending or not self.translation_known(track, track.pending[-1].T_cam_world):
            return
        if track.mixture is None:
            track.mixture = RotationMixture.for_model(
                self.catalog[track.obj_id], self.config.mixture
            )
        matcher = self.matcher(track.obj_id)
        t_world = track.estimate.t_world_obj
        vcfg = self.config.verification
        model = self.catalog[track.obj_id]
        added: list[int] = []  # stamps of the views kept
        for stamp, T_cam_world, K, mask, silhouette in track.pending:
            image = self.images.get(stamp)
            if image is None:
                continue
            t_cam = T_cam_world[:3, :3] @ t_world + T_cam_world[:3, 3]
            for m in matcher.measure(image, K, t_cam, mask):
                R_world_obj = T_cam_world[:3, :3].T @ m.R_cam_obj
                track.mixture.add(R_world_obj, m.confidence)
            others = [v.T_cam_world for v in track.edge_views if v.stamp_ns != stamp]
            if (
                vcfg.enabled
                and t_cam[2] > MIN_DEPTH
                and is_new_viewpoint(
                    np.array(others).reshape(-1, 4, 4),
                    T_cam_world,
                    t_world,
                    vcfg.keyframe_deg,
                    vcfg.keyframe_distance_frac,
                )
            ):
                # the RoI now, while the image is at hand; its maps now, or with a deferred
                # check when the check comes (off the frame's path). A box is not the part's
                # outline: its edges would pull the model's contour onto them
                outline = mask if silhouette else None
                view = edge_roi(
                    image, K, T_cam_world, t_cam, model.diameter, vcfg.edges, outline, stamp
                )
                if not self.config.deferred_verification:
                    view = edge_maps(view, vcfg.edges)
                track.edge_views = [v for v in track.edge_views if v.stamp_ns != stamp] + [view]
                del track.edge_views[: -vcfg.max_views]
                added.append(stamp)
        track.pending.clear()
        if not self.config.deferred_verification:
            self.check(track, added)
        elif added or (self.stale(track) and track.edge_views):
            # the check waits for :meth:`check_due`; a track already waiting keeps its place
            if track.check_since is None:
                track.check_since = serial
            track.check_added = track.check_added | frozenset(added)

    @staticmethod
    def stale(track: Track) -> bool:
        """Whether the mixture no longer has the components the last verdict weighed."""
        verdict = track.verdict
        return verdict is None or len(verdict.weights) != len(track.mixture.components)

    def check(self, track: Track, added: list[int]) -> None:
        """Verify the track again when views (stamps ``added``) add to what the kept views
        show, unless it is settled and they agree with it, or when the mixture no longer has
        the components the last verdict weighed."""
        if track.mixture is None:
            return
        stale = self.stale(track)
        if added and not stale and self.settled(track):
            track.settled_stamps = track.settled_stamps | set(added)
            # the new views may show what tells the turns apart; the pose is the same, so
            # only they are scored (TurnScoreCache)
            self.judge_turns(track)
            self.measure_fit(track)
            return
        if (stale and track.edge_views) or added:
            self.verify(track, new_views=bool(added))
            self.judge_turns(track)
            self.measure_fit(track)

    def check_due(self, track: Track) -> None:
        """The check a deferred track waits for (TrackerConfig.deferred_verification), with
        every view kept since it began to wait; the track then waits no longer, even if the
        check raises (its verdict is then forgotten, so it is not published as verified). The
        maps of the views kept since are made first (:func:`edge_maps` of their RoIs)."""
        kept = {v.stamp_ns for v in track.edge_views}
        added = sorted(s for s in track.check_added if s in kept)
        track.check_since, track.check_added = None, frozenset()
        try:
            ecfg = self.config.verification.edges
            track.edge_views = [
                edge_maps(v, ecfg) if isinstance(v, EdgeRoi) else v for v in track.edge_views
            ]
            self.check(track, added)
        except Exception:
            # the last verdict no longer speaks for the views: the mixture's pose is published
            # (unverified) until a new view asks again
            track.verdict, track.refined, track.turns, track.fit = None, None, None, None
            raise

    def settled(self, track: Track) -> bool:
        """Whether the track's refined pose still holds, so that verifying and refining again
        for the views just kept would change nothing (VerificationConfig.settled_margin):

        - the refinement was accepted, and the translation has moved less than
          ``settled_translation_frac`` of the diameter from the prior it took;
        - every kept view the pose has not yet been checked against agrees with it: in each,
          the pose costs at most ``settled_margin`` more than the best of the hypotheses a
          verification would ask about (:func:`estimator.verification.verify.agrees`: within
          each view, whose costs depend on what it sees, never across views).

        A settled track then costs those hypotheses scored in its new views instead of in every
        kept view, and no refinement. A mixture that changes is verified as before (keeping the
        refined pose without it lost a part on the tuning sets, docs/verification.md), and
        refined unless the winner still holds the refinement (:meth:`verify`)."""
        vcfg = self.config.verification
        refined = track.refined
        if vcfg.settled_margin is None or refined is None or not refined.accepted:
            return False
        edges, variants = self.model_edges(track.obj_id)
        if (
            track.refined_t_prior is None
            or np.linalg.norm(track.estimate.t_world_obj - track.refined_t_prior)
            > vcfg.settled_translation_frac * edges.diameter
        ):
            return False
        new = [v for v in track.edge_views if v.stamp_ns not in track.settled_stamps]
        if len(new) == len(track.edge_views):
            return False
        if not new:
            return True
        components_R = np.array([c.R_world_obj for c in track.mixture.components])
        R_h, _, _ = hypotheses(components_R, track.mixture.weights, variants, vcfg)
        return agrees(
            edges, new, refined.R_world_obj, refined.t_world_obj, R_h, vcfg.settled_margin, vcfg
        )

    def verify(self, track: Track, new_views: bool = True) -> None:
        """Score the leading hypotheses in all kept views; refine the winner over them
        (:mod:`estimator.verification.verify`, :mod:`estimator.verification.refinement`).

        Without new views (the mixture gained or lost a component), a winner whose basin holds
        the last accepted refinement (within ``accept_deg``, and its translation a move from
        today's that a refinement would accept, ``refinement.accepts_translation``), at a
        translation that has moved less than ``settled_translation_frac`` of the diameter from
        that refinement's prior, keeps it: the kept views are the ones it was refined over or
        ones that agreed with it (:meth:`settled`), so refining again from the same place would
        land where it did (``VerificationConfig.reuse_refinement``)."""
        mixture = track.mixture
        if mixture is None or not mixture.components or not track.edge_views:
            return
        edges, variants = self.model_edges(track.obj_id)
        vcfg = self.config.verification
        components_R = np.array([c.R_world_obj for c in mixture.components])
        verdict = verify(
            edges,
            track.edge_views,
            components_R,
            mixture.weights,
            variants,
            track.estimate.t_world_obj,
            vcfg,
            track.scores,
        )
        track.verdict, track.turns = verdict, None  # judged again after it (check)
        rcfg = self.refinement_config(track.obj_id)
        previous, track.refined = track.refined, None
        if verdict is None or not rcfg.enabled:
            return
        lead = mixture.components[int(verdict.component[verdict.best])]
        R_start = verdict.R_world_obj[verdict.best]
        # the last refined pose, where it lies in the basin of today's start, is a warm start
        warm = None
        if (
            previous is not None
            and previous.accepted
            and rotation_angle(previous.R_world_obj @ R_start.T) <= np.deg2rad(rcfg.accept_deg)
            and accepts_translation(
                previous.t_world_obj - track.estimate.t_world_obj,
                np.linalg.inv(track.estimate.cov),
                edges.diameter,
                rcfg,
            )
        ):
            warm = PoseGuess(previous.R_world_obj, previous.t_world_obj)
        if (
            warm is not None  # in the winner's basin, and near today's translation
            and not new_views
            and vcfg.reuse_refinement
            and track.refined_t_prior is not None
            and np.linalg.norm(track.estimate.t_world_obj - track.refined_t_prior)
            <= vcfg.settled_translation_frac * edges.diameter
        ):
            track.refined = previous
            return
        # the component's covariance, turned with its variant (a turn in the object frame
        # leaves a world-frame left perturbation as it is)
        track.refined_t_prior = track.estimate.t_world_obj.copy()
        track.settled_stamps = frozenset(v.stamp_ns for v in track.edge_views)
        t_world = track.estimate.t_world_obj
        track.refined = refine_pose(
            edges,
            track.edge_views,
            PoseGuess(R_start, t_world),
            PosePrior(t_world, track.estimate.cov, lead.cov),
            EdgeScoring.of(vcfg),
            rcfg,
            warm,
        )
        self._challenge(track, edges, rcfg)

    @staticmethod
    def verified_pose(track: Track) -> tuple[np.ndarray, np.ndarray] | None:
        """(R_world_obj (3, 3), t_world_obj (3,)) the track publishes as verified: the refined
        pose where the refinement was accepted, else the verdict's winner at the track's
        translation, turned as the turn judge says; None without a verdict."""
        verdict = track.verdict
        if verdict is None:
            return None
        refined = track.refined
        if refined is not None and refined.accepted:
            R_world_obj, t_world_obj = refined.R_world_obj, refined.t_world_obj
        else:
            R_world_obj = verdict.R_world_obj[verdict.best]
            t_world_obj = track.estimate.t_world_obj
        if track.turns is not None:
            R_world_obj = R_world_obj @ track.turns.turn
        return R_world_obj, t_world_obj

    def measure_fit(self, track: Track) -> None:
        """``track.fit``: the verified pose's mean cost in the kept views (the cost of
        :func:`score_hypotheses`, as the challenge reads it); None without a verdict or views.
        Published above ``VerificationConfig.max_fit``, a confirmed track says tentative;
        without that gate nothing is measured (None)."""
        pose = self.verified_pose(track)
        views = [v for v in track.edge_views if isinstance(v, EdgeView)]
        if pose is None or not views or self.config.verification.max_fit is None:
            track.fit = None
            return
        edges, _ = self.model_edges(track.obj_id)
        R_world_obj, t_world_obj = pose
        cost = score_hypotheses(
            edges, views, R_world_obj[None], t_world_obj, self.config.verification
        )
        track.fit = float(cost.mean())

    def judge_turns(self, track: Track) -> None:
        """Which of the part's unasked near-symmetric turns (a gear's teeth) the kept views
        show, at the verified pose (the refined one when accepted), by the edges that tell them
        apart (:func:`estimator.verification.turns.judge_turns`); None without a verdict, for
        a part without such turns, or where no view shows enough of those edges."""
        track.turns = None
        pose = self.verified_pose(track)  # not turned: the judgement is forgotten above
        if pose is None:
            return
        self.model_edges(track.obj_id)
        distinct = self.distinct.get(track.obj_id)
        if distinct is None:
            return
        R_world_obj, t_world_obj = pose
        vcfg = self.config.verification
        if track.turn_scores is None:  # first judged, or restored from before the judge
            track.turn_scores = turn_judge.TurnScoreCache()
        track.turns = turn_judge.judge_turns(
            distinct,
            [v for v in track.edge_views if isinstance(v, EdgeView)],
            R_world_obj,
            t_world_obj,
            self.unasked[track.obj_id],
            vcfg.edges,
            vcfg.turns,
            vcfg.compiled,
            track.turn_scores,
        )

    def _challenge(self, track: Track, edges: ModelEdges, rcfg: RefineConfig) -> None:
        """A winner whose refined pose still costs more than ``challenge_cost`` in the kept
        views is challenged by the best hypothesis outside the refinement's reach
        (``accept_deg``) of it, refined too; the challenger leads, with its refinement, where
        its refined pose costs at least a temperature less. The two refined costs replace the
        two hypotheses' in the verdict, and the components are weighed again.

        The verification scores every hypothesis at the track's translation; where the front
        end's centres are biased by a tenth of the diameter, the wrong basin can score best
        there, and its refinement stays in it. Refined, each hypothesis is scored at its own
        translation."""
        verdict, refined, vcfg = track.verdict, track.refined, self.config.verification
        views = track.edge_views
        if vcfg.challenge_cost is None:
            return

        def refined_pose(result, R_start: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            if result.accepted:
                return result.R_world_obj, result.t_world_obj
            return R_start, track.estimate.t_world_obj

        best = verdict.best
        R_w, t_w = refined_pose(refined, verdict.R_world_obj[best])
        cost_w = float(score_hypotheses(edges, views, R_w[None], t_w, vcfg).mean())
        if cost_w <= vcfg.challenge_cost:
            return
        away = rotation_angle(np.einsum("ji,hjk->hik", R_w, verdict.R_world_obj))
        outside = np.flatnonzero(away > np.deg2rad(rcfg.accept_deg))
        if len(outside) == 0:
            return
        c = int(outside[np.argmin(verdict.cost[outside])])
        R_c = verdict.R_world_obj[c]
        t_world = track.estimate.t_world_obj
        component = track.mixture.components[int(verdict.component[c])]
        challenger = refine_pose(
            edges,
            views,
            PoseGuess(R_c, t_world),
            PosePrior(t_world, track.estimate.cov, component.cov),
            EdgeScoring.of(vcfg),
            rcfg,
        )
        R_cr, t_cr = refined_pose(challenger, R_c)
        cost_c = float(score_hypotheses(edges, views, R_cr[None], t_cr, vcfg).mean())
        if cost_c > cost_w - vcfg.temperature:
            return
        cost = verdict.cost.copy()
        cost[best], cost[c] = cost_w, cost_c
        weights = reweight(
            cost,
            verdict.component,
            track.mixture.weights,
            len(views),
            vcfg.temperature,
        )
        # the refined costs decide: no lead is kept against the views any more
        track.verdict = replace(verdict, cost=cost, weights=weights, best=c, overruled=-1)
        track.refined = challenger
