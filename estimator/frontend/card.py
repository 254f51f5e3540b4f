"""A front-end model's card: ``NAME.json`` beside ``NAME.onnx``.

The classes (obj_id and name, in output order), a hash of the catalog the model was trained
for, the image size it expects, the input scale and normalisation, the output stride, the
calibrated covariance of its centres by score, the settings its masks call for in the
verification, and how it was trained and measured (free-form, for people). Read and checked
here; :mod:`estimator.frontend.network` runs the model.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from posefuse.estimator.core.errors import PosefuseError
from posefuse.estimator.frontend.detection import ANY_PART

MEAN = (0.45, 0.45, 0.45)
STD = (0.25, 0.25, 0.25)


class ModelError(PosefuseError):
    """A front-end model that is missing, unreadable or made for another catalog."""

    def __init__(self, path: str | Path, reason: str):
        self.path = str(path)
        self.reason = reason
        super().__init__(f"{self.path}: {reason}")


# the one class of a generalist model: its detections are "a part" of no catalog (obj_id 0)
AGNOSTIC_CLASSES = ((ANY_PART, "part"),)


def catalog_hash(catalog) -> str:
    """A hash of the catalog's classes and meshes (what a model was trained on)."""
    h = hashlib.sha256()
    for obj_id, model in sorted(catalog.items()):
        h.update(f"{obj_id}:{model.name}:{model.diameter:.6f}".encode())
        h.update(np.round(np.asarray(model.mesh.vertices), 6).tobytes())
    return h.hexdigest()[:16]


def _cov_by_score(rows) -> tuple[tuple[float, float], ...]:
    """The card's ``center_cov_by_score``: ascending upper scores in (0, 1], factors >= 1."""
    out = tuple((float(upper), float(factor)) for upper, factor in rows)
    uppers = [u for u, _ in out]
    if uppers != sorted(uppers) or not all(0 < u <= 1 for u in uppers):
        raise ValueError(f"center_cov_by_score: upper scores must ascend in (0, 1], got {uppers}")
    if not all(np.isfinite(f) and f >= 1 for _, f in out):
        raise ValueError("center_cov_by_score: factors must be finite and >= 1")
    return out


def score_factor(cov_by_score: tuple[tuple[float, float], ...], score: float) -> float:
    """The covariance factor of a detection's score (1 without a calibration, or above it)."""
    for upper, factor in cov_by_score:
        if score < upper:
            return factor
    return cov_by_score[-1][1] if cov_by_score else 1.0


# the estimator's settings a model card may set for its front end: how far its masks are
# trusted (VerificationConfig), the floor of the published covariance, what the views share
# that no number of them averages out (RefineConfig, keys as ``--verification`` spells them),
# and the share of the part's diameter its centres are biased by alike in every view
# (TrackerConfig.translation_shared_frac)
CARD_VERIFICATION_KEYS = (
    "mask_weight",
    "max_fit",
    "refinement.floor_translation_frac",
    "refinement.floor_rotation_deg",
    "translation_shared_frac",
)


