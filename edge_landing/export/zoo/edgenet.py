"""EdgeNet: the project's joint depth + HVO network, sized for 2 CPU cores (ARCHITECTURE.md §1, §9).

One shared encoder (stride-2 stem, four stride-2 stages of plain 3×3 conv + BatchNorm + ReLU, dilated
context at 1/16), one shared U-Net decoder (bilinear ×2 upsample + concat skip + 3×3 conv) back to 1/2
resolution, and two light heads: depth (1 channel) and HVO logits (3 channels), both at stride 2.

Why these choices: plain 3×3 convolutions at low width (depthwise convs are memory-bound on CPU and quantize
poorly), and a decoder that stops at 1/2 resolution (full-resolution layers are the most expensive ones, and
the fusion works at ~120×160 anyway). Only Conv, Relu, Concat, Resize, Clip, Mul/Add and Exp reach the ONNX
graph (plus Shape/Slice for the resize sizes, constant-folded at load since the input size is fixed); BatchNorm
is folded into the convolutions by ONNX Runtime.

Width chosen by measurement (ONNX Runtime FP32, 2 threads, 240×320, p50 of 50 runs after warm-up, best of 3
interleaved rounds, quiet machine; edgenet.json has the full record):

    channels  params  GMAC   p50 ms  images/s        SafeUAV-Net-Small (same run): 1.03 M, 2.12 GMAC, 23.2 ms, 43/s
    12        238 k   0.32   5.9     169
    16        422 k   0.57   6.9     145   <- shipped (INT8: 3.15 ms, 318 images/s)
    24        949 k   1.27   17.6    57

Depth: the network regresses t = normalised log depth, t = (ln d − ln d_min) / (ln d_max − ln d_min), and
``forward`` returns metres = exp(t · span + ln d_min) so the contract's convention is ``metric``. Log depth
because an oblique camera 30–90 m up sees 30 m to 1 km in one image: an L1 on metres would be dominated by
the horizon, and in log space a wrong global scale (unknowable from one image) is only a constant offset
that the per-scene calibration removes.

    spec = get_arch("edgenet")
    model = spec.build(Task.DEPTH_HVO, channels=16)
    depth_m, hvo_logits = model(x)                       # x: N×3×240×320, (rgb/255 − mean)/std
"""
from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Tuple, cast

import torch
from torch import nn

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

from ..checkpoints import load_state_dict_strict, model_state, read_checkpoint, source_info
from .common import IMAGENET_MEAN, IMAGENET_STD, INPUT_NAME, OUTPUT_DEPTH, OUTPUT_HVO, merged_options, upsample_concat
from .registry import ArchSpec

log = logging.getLogger(__name__)

# Depth range of the product (30–90 m above ground at 45° pitch: ~30 m below to ~1 km at the top rows).
DEFAULT_OPTIONS = {"channels": 16, "min_depth": 1.0, "max_depth": 1000.0}
OUTPUT_STRIDE = 2
SIZE_MULTIPLE = 8   # 1/16 maps may be odd-sized: each decoder step resizes to its skip's exact size
MAX_CHANNELS = 256  # base width: 16x the default already gives ~100 M parameters; more is a typo


class ConvBNReLU(nn.Sequential):
    def __init__(self, c_in: int, c_out: int, stride: int = 1, dilation: int = 1):
        super().__init__(
            nn.Conv2d(c_in, c_out, 3, stride=stride, padding=dilation, dilation=dilation, bias=False),
            nn.BatchNorm2d(c_out),
            nn.ReLU(inplace=True),
        )


class Stage(nn.Sequential):
    """Downsample by 2 then refine: conv s2 + conv (optionally more, dilated, for context)."""

    def __init__(self, c_in: int, c_out: int, dilations: Tuple[int, ...] = (1,)):
        super().__init__(ConvBNReLU(c_in, c_out, stride=2), *[ConvBNReLU(c_out, c_out, dilation=d) for d in dilations])


