"""Training the two-stage front end on synthetic renders (CPU, torch), export to ONNX.

``posefuse train --catalog DIR --out models/NAME.onnx`` renders bin scenes of the catalog once
(:mod:`sim.train_data`: scene seeds from ``TRAIN_SEED_BASE`` on, disjoint from every test and
tuning seed; half of them robi piles, the rest mixed bins), then trains both stages together,
one optimizer step of each per iteration (:mod:`sim.train_targets` draws the batches):

- stage one, ``BoxDetectorNet``: focal loss on the class heatmaps, L1 on box size and offset;
- stage two, ``CropVotingNet``: binary cross-entropy on the object label, smooth L1 on the
  unit vectors of the object's pixels and, with ``vote_loss`` > 0, the proxy voting loss of
  Yu et al. (CVPR 2020): smooth L1 on the distance from the center to the line each pixel votes
  along. The unit-vector loss weighs a pixel's angle alike near and far from the center; a vote
  lands off by that angle times the distance, so the far pixels make the heavy tail of the
  voted centers, and this loss weighs them by it.

Training is a resumable job. The schedule (warm-up, then a cosine over ``iterations`` steps)
and the batches depend on the step number alone, and the checkpoint (``--checkpoint``,
written every ``checkpoint_minutes`` and at the end) keeps the weights, the optimizer state
(bfloat16), the step, the cumulative CPU seconds and the learning curve. ``--resume CKPT``
goes on from there; a run ends at its step count or its time budget, whichever comes first.
At each checkpoint both stages are exported and, given tuning datasets, scored there with the
front end's own code (:class:`estimator.frontend.network.NetworkFrontend`): the learning curve.
At the end the voting covariance is calibrated on held-out renders (mean NEES 2).
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment
from tqdm import tqdm

from posefuse.estimator.core.objects import load_catalog
from posefuse.estimator.frontend.network import (
    AGNOSTIC_CLASSES,
    MEAN,
    STD,
    ModelCard,
    NetworkFrontend,
    catalog_hash,
    class_scale_factors,
)
from posefuse.evaluation.center_calibration import DEFAULT_EDGES, factors_by_score, nees_table
from posefuse.evaluation.dataset import load_dataset
from posefuse.evaluation.frontend_metrics import score_frontend
from posefuse.sim.backgrounds import Backgrounds
from posefuse.sim.photometric import Photometric
from posefuse.sim.scenes import REALSENSE_1280x720
from posefuse.sim.train_data import (
    RenderSpec,
    TrainingSet,
    profile_of,
    render_scene,
    render_training_set,
)
from posefuse.sim.train_targets import (
    CROP_STRIDE,
    DET_STRIDE,
    MIN_TARGET_VISIB,
    BatchConfig,
    crop_batch,
    detector_batch,
)

TRAIN_SEED_BASE = 7_000_000  # scene seeds of training data; test sets use small seeds
VAL_SEED_BASE = TRAIN_SEED_BASE + 1
INPUT_SCALE = 0.5
CHECKPOINT_VERSION = 1

__all__ = ["TRAIN_SEED_BASE", "TrainConfig", "profile_of", "render_scene", "train"]


# the detector thresholds a run with TrainConfig.tune_min_score chooses among
MIN_SCORE_CANDIDATES = (0.05, 0.08, 0.12, 0.18, 0.25, 0.3)
CLOCK_WARMUP = 0.05  # of the time to the deadline, with TrainConfig.clock_schedule
THREAD_CHECK_STEPS = 10  # steps between two looks at the cores other processes leave


@dataclass(frozen=True)
class TrainConfig:
    n_scenes: int = 200
    views_per_scene: int = 4
    val_scenes: int = 8
    minutes: float = 40.0  # this run's wall-clock budget
    max_iterations: int = 40_000  # the schedule's length, over all runs of a checkpoint
    batch: int = 16  # detector crops per step
    crop_batch: int = 48  # stage-two crops per step
    crop_size: int = 96
    lr: float = 2e-3
    warmup: int = 500
    width: int = 16
    # stage one's input: the 1280x720 view resized by this. None: INPUT_SCALE, or with ``init``
    # the checkpoint's; a scale given with ``init`` fine-tunes the same convolutions at it
    input_scale: float | None = None
    crop_width: int | None = None  # stage two's width (None: ``width``)
    crop_box_channel: bool = False  # stage two gets the box as a fourth input channel
    dihedral: bool = False  # flips upside down and transposes besides mirrors (train_targets)
    seed: int = 0
    workers: int = 2
    robi_fraction: float = 0.5
    # one class, "a part", for every object of the catalog: the generalist front end of the
    # shape family (``posefuse catalog --family``), which onboarding starts from
    agnostic: bool = False
    materials: str = "catalog"  # or "random": see sim.train_data.RenderSpec
    # a real camera's effects drawn per training sample (sim.photometric); kept in the checkpoint
    photometric: bool = False
    # the share of training samples whose background (all that is no part) is replaced by
    # procedural clutter (sim.backgrounds); 0: the bins as rendered. Kept in the checkpoint
    backgrounds: float = 0.0
    # the share of training scenes composed from parts rendered alone onto clutter
    # (sim.composite: many times faster to make than a rendered scene); 0: all rendered
    composite: float = 0.0
    # the learning rate by the clock: warm-up over the first CLOCK_WARMUP of the time to the
    # deadline, then the cosine over the rest, whatever the number of steps the time holds (a
    # budget's run ends annealed; by steps, a short run would end near the peak). Onboarding's
    # budget uses it; a run by steps or a resumable job keeps the schedule by steps
    clock_schedule: bool = False
    # the detector's threshold chosen on the calibration renders (tune_min_score) and written
    # into the card; False: the default TwoStageConfig.min_score. Onboarding uses it
    tune_min_score: bool = False
    # both stages' backbones keep the weights they start with (``init``): a step trains the
    # necks and heads only, and no gradient flows back through the backbones
    frozen_backbones: bool = False
    # per class (catalog order) the factor of stage one's input scale it is detected at: a part
    # set's large parts at half the scale, where they look the size the network knows
    # (sim.train_targets, SNIP's scale normalisation); empty: every class at input_scale
    class_scale_factors: tuple[float, ...] = ()
    # class-balanced sampling: a class's parts are drawn (detector crops' centre parts,
    # stage-two crops) in inverse proportion to its share of the training set's parts
    class_balanced: bool = False
    deadline: float | None = None  # wall-clock time (time.time()) the training loop must end by
    data_dir: str | None = None  # where rendered sets live (default ~/.cache/posefuse/train)
    checkpoint: str | None = None  # where the resumable checkpoint goes
    checkpoint_minutes: float = 30.0
    tune: tuple[str, ...] = ()  # BOP datasets scored at each checkpoint (the learning curve)
    # bfloat16 autocast with channels_last; None: where the CPU has bfloat16 instructions
    # (native_bf16: faster than float32 with them, about 9x slower without)
    bf16: bool | None = None
    # torch threads of the loop; None: the cores other processes leave free, measured every
    # THREAD_CHECK_STEPS steps (sim.core_share)
    threads: int | None = None
    resume: str | None = None
    init: str | None = None  # a checkpoint of another catalog to fine-tune from
    run_steps: int | None = None  # this run stops after this many steps (the schedule goes on)
    # warm restarts appended by ``--extend``: (first step, last step + 1, peak learning rate)
    restarts: tuple[tuple[int, int, float], ...] = ()
    extend: tuple[int, float] | None = None  # with ``resume``: (steps, peak lr) of one more restart
    # weight of the proxy voting loss (0: off); not part of the stream, so a resume may add it
    vote_loss: float | None = None  # None: a resume's checkpoint's, else 0
    extra: dict = field(default_factory=dict)

    @property
    def stage_two_width(self) -> int:
        return self.crop_width or self.width

    @property
    def total_steps(self) -> int:
        """The schedule's end: the first cosine, then every restart after it."""
        return max([self.max_iterations] + [end for _, end, _ in self.restarts])

    def extended(self, steps: int, peak_lr: float) -> TrainConfig:
        """This schedule with one more warm restart of ``steps`` steps after its end."""
        if steps <= 0 or peak_lr <= 0:
            raise ValueError(f"extend: steps ({steps}) and peak lr ({peak_lr}) must be positive")
        start = self.total_steps
        return dataclasses.replace(
            self, restarts=(*self.restarts, (start, start + int(steps), float(peak_lr)))
        )

    def schedule(self, step: int) -> float:
        """Learning rate of ``step``: linear warm-up, then a cosine to 2% of ``lr``; within a
        restart, the same shape from its own peak over its own steps."""
        start, end, peak = 0, self.max_iterations, self.lr
        for r_start, r_end, r_peak in self.restarts:
            if step >= r_start:
                start, end, peak = r_start, r_end, r_peak
        local = step - start
        if local < self.warmup:
            return peak * (local + 1) / self.warmup
        frac = min((local - self.warmup) / max(end - start - self.warmup, 1), 1.0)
        return peak * (0.02 + 0.98 * 0.5 * (1 + np.cos(np.pi * frac)))

    def clock_schedule_at(self, frac: float) -> float:
        """Learning rate at a fraction ``frac`` in [0, 1] of the training's time: linear warm-up
        over the first CLOCK_WARMUP, then the cosine of :meth:`schedule` to 2% of ``lr``."""
        frac = float(np.clip(frac, 0.0, 1.0))
        if frac < CLOCK_WARMUP:
            return self.lr * max(frac / CLOCK_WARMUP, 0.01)
        rest = (frac - CLOCK_WARMUP) / (1.0 - CLOCK_WARMUP)
        return self.lr * (0.02 + 0.98 * 0.5 * (1 + np.cos(np.pi * rest)))


