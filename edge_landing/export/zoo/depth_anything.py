"""Depth Anything V2 Small, the architecture only: a speed peer for edge-bench (random weights, never trained here).

What a user would pick for monocular depth today. Built with Hugging Face transformers'
``DepthAnythingForDepthEstimation`` from the published Small configuration (DINOv2 ViT-S/14 backbone:
hidden 384, 12 layers, 6 heads, features from layers 3/6/9/12; DPT neck 48/96/192/384, fusion 64, head 32),
with random weights: the ONNX file is for timing only and its outputs mean nothing. Requires the
``transformers`` package (not part of any extra: edge-bench leaves the row out when it is missing).

The network sees the input floored to whole 14-pixel patches (240x320 -> 17x22 patches = 238x308 pixels) and
its relative inverse depth is resized back to the input size, as the authors' pipeline does.
"""
from __future__ import annotations

from typing import Tuple

from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.perception.contract import DepthConvention, DepthSpec, InputSpec, Layout, ModelContract, Task

from .common import IMAGENET_MEAN, IMAGENET_STD, INPUT_NAME, OUTPUT_DEPTH
from .registry import ArchSpec, require_task

# depth-anything/Depth-Anything-V2-Small-hf config.json (the published Small sizes)
SMALL = {"hidden_size": 384, "num_hidden_layers": 12, "num_attention_heads": 6, "patch_size": 14,
         "out_indices": [3, 6, 9, 12], "neck_hidden_sizes": [48, 96, 192, 384], "fusion_hidden_size": 64,
         "head_hidden_size": 32, "reassemble_factors": [4, 2, 1, 0.5]}


def _config():
    try:
        from transformers import DepthAnythingConfig, Dinov2Config
    except ImportError:
        raise InputError("depth-anything-v2-small needs the transformers package (pip install transformers)") from None
    backbone = Dinov2Config(hidden_size=SMALL["hidden_size"], num_hidden_layers=SMALL["num_hidden_layers"],
                            num_attention_heads=SMALL["num_attention_heads"], patch_size=SMALL["patch_size"],
                            image_size=518, out_indices=SMALL["out_indices"], reshape_hidden_states=False,
                            apply_layernorm=True, mlp_ratio=4, layerscale_value=1.0)
    return DepthAnythingConfig(backbone_config=backbone, neck_hidden_sizes=SMALL["neck_hidden_sizes"],
                               fusion_hidden_size=SMALL["fusion_hidden_size"],
                               head_hidden_size=SMALL["head_hidden_size"], reassemble_factors=SMALL["reassemble_factors"],
                               patch_size=SMALL["patch_size"], depth_estimation_type="relative")


def build(task: Task = Task.DEPTH, seed: int = 0, **_options):
    import torch
    from torch import nn
    from transformers import DepthAnythingForDepthEstimation

    require_task("depth-anything-v2-small", task, (Task.DEPTH,))
    torch.manual_seed(seed)
    config = _config()
    config._attn_implementation = "eager"     # plain matmul + softmax: exports to ONNX everywhere

    class Wrapper(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.net = DepthAnythingForDepthEstimation(config)

        def forward(self, x):
            y = self.net(pixel_values=x).predicted_depth[:, None]
            return (nn.functional.interpolate(y, size=x.shape[-2:], mode="bilinear", align_corners=False),)

    return Wrapper().eval()


def contract(task: Task, height: int, width: int, **_options) -> ModelContract:
    require_task("depth-anything-v2-small", task, (Task.DEPTH,))
    # relative inverse depth: INVERSE with a nominal range (random weights; speed only)
    return ModelContract(arch="depth-anything-v2-small", task=Task.DEPTH,
                         input=InputSpec(name=INPUT_NAME, layout=Layout.NCHW, height=height, width=width,
                                         mean=IMAGENET_MEAN, std=IMAGENET_STD),
                         depth=DepthSpec(output=OUTPUT_DEPTH, convention=DepthConvention.INVERSE, min_depth=0.1,
                                         max_depth=100.0, stride=1, layout=Layout.NCHW))


def output_names(task: Task) -> Tuple[str, ...]:
    return (OUTPUT_DEPTH,)


def load_checkpoint(module, path) -> dict:
    raise InputError("depth-anything-v2-small is a speed peer with random weights; no checkpoint format is supported")


ARCH_SPEC = ArchSpec(
    name="depth-anything-v2-small",
    paper="Yang et al., Depth Anything V2, arXiv:2406.09414 (2024): Small variant, 24.8 M parameters",
    tasks=(Task.DEPTH,),
    default_task=Task.DEPTH,
    input_hw=(518, 518),
    size_multiple=2,
    build=build,
    contract=contract,
    output_names=output_names,
    load_checkpoint=load_checkpoint,
    options={},
    min_hw=(28, 28),
)
