"""SafeUAV-Net Large and Small (Marcu et al., ECCV Workshops 2018), re-implemented from reference/models.md.

Both take and return NHWC tensors (the transposes are inside, as in the authors' code), RGB min-max scaled
to [0, 1], at sizes divisible by 8. Heads: 3 HVO logits or 1 depth channel with metres = y · 323.485.
The authors' ``.pkl`` checkpoints hold an ordered list of tensors without names, so the modules below are
registered in exactly the authors' order and loaded by position::

    spec = get_arch("safeuav-small")
    model = spec.build(Task.HVO)                        # 1,029,283 parameters
    spec.load_checkpoint(model, "safeuav_small_hvo.pkl")
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable, Optional, Tuple

import torch
from torch import nn
from torch.nn import functional as F

from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.perception.contract import (
    DepthConvention,
    DepthSpec,
    HvoSpec,
    InputSpec,
    Layout,
    ModelContract,
    Task,
)

from ..checkpoints import (
    load_ordered_tensors,
    ordered_tensor_list,
    read_checkpoint,
    source_info,
)
from .common import INPUT_NAME, OUTPUT_DEPTH, OUTPUT_HVO, merged_options
from .registry import ArchSpec

MAX_DEPTH_M = 323.485          # the dataset's depth normaliser: target = metres / 323.485
DEFAULT_OPTIONS = {"min_depth": 0.1, "max_depth": MAX_DEPTH_M}
DILATIONS = (1, 2, 4, 8, 16, 32)


def _conv3(c_in: int, c_out: int, dilation: int = 1, stride: int = 1) -> nn.Conv2d:
    return nn.Conv2d(c_in, c_out, kernel_size=3, stride=stride, padding=dilation, dilation=dilation)


def _out_channels(task: Task) -> int:
    if task is Task.HVO:
        return 3
    if task is Task.DEPTH:
        return 1
    raise InputError(f"SafeUAV-Net has one head per network; task '{task}' is not available "
                     f"(expected 'hvo' or 'depth')")


class _NhwcNet(nn.Module):
    """NHWC in, NHWC out; subclasses implement ``forward_nchw``."""

    forward_nchw: Callable[[torch.Tensor], torch.Tensor]

    def forward(self, x: torch.Tensor) -> Tuple[torch.Tensor]:
        y = self.forward_nchw(x.permute(0, 3, 1, 2))
        return (y.permute(0, 2, 3, 1),)


# -- Large: unet_big_concatenate ------------------------------------------------------------------------
class UNetBlock(nn.Module):
    """Two 3×3 convolutions, each followed by ReLU (size preserving)."""

    def __init__(self, c_in: int, c_out: int):
        super().__init__()
        self.conv1 = _conv3(c_in, c_out)
        self.conv2 = _conv3(c_out, c_out)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.relu(self.conv2(F.relu(self.conv1(x))))


class _UpSampleLayer(nn.Module):
    def __init__(self, c_in: int, c_out: int):
        super().__init__()
        self.upSample = nn.ConvTranspose2d(c_in, c_out, kernel_size=3, stride=2, padding=0)


class _ConvTransposed(nn.Module):
    def __init__(self, c_in: int, c_out: int):
        super().__init__()
        self.upSampleLayer = _UpSampleLayer(c_in, c_out)


class UpConv(nn.Module):
    """Transposed conv (k3, s2, no padding: 2H+1 rows), ReLU, crop the last row and column -> exactly 2H.

    The nesting (``convt.upSampleLayer.upSample``) only mirrors the authors' parameter names.
    """

    def __init__(self, c_in: int, c_out: int):
        super().__init__()
        self.convt = _ConvTransposed(c_in, c_out)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.relu(self.convt.upSampleLayer.upSample(x))[:, :, :-1, :-1]


class DilatedBottleneck(nn.Module):
    """Six serial dilated 3×3 convs (256→512, then 512→512), outputs concatenated (3072 ch), UpConv, then
    concatenated after the skip: cat([skip, up]) as the authors' ConcatenateBlock does."""

    def __init__(self, c_in: int, width: int, c_out: int):
        super().__init__()
        self.dilateLayers = nn.ModuleList(
            [_conv3(c_in if i == 0 else width, width, dilation=d) for i, d in enumerate(DILATIONS)])
        self.finalLayer = UpConv(width * len(DILATIONS), c_out)

    def forward(self, x: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
        outs = []
        for conv in self.dilateLayers:
            x = F.relu(conv(x))
            outs.append(x)
        # The authors concatenate [skip, upsampled] (skip channels first); the order matters to the weights.
        return torch.cat([skip, self.finalLayer(torch.cat(outs, dim=1))], dim=1)


class SafeUAVLarge(_NhwcNet):
    def __init__(self, task: Task = Task.HVO, filters: int = 64):
        super().__init__()
        f = filters
        # Registration order == the order of the tensors in the authors' checkpoints.
        self.downBlock1 = UNetBlock(3, f)
        self.downBlock2 = UNetBlock(f, 2 * f)
        self.downBlock3 = UNetBlock(2 * f, 4 * f)
        self.bottleneck = DilatedBottleneck(4 * f, 8 * f, 4 * f)
        self.upBlock3 = UNetBlock(8 * f, 4 * f)
        self.up2 = UpConv(4 * f, 2 * f)
        self.upBlock2 = UNetBlock(4 * f, 2 * f)
        self.up1 = UpConv(2 * f, f)
        self.upBlock1 = UNetBlock(2 * f, f)
        self.finalConv = nn.Conv2d(f, _out_channels(task), kernel_size=1)

    def forward_nchw(self, x: torch.Tensor) -> torch.Tensor:
        d1 = self.downBlock1(x)
        d2 = self.downBlock2(F.max_pool2d(d1, 2))
        d3 = self.downBlock3(F.max_pool2d(d2, 2))
        y = self.upBlock3(self.bottleneck(F.max_pool2d(d3, 2), d3))
        # neural-wrappers' ConcatenateBlock: cat([x_down, y_up]) -- the skip comes first.
        y = self.upBlock2(torch.cat([d2, self.up2(y)], dim=1))
        y = self.upBlock1(torch.cat([d1, self.up1(y)], dim=1))
        return self.finalConv(y)


# -- Small: unet_tiny_sum -------------------------------------------------------------------------------
class SafeUAVSmall(_NhwcNet):
    def __init__(self, task: Task = Task.HVO, filters: int = 16):
        super().__init__()
        f = filters
        # Registration order == the order of the tensors in the authors' checkpoints.
        self.down1 = _conv3(3, f)
        self.down1pool = _conv3(f, f, stride=2)
        self.down2 = _conv3(f, 2 * f)
        self.down2pool = _conv3(2 * f, 2 * f, stride=2)
        self.down3 = _conv3(2 * f, 4 * f)
        self.down3pool = _conv3(4 * f, 4 * f, stride=2)
        self.dilate1 = _conv3(4 * f, 8 * f, dilation=DILATIONS[0])
        for i, d in enumerate(DILATIONS[1:], start=2):
            setattr(self, f"dilate{i}", _conv3(8 * f, 8 * f, dilation=d))
        self.up3_tr = nn.ConvTranspose2d(8 * f, 4 * f, kernel_size=3, stride=2, padding=1)
        self.up3 = _conv3(4 * f, 4 * f)
        self.up2_tr = nn.ConvTranspose2d(4 * f, 2 * f, kernel_size=3, stride=2, padding=1)
        self.up2 = _conv3(2 * f, 2 * f)
        self.up1_tr = nn.ConvTranspose2d(2 * f, f, kernel_size=3, stride=2, padding=1)
        self.up1 = _conv3(f, f)
        self.finalConv = nn.Conv2d(f, _out_channels(task), kernel_size=1)

    @staticmethod
    def _up(tr: nn.ConvTranspose2d, conv: nn.Conv2d, x: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
        # k3/s2/p1 gives 2H-1 rows: pad right and bottom by one to reach the skip's 2H, then add it.
        y = F.pad(F.relu(tr(x)), (0, 1, 0, 1))
        return F.relu(conv(y + skip))

    def forward_nchw(self, x: torch.Tensor) -> torch.Tensor:
        d1 = F.relu(self.down1(x))
        d2 = F.relu(self.down2(F.relu(self.down1pool(d1))))
        d3 = F.relu(self.down3(F.relu(self.down2pool(d2))))
        y = F.relu(self.down3pool(d3))
        total: Optional[torch.Tensor] = None
        for i in range(1, len(DILATIONS) + 1):
            y = F.relu(getattr(self, f"dilate{i}")(y))
            total = y if total is None else total + y
        assert total is not None    # DILATIONS is not empty
        y = self._up(self.up3_tr, self.up3, total, d3)
        y = self._up(self.up2_tr, self.up2, y, d2)
        y = self._up(self.up1_tr, self.up1, y, d1)
        return self.finalConv(y)


# -- ArchSpec plumbing ----------------------------------------------------------------------------------
def output_names(task: Task) -> Tuple[str, ...]:
    _out_channels(task)
    return (OUTPUT_HVO,) if task is Task.HVO else (OUTPUT_DEPTH,)


def _contract_for(arch: str):
    def contract(task: Task, height: int, width: int, **options) -> ModelContract:
        _out_channels(task)
        opts = merged_options(DEFAULT_OPTIONS, options)
        return ModelContract(
            arch=arch, task=task,
            input=InputSpec(name=INPUT_NAME, layout=Layout.NHWC, height=height, width=width),
            depth=(DepthSpec(output=OUTPUT_DEPTH, convention=DepthConvention.NORMALIZED,
                             min_depth=float(opts["min_depth"]), max_depth=float(opts["max_depth"]),
                             stride=1, layout=Layout.NHWC) if task is Task.DEPTH else None),
            hvo=HvoSpec(output=OUTPUT_HVO, layout=Layout.NHWC) if task is Task.HVO else None)
    return contract


def load_checkpoint(module: nn.Module, path) -> dict:
    """The authors' ``.pkl``: torch.save of a dict with "weights" (older files: "params") = ordered tensors."""
    where = str(path)
    obj = read_checkpoint(path)
    key = "weights" if isinstance(obj, dict) and "weights" in obj else "params"
    load_ordered_tensors(module, ordered_tensor_list(obj, where), where)
    return {**source_info(Path(path)), "format": f"safeuav-pkl[{key}]"}


def _spec(name: str, net, paper_name: str) -> ArchSpec:
    return ArchSpec(
        name=name,
        paper=f"Marcu et al., SafeUAV: Learning to estimate depth and safe landing areas for UAVs from synthetic "
              f"data, ECCV Workshops 2018 ({paper_name})",
        tasks=(Task.HVO, Task.DEPTH),
        default_task=Task.HVO,
        input_hw=(240, 320),
        size_multiple=8,
        build=lambda task=Task.HVO, **options: net(task),
        contract=_contract_for(name),
        output_names=output_names,
        load_checkpoint=load_checkpoint,
        options=dict(DEFAULT_OPTIONS),
        min_hw=(16, 16),
    )


ARCH_SPECS = {
    "safeuav-large": _spec("safeuav-large", SafeUAVLarge, "unet_big_concatenate"),
    "safeuav-small": _spec("safeuav-small", SafeUAVSmall, "unet_tiny_sum"),
}