# the CPU flags of bfloat16 arithmetic (Linux's /proc/cpuinfo names)
BF16_CPU_FLAGS = frozenset({"avx512_bf16", "amx_bf16"})


def native_bf16(cpuinfo: str | None = None) -> bool:
    """Whether this CPU computes in bfloat16 natively, read from ``cpuinfo`` (the text of
    ``/proc/cpuinfo``; None reads it). Without those instructions torch emulates bfloat16 and
    autocast is slower than float32 (a training step about nine times slower on an AVX2 CPU);
    with them it was 1.5 times faster. Where the file cannot be read, False: float32 is
    never the slow choice by much."""
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:
            return False
    for line in cpuinfo.splitlines():
        key, _, value = line.partition(":")
        if key.strip() == "flags":
            return not BF16_CPU_FLAGS.isdisjoint(value.split())
    return False


# what a resumed run must share with the run that wrote the checkpoint
_STREAM_FIELDS = (
    "n_scenes",
    "views_per_scene",
    "max_iterations",
    "batch",
    "crop_batch",
    "crop_size",
    "lr",
    "warmup",
    "width",
    "input_scale",
    "crop_width",
    "crop_box_channel",
    "dihedral",
    "seed",
    "robi_fraction",
    "restarts",
    "agnostic",
    "materials",
    "photometric",
    "backgrounds",
    "composite",
    "frozen_backbones",
    "class_scale_factors",
    "class_balanced",
)


# stream fields a checkpoint older than them lacks: read with the value they had before
_OPTIONAL_STREAM_FIELDS = (
    "restarts",
    "crop_box_channel",
    "dihedral",
    "crop_width",
    "photometric",
    "input_scale",
    "backgrounds",
    "composite",
    "frozen_backbones",
    "class_scale_factors",
    "class_balanced",
)


def _default_data_dir() -> Path:
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "posefuse" / "train"


