"""The center-voting network (torch): class segmentation + unit vectors to instance centers.

A small fully convolutional encoder-decoder (FPN-like top-down path) for CPU inference: input
(B, 3, H, W) normalised RGB with H, W multiples of 16; output (B, C + 1 + 2, H/2, W/2): logits
of background and the C classes, then the 2D unit vector (x, y) from each pixel towards the
projected model origin of its instance.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F


def _block(c_in: int, c_out: int, stride: int = 1, dilation: int = 1) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(c_in, c_out, 3, stride, padding=dilation, dilation=dilation, bias=False),
        nn.BatchNorm2d(c_out),
        nn.ReLU(inplace=True),
    )


class CenterVotingNet(nn.Module):
    def __init__(self, n_classes: int, width: int = 16):
        super().__init__()
        w = width
        self.enc1 = nn.Sequential(_block(3, w, 2), _block(w, w))  # 1/2
        self.enc2 = nn.Sequential(_block(w, 2 * w, 2), _block(2 * w, 2 * w))  # 1/4
        self.enc3 = nn.Sequential(_block(2 * w, 4 * w, 2), _block(4 * w, 4 * w))  # 1/8
        self.enc4 = nn.Sequential(_block(4 * w, 6 * w, 2), _block(6 * w, 6 * w, dilation=2))
        self.lat3 = nn.Conv2d(4 * w, 2 * w, 1)
        self.lat2 = nn.Conv2d(2 * w, 2 * w, 1)
        self.lat1 = nn.Conv2d(w, 2 * w, 1)
        self.top = nn.Conv2d(6 * w, 2 * w, 1)
        self.dec3 = _block(2 * w, 2 * w)
        self.dec2 = _block(2 * w, 2 * w)
        self.dec1 = _block(2 * w, 2 * w)
        self.head = nn.Conv2d(2 * w, n_classes + 1 + 2, 1)
        self.n_classes = n_classes

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        e1 = self.enc1(x)
        e2 = self.enc2(e1)
        e3 = self.enc3(e2)
        e4 = self.enc4(e3)
        d = self.top(e4)
        d = self.dec3(F.interpolate(d, scale_factor=2.0, mode="nearest") + self.lat3(e3))
        d = self.dec2(F.interpolate(d, scale_factor=2.0, mode="nearest") + self.lat2(e2))
        d = self.dec1(F.interpolate(d, scale_factor=2.0, mode="nearest") + self.lat1(e1))
        out = self.head(d)
        logits = out[:, : self.n_classes + 1]
        vec = out[:, self.n_classes + 1 :]
        vec = vec / torch.sqrt((vec * vec).sum(1, keepdim=True) + 1e-6)
        return torch.cat([logits, vec], 1)


class Backbone(nn.Module):
    """The shared encoder-decoder of both stages: input (B, 3, H, W), H and W multiples of 16;
    output (B, 2 * width, H / 4, W / 4) features (an FPN-like top-down path from 1/16).

    Both networks of the two-stage front end use it; only their heads are specific (the
    detector's class heatmaps are the one class-specific part, so a new catalog replaces
    that head and fine-tunes the rest)."""

    def __init__(self, width: int = 16, in_channels: int = 3):
        super().__init__()
        w = width
        self.enc1 = nn.Sequential(_block(in_channels, w, 2), _block(w, w))  # 1/2
        self.enc2 = nn.Sequential(_block(w, 2 * w, 2), _block(2 * w, 2 * w))  # 1/4
        self.enc3 = nn.Sequential(_block(2 * w, 4 * w, 2), _block(4 * w, 4 * w))  # 1/8
        self.enc4 = nn.Sequential(_block(4 * w, 6 * w, 2), _block(6 * w, 6 * w, dilation=2))
        self.top = nn.Conv2d(6 * w, 2 * w, 1)
        self.lat3 = nn.Conv2d(4 * w, 2 * w, 1)
        self.lat2 = nn.Conv2d(2 * w, 2 * w, 1)
        self.dec3 = _block(2 * w, 2 * w)
        self.dec2 = _block(2 * w, 2 * w)
        self.out_channels = 2 * w

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        e2 = self.enc2(self.enc1(x))
        e3 = self.enc3(e2)
        d = self.top(self.enc4(e3))
        d = self.dec3(F.interpolate(d, scale_factor=2.0, mode="nearest") + self.lat3(e3))
        return self.dec2(F.interpolate(d, scale_factor=2.0, mode="nearest") + self.lat2(e2))


class BoxDetectorNet(nn.Module):
    """Stage one, on the downscaled frame: CenterNet-style boxes and classes.

    Output (B, C + 4, H / 4, W / 4): per class the probability that a part's visible box is
    centred at that cell (sigmoid applied), then the box's log width and log height in input
    pixels, then the sub-cell offset (x, y) of the box center in cells."""

    def __init__(self, n_classes: int, width: int = 16):
        super().__init__()
        self.backbone = Backbone(width)
        c = self.backbone.out_channels
        self.neck = _block(c, c)
        self.heatmap = nn.Conv2d(c, n_classes, 1)  # the class-specific head
        self.box = nn.Conv2d(c, 4, 1)
        nn.init.constant_(self.heatmap.bias, -2.19)  # prior 0.1, as CenterNet
        self.n_classes = n_classes

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        f = self.neck(self.backbone(x))
        return torch.cat([torch.sigmoid(self.heatmap(f)), self.box(f)], 1)

    def forward_logits(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(heatmap logits (B, C, h, w), box (B, 4, h, w)) for training."""
        f = self.neck(self.backbone(x))
        return self.heatmap(f), self.box(f)


