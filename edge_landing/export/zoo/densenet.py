"""DenseNet-169 (Huang et al. 2017) with torchvision's module layout and parameter names.

Written from the paper's description so that state_dicts saved from torchvision's ``densenet169`` (and the
DenseDepth checkpoints built on it) load by name::

    net = DenseNet(DENSENET169, with_classifier=False)
    feats = net.forward_features(x)    # dict: relu0, pool0, transition1..3, denseblock4, norm5

Names: features.{conv0,norm0,relu0,pool0,denseblockN.denselayerK.{norm1,relu1,conv1,norm2,relu2,conv2},
transitionN.{norm,relu,conv,pool},norm5}, classifier.
"""
from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from typing import Dict, Tuple

import torch
from torch import nn


@dataclass(frozen=True)
class DenseNetConfig:
    growth_rate: int = 32
    block_layers: Tuple[int, ...] = (6, 12, 32, 32)
    init_features: int = 64
    bottleneck_factor: int = 4      # the 1×1 conv widens to bottleneck_factor × growth_rate
    compression: float = 0.5        # transitions keep this share of the channels
    num_classes: int = 1000

    @property
    def out_channels(self) -> int:
        channels = self.init_features
        for i, n in enumerate(self.block_layers):
            channels += n * self.growth_rate
            if i < len(self.block_layers) - 1:
                channels = int(channels * self.compression)
        return channels


DENSENET169 = DenseNetConfig()


class DenseLayer(nn.Module):
    """BN-ReLU-Conv1×1 then BN-ReLU-Conv3×3; returns only the new ``growth_rate`` channels."""

    def __init__(self, in_channels: int, growth_rate: int, bottleneck_factor: int):
        super().__init__()
        mid = bottleneck_factor * growth_rate
        self.norm1 = nn.BatchNorm2d(in_channels)
        self.relu1 = nn.ReLU(inplace=True)
        self.conv1 = nn.Conv2d(in_channels, mid, kernel_size=1, stride=1, bias=False)
        self.norm2 = nn.BatchNorm2d(mid)
        self.relu2 = nn.ReLU(inplace=True)
        self.conv2 = nn.Conv2d(mid, growth_rate, kernel_size=3, stride=1, padding=1, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        # relu1 must not run in place: x is the concatenation that later layers read again.
        y = self.conv1(torch.relu(self.norm1(x)))
        return self.conv2(self.relu2(self.norm2(y)))


class DenseBlock(nn.ModuleDict):
    """Every layer sees the concatenation of the block input and all earlier layers' outputs."""

    def __init__(self, num_layers: int, in_channels: int, growth_rate: int, bottleneck_factor: int):
        super().__init__()
        for i in range(num_layers):
            self[f"denselayer{i + 1}"] = DenseLayer(in_channels + i * growth_rate, growth_rate, bottleneck_factor)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        features = [x]
        for layer in self.values():
            features.append(layer(torch.cat(features, 1)))
        return torch.cat(features, 1)


class Transition(nn.Sequential):
    def __init__(self, in_channels: int, out_channels: int):
        super().__init__(OrderedDict([
            ("norm", nn.BatchNorm2d(in_channels)),
            ("relu", nn.ReLU(inplace=True)),
            ("conv", nn.Conv2d(in_channels, out_channels, kernel_size=1, stride=1, bias=False)),
            ("pool", nn.AvgPool2d(kernel_size=2, stride=2)),
        ]))


class DenseNet(nn.Module):
    """DenseNet with ``features`` (a Sequential, as torchvision) and an optional ``classifier``.

    The depth networks use only ``features``; ``with_classifier=False`` leaves the 1.67 M classifier
    parameters out of the module so that they are neither counted nor exported.
    """

    def __init__(self, config: DenseNetConfig = DENSENET169, with_classifier: bool = True):
        super().__init__()
        c = config
        layers = OrderedDict([
            ("conv0", nn.Conv2d(3, c.init_features, kernel_size=7, stride=2, padding=3, bias=False)),
            ("norm0", nn.BatchNorm2d(c.init_features)),
            ("relu0", nn.ReLU(inplace=False)),  # its output is a skip: keep norm0 intact
            ("pool0", nn.MaxPool2d(kernel_size=3, stride=2, padding=1)),
        ])
        channels = c.init_features
        for i, n in enumerate(c.block_layers):
            layers[f"denseblock{i + 1}"] = DenseBlock(n, channels, c.growth_rate, c.bottleneck_factor)
            channels += n * c.growth_rate
            if i < len(c.block_layers) - 1:
                layers[f"transition{i + 1}"] = Transition(channels, int(channels * c.compression))
                channels = int(channels * c.compression)
        layers["norm5"] = nn.BatchNorm2d(channels)
        self.features = nn.Sequential(layers)
        self.out_channels = channels
        self.classifier = nn.Linear(channels, c.num_classes) if with_classifier else None
        self._init_weights()

    def _init_weights(self) -> None:
        # torchvision's initialisation, so that random-weight exports have sane activations.
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight)
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.constant_(m.weight, 1.0)
                nn.init.constant_(m.bias, 0.0)
            elif isinstance(m, nn.Linear):
                nn.init.constant_(m.bias, 0.0)

    def forward_features(self, x: torch.Tensor) -> Dict[str, torch.Tensor]:
        """The output of every top-level feature module, by name (the skip points of U-Net decoders)."""
        out = {}
        for name, module in self.features.named_children():
            x = module(x)
            out[name] = x
        return out

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.classifier is None:
            raise RuntimeError("this DenseNet was built without its classifier; use forward_features")
        y = torch.relu(self.features(x))
        y = torch.flatten(nn.functional.adaptive_avg_pool2d(y, 1), 1)
        return self.classifier(y)