class _Nets:
    """Both stages, their optimizer, and the losses of one step."""

    def __init__(self, n_classes: int, config: TrainConfig):
        import torch

        from posefuse.sim.net import BoxDetectorNet, CropVotingNet

        torch.manual_seed(config.seed)
        self.torch = torch
        self.config = config
        self.n_classes = n_classes
        self.det = BoxDetectorNet(n_classes, config.width)
        self.crop = CropVotingNet(config.stage_two_width, config.crop_box_channel)
        if config.bf16:
            self.det = self.det.to(memory_format=torch.channels_last)
            self.crop = self.crop.to(memory_format=torch.channels_last)
        if config.frozen_backbones:
            for p in [*self.det.backbone.parameters(), *self.crop.backbone.parameters()]:
                p.requires_grad_(False)
        params = [p for p in [*self.det.parameters(), *self.crop.parameters()] if p.requires_grad]
        self.opt = torch.optim.AdamW(params, lr=config.lr, weight_decay=1e-4)
        self.mean = torch.tensor(MEAN).view(1, 3, 1, 1)
        self.std = torch.tensor(STD).view(1, 3, 1, 1)

    def _input(self, images: np.ndarray, gen) -> object:
        torch = self.torch
        x = torch.from_numpy(images).permute(0, 3, 1, 2).float().div_(255.0)
        x = (x - self.mean) / self.std
        b = x.shape[0]
        gain = torch.empty(b, 1, 1, 1).uniform_(0.7, 1.3, generator=gen)
        bias = torch.empty(b, 1, 1, 1).uniform_(-0.3, 0.3, generator=gen)
        tint = torch.empty(b, 3, 1, 1).uniform_(-0.08, 0.08, generator=gen)
        noise = torch.randn(x.shape, generator=gen) * torch.empty(b, 1, 1, 1).uniform_(
            0.0, 0.08, generator=gen
        )
        x = x * gain + bias + tint + noise
        if self.config.bf16:
            x = x.contiguous(memory_format=torch.channels_last)
        return x

    def step(self, det_batch, crop_batch_, lr: float, gen) -> dict[str, float]:
        torch = self.torch
        F = torch.nn.functional
        for g in self.opt.param_groups:
            g["lr"] = lr
        images, heat, weight, box, box_mask = det_batch
        crops, box_masks, label, vec = crop_batch_
        heat, weight = torch.from_numpy(heat), torch.from_numpy(weight)
        box, box_mask = torch.from_numpy(box), torch.from_numpy(box_mask).unsqueeze(1)
        label, vec = torch.from_numpy(label).unsqueeze(1), torch.from_numpy(vec)
        x_det, x_crop = self._input(images, gen), self._input(crops, gen)
        if self.config.crop_box_channel:
            x_crop = torch.cat([x_crop, torch.from_numpy(box_masks).float().unsqueeze(1)], 1)
            if self.config.bf16:
                x_crop = x_crop.contiguous(memory_format=torch.channels_last)
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=self.config.bf16):
            logits, box_out = self.det.forward_logits(x_det)
            crop_out = self.crop(x_crop)
        logits, box_out, crop_out = logits.float(), box_out.float(), crop_out.float()
        # CenterNet's focal loss on the heatmaps
        p = torch.sigmoid(logits).clamp(1e-4, 1 - 1e-4)
        pos = (heat >= 1.0).float()
        n_pos = pos.sum().clamp(min=1.0)
        pos_loss = -(torch.log(p) * (1 - p) ** 2 * pos).sum()
        neg_loss = -(torch.log(1 - p) * p**2 * (1 - heat) ** 4 * (1 - pos) * weight).sum()
        loss_heat = (pos_loss + neg_loss) / n_pos
        loss_box = (F.l1_loss(box_out, box, reduction="none") * box_mask).sum() / n_pos
        # stage two: object label and the unit vectors on its pixels
        loss_label = F.binary_cross_entropy_with_logits(crop_out[:, :1], label)
        loss_vec = (F.smooth_l1_loss(crop_out[:, 1:], vec, reduction="none") * label).sum()
        loss_vec = loss_vec / label.sum().clamp(min=1.0)
        loss = loss_heat + loss_box + loss_label + 2.0 * loss_vec
        if self.config.vote_loss:
            loss_vote = proxy_voting_loss(crop_out[:, 1:], label, vec)
            loss = loss + self.config.vote_loss * loss_vote
        else:  # logged all the same: the curve then compares runs with it and without
            with torch.no_grad():
                loss_vote = proxy_voting_loss(crop_out[:, 1:].detach(), label, vec)
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        return {
            "heat": float(loss_heat.detach()),
            "box": float(loss_box.detach()),
            "label": float(loss_label.detach()),
            "vec": float(loss_vec.detach()),
            "vote": float(loss_vote.detach()),
        }

    def train_mode(self) -> None:
        """Both stages in training mode, but frozen backbones (``frozen_backbones``), whose
        batch norms keep their statistics: their features stay what the initial weights made."""
        self.det.train()
        self.crop.train()
        if self.config.frozen_backbones:
            self.det.backbone.eval()
            self.crop.backbone.eval()

    def state(self) -> dict:
        """Weights and the optimizer's moments in float32: about 6 MB for both stages, small
        enough to keep exact (a resume then continues bit for bit)."""
        return {
            "det": self.det.state_dict(),
            "crop": self.crop.state_dict(),
            "opt": self.opt.state_dict(),
        }

    def load(self, state: dict) -> None:
        self.det.load_state_dict(state["det"])
        self.crop.load_state_dict(state["crop"])
        self.opt.load_state_dict(state["opt"])

    def init_from(self, state: dict) -> list[str]:
        """Start from another checkpoint's weights: everything but the class heatmaps (the one
        class-specific head) when the class count differs; stage two's first layer widened
        with zeros when this one adds the box channel, and stage two widened by an integer
        factor (``sim.net.widen_state``: it begins computing what the narrower one did, up to
        1% noise that lets the copies of a channel part); returns the layers left fresh."""
        from posefuse.sim.net import widen_state

        torch = self.torch
        det = self.det.state_dict()
        fresh = []
        for k, v in state["det"].items():
            if k in det and det[k].shape == v.shape:
                det[k] = v
            elif k.startswith("heatmap.") and k in det and v.shape[0] == 1:
                # a generalist's one "part" heatmap: every new class starts as "a part" and
                # learns from there which part it is
                det[k] = v.expand_as(det[k]).clone()
                fresh.append(f"{k} (every class from the generalist's one)")
            else:
                fresh.append(k)
        self.det.load_state_dict(det)
        crop = self.crop.state_dict()
        old = dict(state["crop"])
        for k, v in old.items():
            if v.ndim == 4 and v.shape[1] == 3 and crop[k].shape[1] == 4:
                # a stage two without the box channel: its weights for the new input start at
                # zero, so the network begins as the one it comes from
                old[k] = torch.cat([v, torch.zeros_like(v[:, :1])], 1)
                fresh.append(f"crop.{k} (box channel)")
        widened = [k for k, v in old.items() if k in crop and crop[k].shape != v.shape]
        loaded, left = widen_state(old, crop, noise=0.01, seed=self.config.seed)
        fresh += [f"crop.{k}" for k in left]
        if widened:
            fresh.append(
                f"stage two widened to width {self.config.stage_two_width} ({len(widened)} tensors)"
            )
        self.crop.load_state_dict(loaded)
        return fresh

    def export(self, model_path: Path, card: ModelCard) -> None:
        """Both stages as ONNX (opset 17) and the card beside the detector."""
        torch = self.torch
        crop_path = model_path.with_name(model_path.stem + "_crop.onnx")
        det = _float_copy(self.det)
        crop = _float_copy(self.crop)
        w, h = card.image_size
        sw, sh = round(w * card.input_scale), round(h * card.input_scale)
        torch.onnx.export(
            det,
            (torch.zeros(1, 3, sh + (-sh % 16), sw + (-sw % 16)),),
            str(model_path),
            dynamo=False,
            opset_version=17,
            input_names=["image"],
            output_names=["out"],
            dynamic_axes={"image": {2: "h", 3: "w"}, "out": {2: "h4", 3: "w4"}},
        )
        S = self.config.crop_size
        torch.onnx.export(
            crop,
            (torch.zeros(2, 4 if self.config.crop_box_channel else 3, S, S),),
            str(crop_path),
            dynamo=False,
            opset_version=17,
            input_names=["crops"],
            output_names=["out"],
            dynamic_axes={"crops": {0: "n"}, "out": {0: "n"}},
        )
        model_path.with_suffix(".json").write_text(json.dumps(card.to_json(), indent=2) + "\n")


