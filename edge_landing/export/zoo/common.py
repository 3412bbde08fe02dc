"""What the zoo's architectures share: tensor names, ImageNet normalisation, option merging, and the U-Net
decoders' upsample-and-concatenate step.

The step keeps each network's own module and parameter names (the authors' checkpoints load by name), so
only the parameter-free part is shared; the exported ONNX graph is the same Resize + Concat as before.
"""
from __future__ import annotations

from typing import Any, Dict, Mapping

import torch
from torch.nn import functional as F

# Names of the ONNX graph's input and outputs (the runtime's ModelContract refers to them).
INPUT_NAME = "image"
OUTPUT_DEPTH = "depth"
OUTPUT_HVO = "hvo_logits"
# torchvision's ImageNet statistics, applied by the runtime as (rgb/255 - mean) / std.
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def merged_options(defaults: Mapping[str, Any], options: Mapping[str, Any]) -> Dict[str, Any]:
    """``defaults`` overridden by the entries of ``options`` that this architecture knows (callers pass every
    architecture's options generically; the exporter has already refused unknown ones)."""
    return {**defaults, **{k: v for k, v in options.items() if k in defaults}}


def upsample_concat(x: torch.Tensor, skip: torch.Tensor, align_corners: bool) -> torch.Tensor:
    """``x`` (N×C×h×w) resized bilinearly to the skip's spatial size, then [x, skip] along the channels."""
    up = F.interpolate(x, size=skip.shape[2:], mode="bilinear", align_corners=align_corners)
    return torch.cat([up, skip], dim=1)
