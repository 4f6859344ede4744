"""The detector's network: a small YOLOv2-style CNN (grid cells x anchor boxes), for training only.

Imports torch: only `perception.train` and tests that build a tiny model import this module; the
runtime uses the exported ONNX file through `perception.detector`.

Input: float32 tensor (N, 3, H, W), BGR scaled to [0, 1], H and W multiples of `STRIDE_PX`.
Output: raw map (N, A * (5 + C), H / 16, W / 16); per anchor the channels are
(tx, ty, tw, th, objectness, class logits...) as in YOLOv2 (decoded by `perception.detector`).
"""

from __future__ import annotations

import torch
from torch import nn

STRIDE_PX = 16


def _conv(c_in: int, c_out: int, stride: int = 1, kernel: int = 3, dilation: int = 1) -> nn.Sequential:
    pad = dilation * (kernel // 2)
    return nn.Sequential(
        nn.Conv2d(c_in, c_out, kernel, stride, pad, dilation=dilation, bias=False),
        nn.BatchNorm2d(c_out),
        nn.LeakyReLU(0.1, inplace=True),
    )


class TinyYolo(nn.Module):
    """~0.4 M parameters; stride 16; dilated last stage for a receptive field that covers a near door."""

    def __init__(self, n_anchors: int, n_classes: int, width: int = 1) -> None:
        super().__init__()
        w = width
        self.n_anchors = n_anchors
        self.n_classes = n_classes
        self.features = nn.Sequential(
            _conv(3, 16 * w, 2),  # /2
            _conv(16 * w, 32 * w, 2),  # /4
            _conv(32 * w, 64 * w, 2),  # /8
            _conv(64 * w, 64 * w),
            _conv(64 * w, 128 * w, 2),  # /16
            _conv(128 * w, 128 * w),
            _conv(128 * w, 128 * w, dilation=2),
            _conv(128 * w, 64 * w, kernel=1),
            _conv(64 * w, 128 * w, dilation=4),
        )
        self.head = nn.Conv2d(128 * w, n_anchors * (5 + n_classes), 1)
        with torch.no_grad():  # objectness prior ~1 % (a calm start: most slots hold nothing)
            bias = self.head.bias
            assert bias is not None
            bias.view(n_anchors, 5 + n_classes)[:, 4] = -4.5

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.features(x))