def _cell_grid(g: int, dtype):
    """(x, y) of every output cell, each (g, g) torch."""
    import torch

    ys, xs = torch.meshgrid(
        torch.arange(g, dtype=dtype), torch.arange(g, dtype=dtype), indexing="ij"
    )
    return xs, ys


def target_centers(label, vec):
    """Where each crop's target vectors meet, in output cells (x, y): the least-squares point
    closest to every labelled cell's line; exact for rendered targets, which all point at
    the projected model origin.

    Args:
        label: (B, 1, g, g) torch float {0, 1}; vec: (B, 2, g, g) unit vectors (0 off the part).
    Returns:
        (B, 2) torch float; a crop without labelled cells gets the crop's center.
    """
    import torch

    xs, ys = _cell_grid(label.shape[-1], vec.dtype)
    tx, ty, w = vec[:, 0], vec[:, 1], label[:, 0]
    # each line's normal projector (I - t t^T), summed over the labelled cells
    a11, a12, a22 = (
        (w * (1 - tx * tx)).sum((1, 2)),
        (w * -tx * ty).sum((1, 2)),
        (w * (1 - ty * ty)).sum((1, 2)),
    )
    b1 = (w * ((1 - tx * tx) * xs - tx * ty * ys)).sum((1, 2))
    b2 = (w * (-tx * ty * xs + (1 - ty * ty) * ys)).sum((1, 2))
    ridge = 1e-6 * (w.sum((1, 2)) + 1.0)
    half = (label.shape[-1] - 1) / 2
    b1, b2 = b1 + ridge * half, b2 + ridge * half  # ridge pulls an empty crop to its center
    a11, a22 = a11 + ridge, a22 + ridge
    det = a11 * a22 - a12 * a12
    return torch.stack([(a22 * b1 - a12 * b2) / det, (a11 * b2 - a12 * b1) / det], 1)


def proxy_voting_loss(pred, label, vec):
    """The proxy voting loss (Yu et al., CVPR 2020) of stage two's vector field, in cells.

    Args:
        pred: (B, 2, g, g) predicted vectors (any length); label, vec: the targets, (B, 1, g, g)
            and (B, 2, g, g).
    Returns:
        scalar: smooth L1 (beta one cell) of each labelled cell's distance from the center to
        the line through the cell along its predicted direction, averaged over labelled cells.
    """
    import torch
    import torch.nn.functional as F

    center = target_centers(label, vec).detach()
    xs, ys = _cell_grid(label.shape[-1], pred.dtype)
    dx = center[:, 0, None, None] - xs
    dy = center[:, 1, None, None] - ys
    unit = pred / pred.norm(dim=1, keepdim=True).clamp(min=1e-6)
    dist = (dx * unit[:, 1] - dy * unit[:, 0]).abs()
    w = label[:, 0]
    return (F.smooth_l1_loss(dist, torch.zeros_like(dist), reduction="none") * w).sum() / (
        w.sum().clamp(min=1.0)
    )


