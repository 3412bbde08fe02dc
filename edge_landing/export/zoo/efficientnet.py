"""EfficientNet (Tan & Le 2019) with TensorFlow 'same' padding, in the module layout of the PyTorch ports.

Written from the paper's B0 stage table and compound scaling so that state_dicts saved from the PyTorch
ports of the TF weights (``tf_efficientnet_b5_ap`` and friends, as AdaBins uses) load by name::

    net = EfficientNet(EFFICIENTNET_B5_TF)
    feats = net.forward_features(x)    # list: output of every stage (blocks.0..6), then conv_head

Names: conv_stem, bn1, blocks.s.b.{conv_dw,bn1,se.conv_reduce,se.conv_expand,conv_pw,bn2} for the
depthwise-separable blocks of stage 0, blocks.s.b.{conv_pw,bn1,conv_dw,bn2,se.*,conv_pwl,bn3} for the
inverted-residual blocks, conv_head, bn2. The global pool and classifier are left out (the depth networks
that use this encoder replace them by identities).
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import List, Tuple

import torch
import torch.nn.functional as F
from torch import nn


@dataclass(frozen=True)
class StageDef:
    """One row of the EfficientNet-B0 table (before scaling)."""

    kind: str          # "ds": depthwise-separable (no expansion), "ir": inverted residual (MBConv)
    repeats: int
    kernel: int
    stride: int
    expand_ratio: int
    out_channels: int


# EfficientNet-B0 (paper Table 1); every block has squeeze-excitation with ratio 0.25.
B0_STAGES: Tuple[StageDef, ...] = (
    StageDef("ds", 1, 3, 1, 1, 16),
    StageDef("ir", 2, 3, 2, 6, 24),
    StageDef("ir", 2, 5, 2, 6, 40),
    StageDef("ir", 3, 3, 2, 6, 80),
    StageDef("ir", 3, 5, 1, 6, 112),
    StageDef("ir", 4, 5, 2, 6, 192),
    StageDef("ir", 1, 3, 1, 6, 320),
)


@dataclass(frozen=True)
class EfficientNetConfig:
    width_mult: float
    depth_mult: float
    stem_channels: int = 32          # before width scaling
    head_channels: int = 1280        # before width scaling
    se_ratio: float = 0.25           # of the block's *input* channels
    bn_eps: float = 1e-3             # the TF ports keep TensorFlow's BatchNorm epsilon
    tf_same_padding: bool = True
    divisor: int = 8
    stages: Tuple[StageDef, ...] = B0_STAGES

    def channels(self, base: int) -> int:
        return round_filters(base, self.width_mult, self.divisor)

    def repeats(self, base: int) -> int:
        return round_repeats(base, self.depth_mult)

    @property
    def stage_channels(self) -> Tuple[int, ...]:
        return tuple(self.channels(s.out_channels) for s in self.stages)


EFFICIENTNET_B5_TF = EfficientNetConfig(width_mult=1.6, depth_mult=2.2)


def round_filters(channels: float, width_mult: float, divisor: int = 8) -> int:
    """Scale a channel count and round it to a multiple of ``divisor``, never losing more than 10 %."""
    scaled = channels * width_mult
    rounded = max(divisor, int(scaled + divisor / 2) // divisor * divisor)
    if rounded < 0.9 * scaled:
        rounded += divisor
    return int(rounded)


def round_repeats(repeats: int, depth_mult: float) -> int:
    return int(math.ceil(repeats * depth_mult))


def _same_pad(size: int, kernel: int, stride: int, dilation: int = 1) -> Tuple[int, int]:
    """TensorFlow 'same': output = ceil(size / stride); the odd pixel of padding goes after (right/bottom)."""
    total = max((math.ceil(size / stride) - 1) * stride + (kernel - 1) * dilation + 1 - size, 0)
    return total // 2, total - total // 2


class Conv2dSame(nn.Conv2d):
    """Conv2d with TF 'same' padding. Strided convs pad asymmetrically depending on the input size, so the
    padding is computed per call (a fixed-size export bakes it into the graph as constants)."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int, stride: int = 1, groups: int = 1,
                 bias: bool = False):
        super().__init__(in_channels, out_channels, kernel_size, stride=stride, padding=0, groups=groups, bias=bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        with warnings.catch_warnings():
            # Tracing warns that the size becomes a constant: for a fixed-size export that is the intent.
            warnings.simplefilter("ignore", torch.jit.TracerWarning)
            height, width = int(x.shape[-2]), int(x.shape[-1])
        top, bottom = _same_pad(height, self.kernel_size[0], self.stride[0])
        left, right = _same_pad(width, self.kernel_size[1], self.stride[1])
        if top or bottom or left or right:
            x = F.pad(x, (left, right, top, bottom))
        return super().forward(x)


def make_conv(in_channels: int, out_channels: int, kernel: int, stride: int = 1, groups: int = 1,
              bias: bool = False, tf_same: bool = True) -> nn.Conv2d:
    # A stride-1 odd kernel pads symmetrically under 'same' too: a plain padded conv is identical and
    # exports without Pad nodes.
    if not tf_same or (stride == 1 and kernel % 2 == 1):
        return nn.Conv2d(in_channels, out_channels, kernel, stride=stride, padding=kernel // 2, groups=groups,
                         bias=bias)
    return Conv2dSame(in_channels, out_channels, kernel, stride=stride, groups=groups, bias=bias)


def _se_channels(in_channels: int, se_ratio: float) -> int:
    # The ports round half up (make_divisible with divisor 1: int(v + 0.5)), not Python's half-to-even round().
    return max(1, int(in_channels * se_ratio + 0.5))


class SqueezeExcite(nn.Module):
    """Channel gate: global mean -> 1×1 reduce -> swish -> 1×1 expand -> sigmoid (convs with bias)."""

    def __init__(self, channels: int, reduced: int):
        super().__init__()
        self.conv_reduce = nn.Conv2d(channels, reduced, 1, bias=True)
        self.conv_expand = nn.Conv2d(reduced, channels, 1, bias=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        s = F.silu(self.conv_reduce(x.mean(dim=(2, 3), keepdim=True)))
        return x * torch.sigmoid(self.conv_expand(s))


class DepthwiseSeparable(nn.Module):
    """Stage-0 block: depthwise conv, BN, swish, SE, pointwise conv, BN (no activation), residual if shapes match."""

    def __init__(self, in_channels: int, out_channels: int, kernel: int, stride: int, cfg: EfficientNetConfig):
        super().__init__()
        self.has_skip = stride == 1 and in_channels == out_channels
        self.conv_dw = make_conv(in_channels, in_channels, kernel, stride, groups=in_channels,
                                 tf_same=cfg.tf_same_padding)
        self.bn1 = nn.BatchNorm2d(in_channels, eps=cfg.bn_eps)
        self.se = SqueezeExcite(in_channels, _se_channels(in_channels, cfg.se_ratio))
        self.conv_pw = nn.Conv2d(in_channels, out_channels, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(out_channels, eps=cfg.bn_eps)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.se(F.silu(self.bn1(self.conv_dw(x))))
        y = self.bn2(self.conv_pw(y))
        return x + y if self.has_skip else y


class InvertedResidual(nn.Module):
    """MBConv: 1×1 expand, BN, swish, depthwise k×k, BN, swish, SE, 1×1 project, BN, residual if shapes match."""

    def __init__(self, in_channels: int, out_channels: int, kernel: int, stride: int, expand_ratio: int,
                 cfg: EfficientNetConfig):
        super().__init__()
        mid = in_channels * expand_ratio
        self.has_skip = stride == 1 and in_channels == out_channels
        self.conv_pw = nn.Conv2d(in_channels, mid, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(mid, eps=cfg.bn_eps)
        self.conv_dw = make_conv(mid, mid, kernel, stride, groups=mid, tf_same=cfg.tf_same_padding)
        self.bn2 = nn.BatchNorm2d(mid, eps=cfg.bn_eps)
        # The SE bottleneck is sized from the block's input, not from the expanded width.
        self.se = SqueezeExcite(mid, _se_channels(in_channels, cfg.se_ratio))
        self.conv_pwl = nn.Conv2d(mid, out_channels, 1, bias=False)
        self.bn3 = nn.BatchNorm2d(out_channels, eps=cfg.bn_eps)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.silu(self.bn1(self.conv_pw(x)))
        y = self.se(F.silu(self.bn2(self.conv_dw(y))))
        y = self.bn3(self.conv_pwl(y))
        return x + y if self.has_skip else y


class EfficientNet(nn.Module):
    """The feature extractor (stem, 7 stages, head conv + BN); no pooling or classifier."""

    def __init__(self, cfg: EfficientNetConfig = EFFICIENTNET_B5_TF):
        super().__init__()
        self.cfg = cfg
        stem = cfg.channels(cfg.stem_channels)
        self.conv_stem = make_conv(3, stem, 3, stride=2, tf_same=cfg.tf_same_padding)
        self.bn1 = nn.BatchNorm2d(stem, eps=cfg.bn_eps)
        stages, channels = [], stem
        for stage in cfg.stages:
            out = cfg.channels(stage.out_channels)
            blocks: list[nn.Module] = []
            for i in range(cfg.repeats(stage.repeats)):
                stride = stage.stride if i == 0 else 1
                if stage.kind == "ds":
                    blocks.append(DepthwiseSeparable(channels, out, stage.kernel, stride, cfg))
                else:
                    blocks.append(InvertedResidual(channels, out, stage.kernel, stride, stage.expand_ratio, cfg))
                channels = out
            stages.append(nn.Sequential(*blocks))
        self.blocks = nn.Sequential(*stages)
        self.head_channels = cfg.channels(cfg.head_channels)
        self.conv_head = nn.Conv2d(channels, self.head_channels, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(self.head_channels, eps=cfg.bn_eps)

    def forward_features(self, x: torch.Tensor) -> List[torch.Tensor]:
        """Outputs of blocks.0 .. blocks.6 (strides 2, 4, 8, 16, 16, 32, 32), then conv_head before its BN."""
        x = F.silu(self.bn1(self.conv_stem(x)))
        feats = []
        for stage in self.blocks:
            x = stage(x)
            feats.append(x)
        feats.append(self.conv_head(x))
        return feats

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """The final activated head features (N × head_channels × H/32 × W/32)."""
        return F.silu(self.bn2(self.forward_features(x)[-1]))
