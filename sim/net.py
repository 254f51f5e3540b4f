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