def _lineage_cpu(record: dict | None) -> float:
    """CPU seconds of the checkpoints a fine-tune started from (``init_from``, recursively)."""
    if not record:
        return 0.0
    return float(record.get("cpu_seconds") or 0.0) + _lineage_cpu(record.get("init_from"))


def _float_copy(model):
    import copy

    import torch

    m = copy.deepcopy(model).to(memory_format=torch.contiguous_format).float().eval()
    return m


def class_weights(classes: np.ndarray, n_classes: int) -> tuple[float, ...]:
    """(C,) each class's sampling weight, the inverse of its share of ``classes`` (the class
    column, 1..C, of the parts that may be drawn); a class with no part weighs 0."""
    counts = np.bincount(np.asarray(classes, int), minlength=n_classes + 1)[1:]
    share = counts / max(counts.sum(), 1)
    return tuple(float(1.0 / s) if s > 0 else 0.0 for s in share)


def _card(
    catalog,
    config: TrainConfig,
    model_path: Path,
    cov_scale: float,
    extra: dict,
    min_score: float | None = None,
    cov_by_score: list | None = None,
) -> ModelCard:
    two_stage = {
        "crop_model": model_path.stem + "_crop.onnx",
        "det_stride": DET_STRIDE,
        "crop_size": config.crop_size,
        "crop_stride": CROP_STRIDE,
        "box_scale": BatchConfig().box_scale,
        "box_channel": config.crop_box_channel,
    }
    if min_score is not None:
        two_stage["min_score"] = min_score
    return ModelCard(
        classes=AGNOSTIC_CLASSES
        if config.agnostic
        else tuple((k, m.name) for k, m in sorted(catalog.items())),
        agnostic=config.agnostic,
        catalog_hash=catalog_hash(catalog),
        image_size=(REALSENSE_1280x720.width, REALSENSE_1280x720.height),
        input_scale=config.input_scale,
        output_stride=DET_STRIDE,
        cov_scale=cov_scale,
        cov_by_score=tuple((float(u), float(f)) for u, f in cov_by_score or ()),
        kind="two_stage",
        two_stage=two_stage,
        extra=extra,
        class_scale_factors=tuple(config.class_scale_factors),
    )


def score_tuning(model_path: Path, datasets: tuple[str, ...], seed: int = 0) -> dict:
    """Recall, precision, median center error and mean NEES of the exported model on each
    tuning dataset (all views), with the front end's own code."""
    out = {}
    for root in datasets:
        ds = load_dataset(root)
        fe = NetworkFrontend(model_path, ds.catalog, seed=seed)

        def detect(view, fe=fe, ds=ds):
            image = ds.scene(view.scene_id).load_rgb(view.im_id)
            return fe.detect(image)

        s = score_frontend(ds, detect, list(ds.views()), any_class=fe.card.agnostic)
        out[Path(root).name] = {
            "recall": s.recall,
            "precision": s.precision,
            "median_center_error_px": s.median_center_error_px,
            "mean_nees": s.mean_nees,
            "instances": s.n_instances,
        }
    return out


def _val_matches(fe, val: TrainingSet, catalog) -> tuple[int, int, int, list, list, list]:
    """The front end ``fe`` on every view of the calibration renders ``val``: (parts more than
    75% visible, those a detection of their class lies within 15 px of (one to one), detections,
    the matched centres' errors in pixels, their 2D NEES and their detections' scores)."""
    obj_of_class = {k + 1: obj_id for k, obj_id in enumerate(sorted(catalog))}
    if fe.card.agnostic:  # every row's class is "a part", as are the detections
        obj_of_class = dict.fromkeys(obj_of_class, AGNOSTIC_CLASSES[0][0])
    nees, errors, scores = [], [], []
    n_true = n_found = n_dets = 0
    rows_of = val.view_instances()
    for i in range(val.n_views):
        dets = fe.detect(np.asarray(val.full_rgb[i]))
        n_dets += len(dets)
        rows = rows_of[i][rows_of[i][:, 9] > 0.75]
        n_true += len(rows)
        cost = np.full((len(dets), len(rows)), 1e9)
        for a, d in enumerate(dets):
            for b, r in enumerate(rows):
                if obj_of_class[int(r[2])] == d.obj_id:
                    dist = float(np.linalg.norm(d.center_uv - r[3:5]))
                    if dist <= 15.0:
                        cost[a, b] = dist
        if cost.size:
            for a, b in zip(*linear_sum_assignment(cost), strict=True):
                if cost[a, b] < 1e9:
                    n_found += 1
                    e = dets[a].center_uv - rows[b][3:5]
                    errors.append(float(np.linalg.norm(e)))
                    nees.append(float(e @ np.linalg.solve(dets[a].center_cov, e)))
                    scores.append(float(dets[a].score))
    return n_true, n_found, n_dets, errors, nees, scores


def tune_min_score(
    model_path: Path, val: TrainingSet, catalog, seed: int = 0
) -> tuple[float, list]:
    """The detector's peak threshold (``TwoStageConfig.min_score``) of the highest F1 of recall
    and precision on the calibration renders ``val``, of MIN_SCORE_CANDIDATES (ties: the higher),
    and the table [(threshold, recall, precision)]. A short fine-tune's new class heatmaps peak
    low: at the default 0.3 one found a fifth of the parts its heatmaps were on."""
    import dataclasses

    fe = NetworkFrontend(model_path, catalog, seed=seed)
    table = []
    for t in MIN_SCORE_CANDIDATES:
        fe.two_stage = dataclasses.replace(fe.two_stage, min_score=t)
        n_true, n_found, n_dets, *_ = _val_matches(fe, val, catalog)
        table.append((t, n_found / max(n_true, 1), n_found / max(n_dets, 1)))

    def f1(row):
        _, r, p = row
        return 2 * r * p / (r + p) if r + p > 0 else 0.0

    best = max(table, key=lambda row: (round(f1(row), 6), row[0]))
    return float(best[0]), table


