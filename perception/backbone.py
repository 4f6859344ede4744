"""A detector started from pretrained features: ShuffleNetV2-0.5x (ImageNet, then COCO detection) under a YOLOv2
door/window head, for training only (imports torch; the runtime runs the exported ONNX through
`perception.detector`, which decodes it exactly as it decodes `perception.model.TinyYolo`).

Written here from the architecture's description (Ma et al., ShuffleNet V2, ECCV 2018; FastestDet's neck: the
stride-8 and stride-32 maps brought to stride 16, concatenated, and mixed by depthwise 5x5 convolutions of growing
reach); the parameter names follow the published weights' layout so that they load with `strict=True`:

- `../shared/weights/fastestdet_coco/fastestdet_coco.pth` (FastestDet, COCO, BSD-3-Clause): backbone and neck
  (`backbone.*`, `SPP.*`); its 80-class head is not used.
- `../shared/weights/fastestdet_coco/shufflenetv2_0.5x_imagenet_backbone.pth` (ImageNet, BSD-3-Clause): the backbone
  alone; the neck then starts at random.

Input: float32 (N, 3, H, W), BGR scaled to [0, 1] (as the pretrained networks were trained: no mean subtraction),
H and W multiples of 16. Output: raw map (N, A * (5 + C), H / 16, W / 16), per anchor (tx, ty, tw, th, objectness,
class logits...) as `TinyYolo`'s.
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn

STAGE_CHANNELS = (24, 48, 96, 192)  # first conv, stages 2-4 (the 0.5x width)
STAGE_REPEATS = (4, 8, 4)
NECK_CHANNELS = 96


def _bn_relu(c: int) -> list[nn.Module]:
    return [nn.BatchNorm2d(c), nn.ReLU(inplace=True)]


class ShuffleUnit(nn.Module):
    """One ShuffleNetV2 unit. Stride 1: half the channels pass, the other half go through 1x1 -> depthwise 3x3 ->
    1x1; stride 2: both halves are computed from all inputs (the `proj` branch downsamples the input)."""

    def __init__(self, c_in: int, c_out: int, stride: int) -> None:
        super().__init__()
        self.stride = stride
        c_main_in = c_in if stride == 2 else c_in // 2
        c_main_out = c_out - c_main_in if stride == 1 else c_out - c_in
        mid = c_out // 2
        self.branch_main = nn.Sequential(
            nn.Conv2d(c_main_in, mid, 1, bias=False), *_bn_relu(mid),
            nn.Conv2d(mid, mid, 3, stride, 1, groups=mid, bias=False), nn.BatchNorm2d(mid),
            nn.Conv2d(mid, c_main_out, 1, bias=False), *_bn_relu(c_main_out))
        if stride == 2:
            self.branch_proj = nn.Sequential(
                nn.Conv2d(c_in, c_in, 3, stride, 1, groups=c_in, bias=False), nn.BatchNorm2d(c_in),
                nn.Conv2d(c_in, c_in, 1, bias=False), *_bn_relu(c_in))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.stride == 2:
            return torch.cat((self.branch_proj(x), self.branch_main(x)), 1)
        passed, processed = _split_shuffled(x)
        return torch.cat((passed, self.branch_main(processed)), 1)


def _split_shuffled(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The channel shuffle of the unit before this one, then the split: even channels pass, odd ones are processed."""
    n, c, h, w = x.shape
    pairs = x.reshape(n, c // 2, 2, h, w)
    return pairs[:, :, 0], pairs[:, :, 1]


class ShuffleNetV2(nn.Module):
    """The backbone: stride-8, -16 and -32 feature maps (48, 96, 192 channels)."""

    def __init__(self) -> None:
        super().__init__()
        c0 = STAGE_CHANNELS[0]
        self.first_conv = nn.Sequential(nn.Conv2d(3, c0, 3, 2, 1, bias=False), *_bn_relu(c0))
        self.maxpool = nn.MaxPool2d(3, 2, 1)
        stages = []
        for c_in, c_out, n in zip(STAGE_CHANNELS[:-1], STAGE_CHANNELS[1:], STAGE_REPEATS, strict=True):
            stages.append(nn.Sequential(*[ShuffleUnit(c_in if i == 0 else c_out, c_out, 2 if i == 0 else 1)
                                          for i in range(n)]))
        self.stage2, self.stage3, self.stage4 = stages

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        s8 = self.stage2(self.maxpool(self.first_conv(x)))
        s16 = self.stage3(s8)
        return s8, s16, self.stage4(s16)


class _Pointwise(nn.Module):
    def __init__(self, c_in: int, c_out: int) -> None:
        super().__init__()
        self.conv1x1 = nn.Sequential(nn.Conv2d(c_in, c_out, 1, bias=False), *_bn_relu(c_out))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv1x1(x)


def _depthwise_5x5(c: int, n: int) -> nn.Sequential:
    layers: list[nn.Module] = []
    for _ in range(n):
        layers += [nn.Conv2d(c, c, 5, 1, 2, groups=c, bias=False), *_bn_relu(c)]
    return nn.Sequential(*layers)


class ReachMixer(nn.Module):
    """The neck at stride 16: a 1x1 projection, then three depthwise 5x5 stacks (reach 5, 9, 13 px of the map)
    concatenated and projected back, added to the projection (a residual)."""

    def __init__(self, c_in: int, c: int) -> None:
        super().__init__()
        self.Conv1x1 = _Pointwise(c_in, c)  # noqa: N815 (the published weights' name)
        self.S1, self.S2, self.S3 = (_depthwise_5x5(c, n) for n in (1, 2, 3))  # noqa: N815
        self.output = nn.Sequential(nn.Conv2d(3 * c, c, 1, bias=False), nn.BatchNorm2d(c))
        self.relu = nn.ReLU(inplace=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.Conv1x1(x)
        return self.relu(x + self.output(torch.cat((self.S1(x), self.S2(x), self.S3(x)), 1)))


class ShuffleYolo(nn.Module):
    """ShuffleNetV2-0.5x backbone, the stride-16 neck, and a YOLOv2 head (A anchors x (5 + C) channels)."""

    def __init__(self, n_anchors: int, n_classes: int) -> None:
        super().__init__()
        self.n_anchors, self.n_classes = n_anchors, n_classes
        self.backbone = ShuffleNetV2()
        self.avg_pool = nn.AvgPool2d(3, 2, 1)
        self.SPP = ReachMixer(sum(STAGE_CHANNELS[1:]), NECK_CHANNELS)  # noqa: N815
        self.head = nn.Sequential(_Pointwise(NECK_CHANNELS, NECK_CHANNELS), _depthwise_5x5(NECK_CHANNELS, 1),
                                  nn.Conv2d(NECK_CHANNELS, n_anchors * (5 + n_classes), 1))
        with torch.no_grad():  # objectness prior ~1 % (a calm start: most slots hold nothing)
            last = self.head[-1]
            assert isinstance(last, nn.Conv2d) and last.bias is not None
            bias = last.bias
            bias.view(n_anchors, 5 + n_classes)[:, 4] = -4.5

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        s8, s16, s32 = self.backbone(x)
        s32_up = nn.functional.interpolate(s32, size=s16.shape[-2:], mode="nearest")  # an odd stride-16 map too
        neck = self.SPP(torch.cat((self.avg_pool(s8), s16, s32_up), 1))
        return self.head(neck)

    def load_pretrained(self, path: Path) -> list[str]:
        """Copy a pretrained backbone (and neck, where the file has one) into this network, exactly (every tensor
        of the file's backbone and neck must fit; anything else in the file, e.g. a COCO head, is skipped).
        Returns the names of this network's tensors that were loaded."""
        state = torch.load(path, map_location="cpu", weights_only=True)  # saved with CUDA device tags
        if not any(k.startswith("backbone.") for k in state):  # a backbone saved alone
            state = {f"backbone.{k}": v for k, v in state.items()}
        own = self.state_dict()
        taken = {k: v for k, v in state.items() if k.split(".")[0] in ("backbone", "SPP")}
        missing = [k for k in taken if k not in own or own[k].shape != taken[k].shape]
        if missing or not taken:
            raise ValueError(f"{path}: not a ShuffleNetV2-0.5x backbone of the expected layout "
                             f"({len(missing)} tensors do not fit, e.g. {missing[:3]})")
        self.load_state_dict(taken, strict=False)
        return sorted(taken)
