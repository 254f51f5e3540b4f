"""The tracker's settings: one frozen record gathering every step's configuration."""

from __future__ import annotations

from dataclasses import dataclass, replace

from posefuse.estimator.core.bin_region import BinRegion
from posefuse.estimator.rotation.matching import RotationConfig
from posefuse.estimator.rotation.mixture import MixtureConfig
from posefuse.estimator.rotation.templates import TemplateConfig
from posefuse.estimator.translation.association import AssociationConfig
from posefuse.estimator.translation.founding import FoundingConfig
from posefuse.estimator.translation.merging import MergeConfig
from posefuse.estimator.translation.splitting import SplitConfig
from posefuse.estimator.verification.refinement import RefineConfig
from posefuse.estimator.verification.verify import VerificationConfig


@dataclass(frozen=True)
class TrackerConfig:
    association: AssociationConfig = AssociationConfig()
    confirm_views: int = 2  # views before a track is confirmed
    # a confirmed track is dropped after this many consecutive views that predicted it in view
    # without detecting it, or as many as it was seen in, whichever is more: in a pile a part
    # is hidden for a while as the camera moves, and evidence for it should outweigh its misses
    max_misses: int = 5
    max_misses_tentative: int = 2
    # a confirmed track is published as confirmed only while the views that predicted it in
    # view detected it at least this often (views seen / (seen + missed)), once it has missed
    # ``support_after`` of them: in a pile a track founded on stray detections is predicted in
    # view again and again and never seen; it falls back to tentative, and is dropped as one
    # after max_misses_tentative misses in a row (0: never)
    # off: 0.7 after 2 misses raised the precision at 8 views on the tuning sets (robi 4343:
    # 22.8 -> 33.3%, mixed 4242: 94.3 -> 100%, ADD-sym unchanged), but held out in piles (robi
    # 9200) it cost ADD-sym 47.8 -> 41.0% at 8 views for 32.7 -> 41.4% precision: parts hidden
    # by their neighbours are predicted in view and missed too (docs/frontend.md)
    min_support: float = 0.0
    support_after: int = 2
    border_margin_px: float = 2.0  # a box this close to the border is truncated
    founding: FoundingConfig = FoundingConfig()
    merging: MergeConfig = MergeConfig()
    splitting: SplitConfig = SplitConfig()
    rotation: RotationConfig = RotationConfig()
    mixture: MixtureConfig = MixtureConfig()
    templates: TemplateConfig = TemplateConfig()
    # every view's hypotheses checked in all the track's views, then the pose refined over them
    verification: VerificationConfig = VerificationConfig()
    refinement: RefineConfig = RefineConfig()
    # a view's rotation is measured once the depth is known to this relative std; earlier
    # views of the track wait (their images are kept for up to max_pending_views frames)
    rotation_max_depth_rel_std: float = 0.05
    max_pending_views: int = 8
    # a track keeps this many views for its translation; older ones are folded into its prior
    max_track_views: int = 30
    # a track's translation covariance is widened by the scatter of its centres about the
    # solution when they scatter more than their covariances say (the a posteriori variance
    # factor, ``translation.gaussian.variance_factor``, shrunk towards 1 by this many prior
    # degrees of freedom); None: the inverse information alone. 0 chosen on the tuning sets
    # (robi 4343, 4444; mixed 4242, 4445): piles' mean translation NEES at 8 views 199 -> 99 and
    # 515 -> 193, precision 34.1 -> 37.6 and 50.5 -> 52.8%, ADD-sym not lower anywhere; 4 gave
    # less of each (docs/lab/2026-12-05-translation-variance-factor.md)
    translation_variance_dof: float | None = 0.0
    # the error a track's views share, as a share of the part's diameter (std per axis), added
    # to its translation covariance: a learned front end's centres are biased alike in
    # neighbouring views, so more views do not average it out and their scatter does not show
    # it (on a part set's tuning bins the translation NEES grew 2.1 / 5.8 / 10.9 at 2 / 4 / 8
    # views). A property of the front end: its card gives it (``translation_shared_frac`` in
    # ModelCard.verification); 0, the default, for centres whose errors are the views' own
    # (docs/lab/2026-12-07-translation-error-the-views-share.md)
    translation_shared_frac: float = 0.0
    # verification and refinement in the update (False), or later, track by track, when
    # asked (MultiViewEstimator.check_next): the daemon runs them between frames, so a frame
    # never waits for them; checked after every update, the estimates are the same
    deferred_verification: bool = False
    # the bin the parts lie in, where the cell knows it (world frame; None: not known). A
    # confirmed track whose centre lies outside it by more than ``bin_margin_frac`` of the
    # part's diameter is published tentative: in a pile, detections of different parts meet
    # under the floor (estimator/core/bin_region.py). The track itself lives on as before:
    # refusing such foundings, or dropping such tracks, freed detections that founded other
    # wrong tracks and lost parts held out (docs/lab/2026-12-08-bin-floor-ghosts.md)
    bin: BinRegion | None = None
    # an estimate right to 0.1 d of a centre inside the bin lies at most 0.1 d outside it
    bin_margin_frac: float = 0.25

    def __post_init__(self) -> None:
        if self.bin is not None and not isinstance(self.bin, BinRegion):
            raise ValueError(f"bin must be a BinRegion or None, got {type(self.bin).__name__}")
        if not self.bin_margin_frac >= 0:
            raise ValueError(f"bin_margin_frac must be at least 0, got {self.bin_margin_frac}")
        if self.confirm_views < 1 or self.max_misses < 1 or self.max_misses_tentative < 1:
            raise ValueError(f"invalid tracker config: {self}")
        if self.translation_variance_dof is not None and not self.translation_variance_dof >= 0:
            raise ValueError(
                "translation_variance_dof must be None or at least 0, got "
                f"{self.translation_variance_dof}"
            )
        if not self.translation_shared_frac >= 0:
            raise ValueError(
                f"translation_shared_frac must be at least 0, got {self.translation_shared_frac}"
            )
        if not 0.0 <= self.min_support <= 1.0 or self.support_after < 1:
            raise ValueError(
                f"min_support must be in [0, 1] and support_after >= 1, got {self.min_support} "
                f"and {self.support_after}"
            )

    @classmethod
    def with_verification(cls, enabled: bool, deferred: bool = False) -> TrackerConfig:
        """The defaults, with the verification across views on or off, in the update or
        deferred (``deferred_verification``)."""
        return cls(verification=VerificationConfig(enabled=enabled), deferred_verification=deferred)

    def with_card(self, card_verification: dict | None) -> TrackerConfig:
        """These settings with the verification settings a model card gives for its front
        end (``ModelCard.verification``: ``mask_weight``, how far its mask outlines are
        trusted, ``max_fit``, and ``refinement.KEY`` for the published covariance's floor);
        None: unchanged."""
        return self.with_verification_settings(card_verification or {})

    def with_verification_settings(self, settings: dict) -> TrackerConfig:
        """These settings with VerificationConfig fields replaced by ``settings`` (field
        name -> value), ``edges.KEY`` and ``turns.KEY`` for the EdgeConfig and TurnJudgeConfig
        it holds, ``refinement.KEY`` for the RefineConfig, and ``translation_shared_frac``
        (this config's own). Raises ValueError naming the group of a setting its config
        refuses."""
        settings = dict(settings)
        if "translation_shared_frac" in settings:
            shared = settings.pop("translation_shared_frac")
            return replace(self, translation_shared_frac=shared).with_verification_settings(
                settings
            )
        groups: dict[str, dict] = {"": {}, "edges": {}, "turns": {}, "refinement": {}}
        for key, value in settings.items():
            group, dot, name = key.partition(".")
            if dot and group in groups:
                groups[group][name] = value
            else:
                groups[""][key] = value
        config = self
        if groups["refinement"]:
            try:
                config = replace(
                    config, refinement=replace(config.refinement, **groups["refinement"])
                )
            except ValueError as err:
                raise ValueError(f"refinement.*: {err}") from None
        verification = replace(config.verification, **groups[""])
        for name in ("edges", "turns"):  # the settings the verification's config holds
            if groups[name]:
                try:
                    inner = replace(getattr(verification, name), **groups[name])
                except ValueError as err:
                    raise ValueError(f"{name}.*: {err}") from None
                verification = replace(verification, **{name: inner})
        return replace(config, verification=verification)