def calibrate(model_path: Path, val: TrainingSet, catalog, seed: int = 0) -> tuple[float, dict]:
    """The covariance scale that makes the mean NEES of matched centers 2 on held-out renders
    (the model's card read with scale 1), and validation figures. ``catalog`` is the one being
    trained: a rendered set is shared by every copy of the same catalog (its folder is named by
    the catalog's hash), so the path it was rendered from may be gone."""
    card_path = model_path.with_suffix(".json")
    data = json.loads(card_path.read_text())
    data["voting_cov_scale"] = 1.0
    card_path.write_text(json.dumps(data, indent=2) + "\n")
    fe = NetworkFrontend(model_path, catalog, seed=seed)
    n_true, n_found, _, errors, nees, _ = _val_matches(fe, val, catalog)
    scale = float(np.mean(nees) / 2.0) if nees else 1.0
    return scale, {
        "views": int(val.n_views),
        "visible_instances": int(n_true),
        "found": int(n_found),
        "median_center_error_px": float(np.median(errors)) if errors else None,
        "mean_nees_before_calibration": float(np.mean(nees)) if nees else None,
    }


def calibrate_by_score(
    model_path: Path, val: TrainingSet, catalog, cov_scale: float, seed: int = 0
) -> tuple[list, list]:
    """The card's ``center_cov_by_score`` fitted on the calibration renders ``val``
    (:func:`posefuse.evaluation.center_calibration.factors_by_score`), the model's card read
    with ``cov_scale``, and the table it was fitted from. A short fine-tune's centres are far
    less certain at a low score than at a high one, as the shipped model's are."""
    card_path = model_path.with_suffix(".json")
    data = json.loads(card_path.read_text())
    data["voting_cov_scale"] = cov_scale
    data.pop("center_cov_by_score", None)
    card_path.write_text(json.dumps(data, indent=2) + "\n")
    fe = NetworkFrontend(model_path, catalog, seed=seed)
    *_, nees, scores = _val_matches(fe, val, catalog)
    factors = factors_by_score(scores, nees)
    rows = nees_table(scores, nees, DEFAULT_EDGES)
    return factors, [
        {k: (round(v, 3) if isinstance(v, float) else v) for k, v in r.items()} for r in rows
    ]


def _finish_seconds(nets, model_path: Path, catalog, config: TrainConfig, val, after) -> dict:
    """What follows a budgeted run's loop, timed on the initial model: the export, the passes
    of the front end over the calibration renders (one for :func:`calibrate`; with
    ``tune_min_score`` one per threshold and one for :func:`calibrate_by_score`), each timed
    as one at the lowest threshold, and ``after(model_path)``. Seconds by name."""
    t0 = time.perf_counter()
    nets.det.eval(), nets.crop.eval()
    nets.export(model_path, _card(catalog, config, model_path, 1.0, {}))
    nets.train_mode()
    kept = {"export": time.perf_counter() - t0}
    t0 = time.perf_counter()
    fe = NetworkFrontend(model_path, catalog, seed=config.seed)
    # at the lowest threshold: the most stage-two crops a pass can have
    fe.two_stage = dataclasses.replace(fe.two_stage, min_score=MIN_SCORE_CANDIDATES[0])
    _val_matches(fe, val, catalog)
    passes = 1 + (len(MIN_SCORE_CANDIDATES) + 1 if config.tune_min_score else 0)
    kept["calibration"] = passes * (time.perf_counter() - t0)
    if after is not None:
        kept["validation"] = float(after(model_path))
    return kept