class CropVotingNet(nn.Module):
    """Stage two, PVNet-style, on one box cropped and resized to a fixed square: which pixels
    belong to the part the crop is centred on, and a unit vector from each towards its
    projected model origin. Class-agnostic (the class comes from stage one).

    Input (B, 3, S, S), or (B, 4, S, S) with ``box_channel``: the normalised RGB, then the
    box stage one gave (1 inside, 0 outside; see ``estimator.frontend.crops.box_mask``).
    Output (B, 3, S / 4, S / 4): the object-vs-not logit, then the unit vector (x, y)."""

    def __init__(self, width: int = 16, box_channel: bool = False):
        super().__init__()
        self.backbone = Backbone(width, 4 if box_channel else 3)
        c = self.backbone.out_channels
        self.neck = _block(c, c)
        self.head = nn.Conv2d(c, 3, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.head(self.neck(self.backbone(x)))
        vec = out[:, 1:]
        vec = vec / torch.sqrt((vec * vec).sum(1, keepdim=True) + 1e-6)
        return torch.cat([out[:, :1], vec], 1)


def widen_state(
    old: dict[str, torch.Tensor],
    new: dict[str, torch.Tensor],
    noise: float = 0.0,
    seed: int = 0,
) -> tuple[dict[str, torch.Tensor], list[str]]:
    """A wider network's state that computes what the narrower one did (Net2WiderNet).

    ``old`` is a state dict of one of the networks above at width w, ``new`` the same network's
    at width k * w (for an integer k): every channel c of the wider network copies channel
    c mod (its old count), and a convolution's weights on a widened input are divided by k, so
    that the k copies of an input channel sum to the original. Batch-norm statistics and
    affine parameters are copied alike. Each widened convolution gets Gaussian noise of
    ``noise`` times its own weights' standard deviation (seeded), or the k copies of a channel
    would receive equal gradients and stay equal; ``noise=0`` preserves the function exactly
    (in eval mode).

    Shapes: conv weights (C_out, C_in, kh, kw), the rest (C,). A tensor whose size in a
    dimension is not a multiple of the old one is not widened there; returns the state and the
    names of the tensors left as ``new`` had them (no counterpart, or incompatible shapes).
    """
    gen = torch.Generator().manual_seed(seed)
    out = dict(new)
    kept_fresh = []
    for name, target in new.items():
        if name not in old:
            kept_fresh.append(name)
            continue
        src = old[name]
        if src.shape == target.shape:
            out[name] = src.clone()
            continue
        if src.ndim != target.ndim or any(
            t % s for s, t in zip(src.shape, target.shape, strict=True)
        ):
            kept_fresh.append(name)
            continue
        reps = [t // s for s, t in zip(src.shape, target.shape, strict=True)]
        w = src.repeat(*reps)
        if src.ndim == 4 and reps[1] > 1:
            w = w / reps[1]
        if noise > 0 and src.ndim == 4:
            w = w + noise * float(src.float().std()) * torch.randn(w.shape, generator=gen)
        out[name] = w.to(target.dtype)
    return out, kept_fresh