class UpFuse(nn.Module):
    """Bilinear ×2, concatenate the skip, one 3×3 conv."""

    def __init__(self, c_in: int, c_skip: int, c_out: int):
        super().__init__()
        self.conv = ConvBNReLU(c_in + c_skip, c_out)

    def forward(self, x: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
        return self.conv(upsample_concat(x, skip, align_corners=False))


class Head(nn.Sequential):
    def __init__(self, c_in: int, c_out: int):
        super().__init__(ConvBNReLU(c_in, c_in), nn.Conv2d(c_in, c_out, 1))


def channels_for(base: int) -> Tuple[int, int, int, int]:
    """Channels at strides 2, 4, 8, 16 for a base width."""
    return base, int(1.5 * base), 3 * base, 6 * base


class EdgeNet(nn.Module):
    def __init__(self, task: Task = Task.DEPTH_HVO, channels: int = 16, min_depth: float = 1.0,
                 max_depth: float = 1000.0):
        super().__init__()
        c1, c2, c3, c4 = channels_for(int(channels))
        self.task = task
        self.log_min = math.log(float(min_depth))
        self.log_span = math.log(float(max_depth)) - self.log_min
        self.stem = Stage(3, c1)                      # 1/2
        self.enc2 = Stage(c1, c2)                     # 1/4
        self.enc3 = Stage(c2, c3)                     # 1/8
        self.enc4 = Stage(c3, c4, dilations=(1, 2, 4))  # 1/16, receptive field covers the whole 15×20 map
        self.up3 = UpFuse(c4, c3, c3)
        self.up2 = UpFuse(c3, c2, c2)
        self.up1 = UpFuse(c2, c1, c1)
        self.depth_head = Head(c1, 1) if task.has_depth else None
        self.hvo_head = Head(c1, 3) if task.has_hvo else None
        if self.depth_head is not None:
            # Start in the middle of the log range (~30 m for 1..1000 m) rather than at 1 m.
            nn.init.constant_(cast(torch.Tensor, self.depth_head[-1].bias), 0.5)   # Head's last conv has a bias

    def features(self, x: torch.Tensor) -> torch.Tensor:
        e1 = self.stem(x)
        e2 = self.enc2(e1)
        e3 = self.enc3(e2)
        y = self.enc4(e3)
        y = self.up3(y, e3)
        y = self.up2(y, e2)
        return self.up1(y, e1)

    def forward(self, x: torch.Tensor) -> Tuple[torch.Tensor, ...]:
        f = self.features(x)
        outs = []
        if self.depth_head is not None:
            t = self.depth_head(f)
            # Clamp before exp so an untrained or diverging net cannot overflow to inf.
            outs.append(torch.exp(torch.clamp(t, -1.0, 2.0) * self.log_span + self.log_min))
        if self.hvo_head is not None:
            outs.append(self.hvo_head(f))
        return tuple(outs)


def output_names(task: Task) -> Tuple[str, ...]:
    return tuple(n for n, keep in ((OUTPUT_DEPTH, task.has_depth), (OUTPUT_HVO, task.has_hvo)) if keep)


def build(task: Task = Task.DEPTH_HVO, **options) -> EdgeNet:
    opts = merged_options(DEFAULT_OPTIONS, options)
    return EdgeNet(task, channels=int(opts["channels"]), min_depth=float(opts["min_depth"]),
                   max_depth=float(opts["max_depth"]))


def check_channels(channels) -> None:
    """The base width must be a whole number 1 .. MAX_CHANNELS (0 or less builds no network, more no sane one)."""
    if not (float(channels).is_integer() and 1 <= channels <= MAX_CHANNELS):
        raise InputError(f"edgenet channels must be a whole number between 1 and {MAX_CHANNELS}, got {channels}")


def contract(task: Task, height: int, width: int, **options) -> ModelContract:
    opts = merged_options(DEFAULT_OPTIONS, options)
    check_channels(opts["channels"])   # the contract comes before the build: refused before any work
    return ModelContract(
        arch="edgenet", task=task,
        input=InputSpec(name=INPUT_NAME, layout=Layout.NCHW, height=height, width=width,
                        mean=IMAGENET_MEAN, std=IMAGENET_STD),
        depth=(DepthSpec(output=OUTPUT_DEPTH, convention=DepthConvention.METRIC,
                         min_depth=float(opts["min_depth"]), max_depth=float(opts["max_depth"]),
                         stride=OUTPUT_STRIDE, layout=Layout.NCHW) if task.has_depth else None),
        hvo=HvoSpec(output=OUTPUT_HVO, layout=Layout.NCHW) if task.has_hvo else None)


def load_checkpoint(module: nn.Module, path) -> dict:
    """Our training checkpoints (export/train.py): a dict with the state_dict under "model"."""
    where = str(path)
    obj = read_checkpoint(path)
    load_state_dict_strict(module, model_state(obj, where), where)
    info = source_info(Path(path))
    if isinstance(obj, dict):
        # export/train.py stores its config and history as JSON strings: carry them into edge.source.
        if isinstance(obj.get("epoch"), int):
            info["epoch"] = obj["epoch"]
        for key, name in (("config", "train_config"), ("history", "history_last")):
            if isinstance(obj.get(key), str):
                try:
                    value = json.loads(obj[key])
                except json.JSONDecodeError:
                    continue
                info[name] = value[-1] if name == "history_last" and isinstance(value, list) and value else value
    return info


def _input_channel_map(name: str, old: Tuple[int, ...], new: Tuple[int, ...], old_in: int) -> torch.Tensor:
    """Where the narrow conv's input channels sit in the wide conv's input (decoder convs read [x, skip])."""
    splits = {"up3.conv": (3, 2), "up2.conv": (2, 1), "up1.conv": (1, 0)}   # (x, skip) indices into widths
    for prefix, (ix, isk) in splits.items():
        if name.startswith(prefix + "."):
            return torch.cat([torch.arange(old[ix]), new[ix] + torch.arange(old[isk])])
    return torch.arange(old_in)


def widen_state_dict(narrow: dict, model: nn.Module) -> dict:
    """A narrower EdgeNet's weights placed inside ``model`` so that the wide model computes the same outputs.

    Old channels keep their weights; each new channel keeps its random incoming weights (so it is active and
    learns) while every old channel's weights *from* new channels are zero (so nothing it computes changes).
    Heads keep their 1 or 3 outputs, so depth and HVO are exactly those of the narrow network.
    """
    wide = model.state_dict()
    old_w = channels_for(int(narrow["stem.0.0.weight"].shape[0]))
    new_w = channels_for(int(wide["stem.0.0.weight"].shape[0]))
    if any(o > n for o, n in zip(old_w, new_w)):
        raise InputError(f"cannot widen EdgeNet base width {old_w[0]} into {new_w[0]}: the checkpoint is wider")
    out = {}
    for name, target in wide.items():
        if name not in narrow:
            raise InputError(f"checkpoint has no parameter '{name}'; is it an EdgeNet checkpoint?")
        src = narrow[name]
        if tuple(src.shape) == tuple(target.shape):
            out[name] = src.clone()
            continue
        t = target.clone()
        n_out = src.shape[0]
        if t.dim() == 4:
            idx = _input_channel_map(name, old_w, new_w, src.shape[1])
            t[:n_out] = 0.0
            t[:n_out, idx] = src
        else:   # BatchNorm weight/bias/running stats, conv bias: old channels first, new ones keep their init
            t[:n_out] = src
        out[name] = t
    return out


def init_checkpoint(module: nn.Module, path) -> dict:
    """``edge-train --init``: our checkpoint, widened first when it was trained at a smaller base width."""
    where = str(path)
    state = model_state(read_checkpoint(path), where)
    narrow_width = state["stem.0.0.weight"].shape[0] if "stem.0.0.weight" in state else None
    wide_width = module.state_dict()["stem.0.0.weight"].shape[0]
    if narrow_width is None or narrow_width >= wide_width:
        return load_checkpoint(module, path)      # same width (or not ours): the strict loader names any mismatch
    load_state_dict_strict(module, widen_state_dict(state, module), where)
    log.info("widened %s from base width %d to %d", where, narrow_width, wide_width)
    return source_info(Path(path))


ARCH_SPEC = ArchSpec(
    name="edgenet",
    paper="this project: joint depth + HVO network for 2 CPU cores (the paper's future work)",
    tasks=(Task.DEPTH_HVO, Task.DEPTH, Task.HVO),
    default_task=Task.DEPTH_HVO,
    input_hw=(240, 320),
    size_multiple=SIZE_MULTIPLE,
    build=build,
    contract=contract,
    output_names=output_names,
    load_checkpoint=load_checkpoint,
    options=dict(DEFAULT_OPTIONS),
    min_hw=(32, 32),
    init_checkpoint=init_checkpoint,
)