def train(catalog_dir: str | Path, model_path: str | Path, config: TrainConfig, after=None) -> dict:
    """Render (or reuse), train (or resume), export; returns the model card's dict.

    A run with a ``config.deadline`` (onboarding's budget) ends its loop early by what follows
    it, measured here before the loop on the initial model, exported to ``model_path``: the
    export, the calibration passes over the calibration renders, and ``after(model_path)``,
    the seconds the caller's own work after the run will take (its validation), if given."""
    import torch

    from posefuse.sim.core_share import CoreShare

    share = CoreShare() if config.threads is None else None
    threads = config.threads or share.cores  # until the first look, in the loop
    torch.set_num_threads(threads)
    catalog = load_catalog(catalog_dir)
    if config.bf16 is None:
        config = dataclasses.replace(config, bf16=native_bf16())
    model_path = Path(model_path)
    model_path.parent.mkdir(parents=True, exist_ok=True)
    ckpt_path = Path(config.checkpoint) if config.checkpoint else model_path.with_suffix(".ckpt")
    state = None
    if config.resume:
        state = torch.load(config.resume, map_location="cpu", weights_only=False)
        if state.get("version") != CHECKPOINT_VERSION:
            raise ValueError(f"{config.resume}: checkpoint version {state.get('version')}")
        if state["catalog_hash"] != catalog_hash(catalog):
            raise ValueError(f"{config.resume}: trained for another catalog")
        stored = state["config"]
        config = dataclasses.replace(
            config,
            **{
                k: (tuple(v) if isinstance(v, list) else v)
                for k, v in stored.items()
                if k in _STREAM_FIELDS and k not in _OPTIONAL_STREAM_FIELDS
            },
            crop_width=stored.get("crop_width"),
            restarts=tuple(tuple(r) for r in stored.get("restarts", ())),
            crop_box_channel=bool(stored.get("crop_box_channel", False)),
            # a checkpoint older than the option was trained without it
            dihedral=bool(stored.get("dihedral", False)),
            photometric=bool(stored.get("photometric", False)),
            backgrounds=float(stored.get("backgrounds", 0.0)),
            composite=float(stored.get("composite", 0.0)),
            input_scale=float(stored.get("input_scale", INPUT_SCALE)),
            frozen_backbones=bool(stored.get("frozen_backbones", False)),
            class_scale_factors=tuple(float(f) for f in stored.get("class_scale_factors", ())),
            class_balanced=bool(stored.get("class_balanced", False)),
        )
        if config.vote_loss is None:
            config = dataclasses.replace(config, vote_loss=float(stored.get("vote_loss", 0.0)))
        if config.extend is not None:
            config = config.extended(*config.extend)
    # a fine-tune's architecture is settled (and refused) before any rendering
    base = None
    if config.init and state is None:
        base = torch.load(config.init, map_location="cpu", weights_only=False)
        stored = base.get("config", {})
        # a fine-tune keeps the architecture it starts from (and may add the box channel, or
        # widen stage two by an integer factor: ``init_from``)
        base_width = int(stored.get("width", config.width))
        base_crop_width = int(stored.get("crop_width") or base_width)
        crop_width = config.crop_width or base_crop_width
        if crop_width % base_crop_width:
            raise ValueError(
                f"--crop-width {crop_width}: must be a multiple of {config.init}'s stage-two "
                f"width {base_crop_width}"
            )
        config = dataclasses.replace(
            config,
            width=base_width,
            input_scale=config.input_scale or float(stored.get("input_scale", INPUT_SCALE)),
            crop_width=crop_width if crop_width != base_width else None,
            crop_box_channel=bool(stored.get("crop_box_channel")) or config.crop_box_channel,
        )
    if config.input_scale is None:
        config = dataclasses.replace(config, input_scale=INPUT_SCALE)
    # a generalist has one class, so one scale
    class_scale_factors(config.class_scale_factors, 1 if config.agnostic else len(catalog))
    data_dir = Path(config.data_dir) if config.data_dir else _default_data_dir()
    t_render = time.time()
    spec = RenderSpec(
        config.n_scenes,
        config.views_per_scene,
        TRAIN_SEED_BASE,
        config.robi_fraction,
        small_scale=config.input_scale,
        materials=config.materials,
        composite=config.composite,
    )
    ts = render_training_set(catalog_dir, spec, data_dir, config.workers, "render train")
    val_spec = dataclasses.replace(spec, n_scenes=config.val_scenes, seed_base=VAL_SEED_BASE)
    val = render_training_set(catalog_dir, val_spec, data_dir, config.workers, "render val")
    render_minutes = (time.time() - t_render) / 60
    n_classes = 1 if config.agnostic else len(catalog)
    if config.agnostic:  # every instance is of the one class (the rows are in memory)
        ts.instances[:, 2] = 1.0
        val.instances[:, 2] = 1.0
    nets = _Nets(n_classes, config)
    step, cpu_seconds, wall_seconds, curve = 0, 0.0, 0.0, []
    # what a fine-tune started from, so that its learning curve can continue the base's
    lineage = None
    if base is not None:
        fresh = nets.init_from(base["nets"])
        tqdm.write(f"fine-tuning from {config.init}; new layers: {', '.join(fresh) or 'none'}")
        lineage = {
            "checkpoint": str(config.init),
            "catalog_hash": base.get("catalog_hash"),
            "step": base.get("step"),
            "cpu_seconds": base.get("cpu_seconds"),
            "wall_seconds": base.get("wall_seconds"),
            "curve": base.get("curve", []),
            "init_from": base.get("init_from"),  # and what the base started from
        }
    if state is not None:
        nets.load(state["nets"])
        step, cpu_seconds, wall_seconds = state["step"], state["cpu_seconds"], state["wall_seconds"]
        curve = state["curve"]
        lineage = state.get("init_from")
    view_rows = ts.view_instances()
    candidates = np.flatnonzero(ts.instances[:, 9] >= MIN_TARGET_VISIB)
    batch_config = BatchConfig(
        det_batch=config.batch,
        crop_batch=config.crop_batch,
        crop_size=config.crop_size,
        box_channel=config.crop_box_channel,
        dihedral=config.dihedral,
        photometric=Photometric() if config.photometric else None,
        backgrounds=Backgrounds(p=config.backgrounds) if config.backgrounds > 0 else None,
        class_scale_factors=config.class_scale_factors,
        class_weights=class_weights(ts.instances[candidates, 2], n_classes)
        if config.class_balanced
        else (),
    )
    start = time.time()
    deadline = start + config.minutes * 60
    if config.deadline is not None:
        kept = _finish_seconds(nets, model_path, catalog, config, val, after)
        tqdm.write(
            f"kept {sum(kept.values()):.0f} s of the deadline for what follows the loop "
            f"(measured: {', '.join(f'{k} {v:.0f} s' for k, v in kept.items())})"
        )
        deadline = min(deadline, config.deadline - sum(kept.values()))
    last_ckpt = time.time()
    cpu_mark, wall_mark = time.process_time(), time.time()
    losses: list[dict] = []

    def account():
        nonlocal cpu_seconds, wall_seconds, cpu_mark, wall_mark
        now_cpu, now_wall = time.process_time(), time.time()
        cpu_seconds += now_cpu - cpu_mark
        wall_seconds += now_wall - wall_mark
        cpu_mark, wall_mark = now_cpu, now_wall

    def checkpoint(final: bool):
        nonlocal cpu_mark, wall_mark
        account()
        point = {
            "step": step,
            "cpu_hours": cpu_seconds / 3600,
            "wall_hours": wall_seconds / 3600,
            "loss": {k: float(np.mean([d[k] for d in losses[-200:]])) for k in losses[0]}
            if losses
            else None,
        }
        nets.export(model_path, _card(catalog, config, model_path, 1.0, {}))
        if config.tune:
            point["tuning"] = score_tuning(model_path, config.tune, config.seed)
        curve.append(point)
        torch.save(
            {
                "version": CHECKPOINT_VERSION,
                "catalog_hash": catalog_hash(catalog),
                "config": {
                    **{k: getattr(config, k) for k in _STREAM_FIELDS},
                    "vote_loss": config.vote_loss or 0.0,
                },
                "step": step,
                "cpu_seconds": cpu_seconds,
                "wall_seconds": wall_seconds,
                "curve": curve,
                "init_from": lineage,
                "nets": nets.state(),
            },
            ckpt_path.with_suffix(".tmp"),
        )
        os.replace(ckpt_path.with_suffix(".tmp"), ckpt_path)
        tqdm.write(f"checkpoint {ckpt_path} at step {step}: {json.dumps(point)}")
        # the evaluation's time is not training time
        cpu_mark, wall_mark = time.process_time(), time.time()

    total = config.total_steps
    if config.run_steps is not None:
        total = min(total, step + config.run_steps)
    bar = tqdm(total=total, initial=step, desc="train", unit="step")
    if share is not None:
        share.others()  # the first look measures the loop, not the rendering before it
    nets.train_mode()
    loop_start = time.time()
    loop_span = max(deadline - loop_start, 1e-3)
    while step < total and time.time() < deadline:
        rng = np.random.default_rng([config.seed, step])
        gen = torch.Generator().manual_seed(int(rng.integers(2**62)))
        det_b = detector_batch(ts, view_rows, n_classes, batch_config, rng)
        crop_b = crop_batch(ts, batch_config, rng, candidates)
        if config.clock_schedule and np.isfinite(deadline):
            lr = config.clock_schedule_at((time.time() - loop_start) / loop_span)
        else:
            lr = config.schedule(step)
        losses.append(nets.step(det_b, crop_b, lr, gen))
        step += 1
        if share is not None and step % THREAD_CHECK_STEPS == 0:
            free = share.free()
            if free != threads:  # the others' load changed: run on what they leave
                threads = free
                torch.set_num_threads(threads)
        if step % 20 == 0:
            m = {k: f"{np.mean([d[k] for d in losses[-20:]]):.3f}" for k in losses[-1]}
            m["threads"] = str(threads)
            bar.set_postfix(m, refresh=False)
            bar.update(step - bar.n)
        if time.time() - last_ckpt > config.checkpoint_minutes * 60 and step < total:
            nets.det.eval(), nets.crop.eval()
            checkpoint(final=False)
            nets.train_mode()
            last_ckpt = time.time()
    bar.close()
    nets.det.eval()
    nets.crop.eval()
    checkpoint(final=True)
    min_score, thresholds = None, None
    if config.tune_min_score:
        min_score, thresholds = tune_min_score(model_path, val, catalog, config.seed)
        card_path = model_path.with_suffix(".json")
        data = json.loads(card_path.read_text())
        data["two_stage"]["min_score"] = min_score
        card_path.write_text(json.dumps(data, indent=2) + "\n")
    cov_scale, val_metrics = calibrate(model_path, val, catalog, config.seed)
    cov_by_score = None
    if config.tune_min_score:  # onboarding: the centres' covariance by score too
        cov_by_score, val_metrics["center_nees_by_score"] = calibrate_by_score(
            model_path, val, catalog, cov_scale, config.seed
        )
    if thresholds is not None:
        val_metrics["min_score_tuning"] = [
            {"min_score": t, "recall": round(r, 4), "precision": round(p, 4)}
            for t, r, p in thresholds
        ]
    account()
    extra = {
        "architecture": (
            f"two stages: BoxDetectorNet(width={config.width}) "
            f"{sum(p.numel() for p in nets.det.parameters())} parameters, "
            f"CropVotingNet(width={config.stage_two_width}, box_channel={config.crop_box_channel}) "
            f"{sum(p.numel() for p in nets.crop.parameters())} parameters"
        ),
        "training": {
            "data": f"{config.n_scenes} scenes x {config.views_per_scene} views "
            f"({config.robi_fraction:.0%} robi profile, the rest mixed), "
            + (
                f"{config.composite:.0%} composed from parts rendered alone (sim.composite), "
                if config.composite > 0
                else ""
            )
            + "rendered at 1280x720, "
            f"scene seeds scene_seed({TRAIN_SEED_BASE}, 0..{config.n_scenes - 1}); "
            f"calibration scene_seed({VAL_SEED_BASE}, 0..{config.val_scenes - 1})",
            "steps": step,
            "schedule_steps": config.total_steps,
            "schedule": "by the clock: warm-up, then a cosine to the deadline"
            if config.clock_schedule
            else "by steps: warm-up, then a cosine over schedule_steps",
            "warm_restarts": [list(r) for r in config.restarts],
            "detector_batch": config.batch,
            "crop_batch": config.crop_batch,
            "cpu_hours": round(cpu_seconds / 3600, 3),
            "wall_hours": round(wall_seconds / 3600, 3),
            "render_minutes_this_run": round(render_minutes, 1),
            "seed": config.seed,
            "bf16_autocast": config.bf16,
            **({"frozen_backbones": True} if config.frozen_backbones else {}),
            "proxy_voting_loss_weight": config.vote_loss or 0.0,
            "augmentation": "mirrors"
            + (", flips and transposes" if config.dihedral else "")
            + (", a camera's photometric effects (sim.photometric)" if config.photometric else "")
            + (
                f", clutter behind the parts in {config.backgrounds:.0%} of samples "
                "(sim.backgrounds)"
                if config.backgrounds > 0
                else ""
            ),
            "initialised_from": config.init or (lineage or {}).get("checkpoint"),
            # this run's hours and those of every checkpoint it was fine-tuned from
            "cumulative_cpu_hours": round((cpu_seconds + _lineage_cpu(lineage)) / 3600, 3),
        },
        "validation": val_metrics,
        **config.extra,
    }
    card = _card(catalog, config, model_path, cov_scale, extra, min_score, cov_by_score)
    model_path.with_suffix(".json").write_text(json.dumps(card.to_json(), indent=2) + "\n")
    return card.to_json()