@dataclass(frozen=True)
class ModelCard:
    classes: tuple[tuple[int, str], ...]  # (obj_id, name) in output order
    catalog_hash: str
    image_size: tuple[int, int]  # (width, height) of the camera images it expects
    input_scale: float  # network input = image resized by this
    output_stride: int  # network output pixels per input pixel
    mean: tuple[float, float, float] = MEAN
    std: tuple[float, float, float] = STD
    cov_scale: float = 1.0
    # ((upper score, factor), ...) ascending: the centre covariance of a detection scored
    # below ``upper`` (and at least the previous one) is multiplied by ``factor``, as measured
    # on calibration sets (bench.center_calibration); empty: as voted
    cov_by_score: tuple[tuple[float, float], ...] = ()
    extra: dict | None = None  # training data, metrics: free-form, for people
    # "two_stage": boxes from this model, centers from ``two_stage["crop_model"]`` beside it
    # (see estimator.frontend.two_stage); "center_voting": one network over the whole frame
    kind: str = "center_voting"
    two_stage: dict | None = None  # TwoStageConfig fields and "crop_model"
    # a generalist: one class, "a part" (``AGNOSTIC_CLASSES``), for any catalog; trained on the
    # shape family to find parts it has never seen, and the start of every onboarding
    agnostic: bool = False
    # per class (output order) the factor of ``input_scale`` stage one finds it at: a part
    # set's large parts at half the scale, where they look the size the network was trained
    # on (sim.train_targets); stage one then runs once per distinct factor. Empty: one scale
    class_scale_factors: tuple[float, ...] = ()
    # VerificationConfig settings this model's masks call for (``CARD_VERIFICATION_KEYS``),
    # where they follow the parts less closely than the shipped model's (a part set's short
    # fine-tune: sim.onboard); None: the verification's defaults
    verification: dict | None = None

    def scale_factor_of(self, class_index: int) -> float:
        """The factor of ``input_scale`` stage one finds class ``class_index`` (0-based) at."""
        return self.class_scale_factors[class_index] if self.class_scale_factors else 1.0

    def to_json(self) -> dict:
        return {
            "classes": [{"obj_id": k, "name": n} for k, n in self.classes],
            "catalog_hash": self.catalog_hash,
            "image_size": list(self.image_size),
            "input_scale": self.input_scale,
            "output_stride": self.output_stride,
            "normalisation": {"mean": list(self.mean), "std": list(self.std)},
            "voting_cov_scale": self.cov_scale,
            **(
                {"center_cov_by_score": [list(p) for p in self.cov_by_score]}
                if self.cov_by_score
                else {}
            ),
            "kind": self.kind,
            **({"two_stage": self.two_stage} if self.two_stage else {}),
            **({"agnostic": True} if self.agnostic else {}),
            **(
                {"class_scale_factors": list(self.class_scale_factors)}
                if self.class_scale_factors
                else {}
            ),
            **({"verification": dict(self.verification)} if self.verification else {}),
            **(self.extra or {}),
        }

    @staticmethod
    def from_json(data: dict, path: Path) -> ModelCard:
        try:
            known = {
                "classes",
                "catalog_hash",
                "image_size",
                "input_scale",
                "output_stride",
                "normalisation",
                "voting_cov_scale",
                "center_cov_by_score",
                "kind",
                "two_stage",
                "agnostic",
                "class_scale_factors",
                "verification",
            }
            kind = str(data.get("kind", "center_voting"))
            if kind not in ("center_voting", "two_stage"):
                raise ValueError(f"unknown kind {kind!r}")
            two_stage = data.get("two_stage")
            if kind == "two_stage" and not isinstance(two_stage, dict):
                raise ValueError("a two_stage model needs its two_stage section")
            return ModelCard(
                classes=tuple((int(c["obj_id"]), str(c["name"])) for c in data["classes"]),
                catalog_hash=str(data["catalog_hash"]),
                image_size=(int(data["image_size"][0]), int(data["image_size"][1])),
                input_scale=float(data["input_scale"]),
                output_stride=int(data["output_stride"]),
                mean=tuple(data["normalisation"]["mean"]),
                std=tuple(data["normalisation"]["std"]),
                cov_scale=float(data.get("voting_cov_scale", 1.0)),
                cov_by_score=_cov_by_score(data.get("center_cov_by_score", [])),
                extra={k: v for k, v in data.items() if k not in known},
                kind=kind,
                two_stage=dict(two_stage) if kind == "two_stage" else None,
                agnostic=bool(data.get("agnostic", False)),
                class_scale_factors=class_scale_factors(
                    data.get("class_scale_factors", []), len(data["classes"])
                ),
                verification=card_verification(data.get("verification")),
            )
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            raise ModelError(path, f"model card is malformed ({exc!r})") from None


def card_verification(values) -> dict | None:
    """A card's ``verification``: absent (None), or a mapping of ``CARD_VERIFICATION_KEYS`` to
    finite numbers >= 0. Raises ValueError naming the field otherwise."""
    if values is None:
        return None
    if not isinstance(values, dict) or not set(values) <= set(CARD_VERIFICATION_KEYS):
        raise ValueError(f"verification must map some of {CARD_VERIFICATION_KEYS}, got {values!r}")
    out = {k: float(v) for k, v in values.items()}
    if not all(np.isfinite(v) and v >= 0 for v in out.values()):
        raise ValueError(f"verification settings must be finite and >= 0, got {values!r}")
    return out or None


def class_scale_factors(values, n_classes: int) -> tuple[float, ...]:
    """``values`` as a card's ``class_scale_factors`` for ``n_classes`` classes (empty, or one
    factor in (0, 1] per class). Raises ValueError naming the field otherwise."""
    factors = tuple(float(f) for f in values)
    if factors and len(factors) != n_classes:
        raise ValueError(f"class_scale_factors: {len(factors)} factors for {n_classes} classes")
    if not all(0.0 < f <= 1.0 for f in factors):
        raise ValueError(f"class_scale_factors: {list(factors)} must lie in (0, 1]")
    return factors


def load_card(model_path: str | Path) -> ModelCard:
    model_path = Path(model_path)
    card_path = model_path.with_suffix(".json")
    if not model_path.is_file():
        raise ModelError(model_path, "model file not found")
    if not card_path.is_file():
        raise ModelError(card_path, "model card not found (it lies beside the .onnx file)")
    try:
        data = json.loads(card_path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ModelError(card_path, f"model card is not valid JSON ({exc})") from None
    return ModelCard.from_json(data, card_path)
