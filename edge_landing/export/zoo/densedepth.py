"""DenseDepth (Alhashim & Wonka 2018): DenseNet-169 encoder, U-Net decoder of width 1.0.

Re-implemented from reference/models.md with the authors' PyTorch key names, so their converted checkpoints
load by name (``encoder.original_model.features...``, ``decoder.conv2``, ``decoder.up1..4.convA/convB``,
``decoder.conv3``). Input RGB/255 (no mean/std), output y at half resolution with
metres = clip(max_depth / y, min_depth, max_depth) (NYU 10/0.1 m, KITTI 80/1 m)::

    spec = get_arch("densedepth")
    model = spec.build(Task.DEPTH)                          # 42,657,689 parameters
    spec.load_checkpoint(model, "nyu.pth")                  # state_dict, with or without classifier/module.
"""
from __future__ import annotations

from pathlib import Path
from typing import Tuple

import torch
from torch import nn
from torch.nn import functional as F

from edge_landing.runtime.perception.contract import (
    DepthConvention,
    DepthSpec,
    InputSpec,
    Layout,
    ModelContract,
    Task,
)

from ..checkpoints import drop_keys, load_state_dict_strict, model_state, read_checkpoint, source_info
from .common import INPUT_NAME, OUTPUT_DEPTH, merged_options, upsample_concat
from .densenet import DENSENET169, DenseNet
from .registry import ArchSpec, require_task

CLASSIFIER_PREFIX = "encoder.original_model.classifier."
# DenseNet-169 feature modules whose outputs the decoder reads, finest first (H/2, H/4, H/8, H/16).
SKIP_POINTS = ("relu0", "pool0", "transition1", "transition2")
SKIP_CHANNELS = (64, 64, 128, 256)
DEFAULT_OPTIONS = {"min_depth": 0.1, "max_depth": 10.0}   # the NYU weights; KITTI: 1.0 / 80.0


class Encoder(nn.Module):
    """Holds the DenseNet as ``original_model`` (the authors' name), without its classifier."""

    def __init__(self):
        super().__init__()
        self.original_model = DenseNet(DENSENET169, with_classifier=False)

    def forward(self, x: torch.Tensor):
        return self.original_model.forward_features(x)


class UpSample(nn.Module):
    """Bilinear upsampling to the skip's size, concatenation, conv 3×3, conv 3×3, LeakyReLU(0.2).

    The released weights were trained with no activation between convA and convB; keep it that way.
    """

    def __init__(self, in_channels: int, out_channels: int):
        super().__init__()
        self.convA = nn.Conv2d(in_channels, out_channels, kernel_size=3, stride=1, padding=1)
        self.convB = nn.Conv2d(out_channels, out_channels, kernel_size=3, stride=1, padding=1)
        self.leakyreluB = nn.LeakyReLU(0.2)

    def forward(self, x: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
        return self.leakyreluB(self.convB(self.convA(upsample_concat(x, skip, align_corners=True))))


class Decoder(nn.Module):
    def __init__(self, bottleneck_channels: int = 1664, width: float = 1.0):
        super().__init__()
        features = int(bottleneck_channels * width)
        self.conv2 = nn.Conv2d(bottleneck_channels, features, kernel_size=1, stride=1, padding=0)
        widths = [features // 2 ** i for i in range(5)]      # 1664, 832, 416, 208, 104
        skips = SKIP_CHANNELS[::-1]                          # coarsest skip first
        self.up1 = UpSample(widths[0] + skips[0], widths[1])
        self.up2 = UpSample(widths[1] + skips[1], widths[2])
        self.up3 = UpSample(widths[2] + skips[2], widths[3])
        self.up4 = UpSample(widths[3] + skips[3], widths[4])
        self.conv3 = nn.Conv2d(widths[4], 1, kernel_size=3, stride=1, padding=1)

    def forward(self, feats) -> torch.Tensor:
        x = self.conv2(F.relu(feats["norm5"]))
        x = self.up1(x, feats[SKIP_POINTS[3]])
        x = self.up2(x, feats[SKIP_POINTS[2]])
        x = self.up3(x, feats[SKIP_POINTS[1]])
        x = self.up4(x, feats[SKIP_POINTS[0]])
        return self.conv3(x)


class DenseDepth(nn.Module):
    """NCHW RGB/255 in, (y,) out with y = max_depth / depth at half resolution (N×1×H/2×W/2)."""

    def __init__(self):
        super().__init__()
        self.encoder = Encoder()
        self.decoder = Decoder()

    def forward(self, x: torch.Tensor) -> Tuple[torch.Tensor]:
        return (self.decoder(self.encoder(x)),)


def build(task: Task = Task.DEPTH, **options) -> DenseDepth:
    _check_task(task)
    return DenseDepth()


def contract(task: Task, height: int, width: int, **options) -> ModelContract:
    _check_task(task)
    opts = merged_options(DEFAULT_OPTIONS, options)
    return ModelContract(
        arch="densedepth", task=Task.DEPTH,
        input=InputSpec(name=INPUT_NAME, layout=Layout.NCHW, height=height, width=width),
        depth=DepthSpec(output=OUTPUT_DEPTH, convention=DepthConvention.INVERSE, min_depth=float(opts["min_depth"]),
                        max_depth=float(opts["max_depth"]), stride=2, layout=Layout.NCHW))


def output_names(task: Task) -> Tuple[str, ...]:
    _check_task(task)
    return (OUTPUT_DEPTH,)


def load_checkpoint(module: nn.Module, path) -> dict:
    """The authors' PyTorch state_dict (with or without the unused classifier, with or without ``module.``)."""
    where = str(path)
    state = model_state(read_checkpoint(path), where)
    had_classifier = any(k.startswith(CLASSIFIER_PREFIX) for k in state)
    load_state_dict_strict(module, drop_keys(state, CLASSIFIER_PREFIX), where)
    return {**source_info(Path(path)), "format": "densedepth-pytorch-state_dict",
            "dropped_classifier": had_classifier}


def _check_task(task: Task) -> None:
    require_task("densedepth", task, (Task.DEPTH,))


ARCH_SPEC = ArchSpec(
    name="densedepth",
    paper="Alhashim & Wonka, High Quality Monocular Depth Estimation via Transfer Learning, arXiv:1812.11941 (2018)",
    tasks=(Task.DEPTH,),
    default_task=Task.DEPTH,
    input_hw=(480, 640),
    size_multiple=32,
    build=build,
    contract=contract,
    output_names=output_names,
    load_checkpoint=load_checkpoint,
    options=dict(DEFAULT_OPTIONS),
    min_hw=(64, 64),
)
