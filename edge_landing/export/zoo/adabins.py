"""AdaBins (Bhat, Alhashim & Wonka 2020): EfficientNet-B5 U-Net + mini-ViT adaptive bins, metric depth.

Re-implemented from the facts in reference/models.md, keeping the authors' parameter names so that their
checkpoints load by name::

    spec = get_arch("adabins")
    net = spec.build(Task.DEPTH, bins=256, max_depth=10.0).eval()
    bin_edges, depth = net(x)          # x: N×3×H×W, (rgb/255 - ImageNet mean) / std
    # bin_edges: N×(bins+1) metres; depth: N×1×H/2×W/2 metres

The transformer reads 16×16 patches of the half-resolution decoder map: token 0 regresses the bin widths,
tokens 1..128 become 128 range-attention maps. So the half-resolution map must hold at least 129 patches
and at most 500 (the learned positional table); :func:`check_input_size` enforces both.
"""
from __future__ import annotations

from pathlib import Path
from typing import Dict, List, Tuple

import torch
import torch.nn.functional as F
from torch import nn

from edge_landing.export.checkpoints import load_state_dict_strict, model_state, read_checkpoint, source_info
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.perception.contract import (
    DepthConvention,
    DepthSpec,
    InputSpec,
    Layout,
    ModelContract,
    Task,
)

from .common import IMAGENET_MEAN, IMAGENET_STD, INPUT_NAME, OUTPUT_DEPTH, merged_options, upsample_concat
from .efficientnet import EFFICIENTNET_B5_TF, EfficientNet
from .registry import ArchSpec, require_task

OUTPUT_BIN_EDGES = "bin_edges"
DEFAULT_OPTIONS = {"bins": 256, "min_depth": 1e-3, "max_depth": 10.0}
MAX_BINS = 4096   # the paper uses 80 and 256

SIZE_MULTIPLE = 32          # every encoder stage then halves the map exactly, as at the authors' sizes
PATCH_SIZE = 16
EMBEDDING_DIM = 128         # also the decoder's output width and the number of range-attention queries
N_QUERIES = 128
MAX_PATCHES = 500           # rows of the learned positional table
DECODER_FEATURES = 2048
SKIP_STAGES = (0, 1, 2, 4)  # encoder stages whose outputs feed the decoder (strides 2, 4, 8, 16)
LEAKY_SLOPE = 0.01          # nn.LeakyReLU's default, as the authors use it

# Renames of older AdaBins releases (their model_io.load_checkpoint maps these prefixes the same way).
OLD_KEY_PREFIXES = (
    ("adaptive_bins_layer.embedding_conv.", "adaptive_bins_layer.conv3x3."),
    ("adaptive_bins_layer.patch_transformer.embedding_encoder.",
     "adaptive_bins_layer.patch_transformer.embedding_convPxP."),
)


def patch_count(height: int, width: int) -> int:
    """How many 16×16 patches the half-resolution decoder map of an H×W input holds."""
    return (height // 2 // PATCH_SIZE) * (width // 2 // PATCH_SIZE)


def check_input_size(height: int, width: int) -> None:
    """One InputError unless H×W is a multiple of 32 and gives between 129 and 500 transformer patches."""
    if height <= 0 or width <= 0 or height % SIZE_MULTIPLE or width % SIZE_MULTIPLE:
        raise InputError(f"adabins input {height}x{width}: height and width must be positive multiples of "
                         f"{SIZE_MULTIPLE} (e.g. 480x640)")
    n = patch_count(height, width)
    if n < N_QUERIES + 1:
        raise InputError(f"adabins input {height}x{width} gives {n} patches of {PATCH_SIZE}x{PATCH_SIZE} at half "
                         f"resolution; the mViT needs at least {N_QUERIES + 1} (128 range-attention queries plus "
                         f"the bin token), e.g. 320x448 or larger")
    if n > MAX_PATCHES:
        raise InputError(f"adabins input {height}x{width} gives {n} patches at half resolution; the positional "
                         f"table holds at most {MAX_PATCHES} (e.g. 480x640 gives 300, 352x1216 gives 418)")


class Encoder(nn.Module):
    """Wraps the backbone as ``original_model`` (the checkpoint prefix) and returns the decoder's inputs."""

    def __init__(self):
        super().__init__()
        self.original_model = EfficientNet(EFFICIENTNET_B5_TF)

    def forward(self, x: torch.Tensor) -> List[torch.Tensor]:
        feats = self.original_model.forward_features(x)
        # skips at strides 2, 4, 8, 16, then conv_head's output before its BN (the authors' bottleneck)
        return [feats[i] for i in SKIP_STAGES] + [feats[-1]]


class UpSampleBN(nn.Module):
    """Bilinear upsample (align_corners) to the skip's size, concat, then 2 × (conv3×3, BN, LeakyReLU)."""

    def __init__(self, in_channels: int, out_channels: int):
        super().__init__()
        self._net = nn.Sequential(
            nn.Conv2d(in_channels, out_channels, 3, padding=1), nn.BatchNorm2d(out_channels),
            nn.LeakyReLU(LEAKY_SLOPE),
            nn.Conv2d(out_channels, out_channels, 3, padding=1), nn.BatchNorm2d(out_channels),
            nn.LeakyReLU(LEAKY_SLOPE))

    def forward(self, x: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
        return self._net(upsample_concat(x, skip, align_corners=True))


class DecoderBN(nn.Module):
    def __init__(self, skip_channels: Tuple[int, ...], out_channels: int = EMBEDDING_DIM):
        super().__init__()
        f = DECODER_FEATURES
        # padding=1 on a 1×1 conv grows the map by a pixel each side; kept because the weights were trained so
        self.conv2 = nn.Conv2d(f, f, 1, padding=1)
        s0, s1, s2, s3 = skip_channels
        self.up1 = UpSampleBN(f + s3, f // 2)
        self.up2 = UpSampleBN(f // 2 + s2, f // 4)
        self.up3 = UpSampleBN(f // 4 + s1, f // 8)
        self.up4 = UpSampleBN(f // 8 + s0, f // 16)
        self.conv3 = nn.Conv2d(f // 16, out_channels, 3, padding=1)

    def forward(self, feats: List[torch.Tensor]) -> torch.Tensor:
        s0, s1, s2, s3, bottleneck = feats
        x = self.conv2(bottleneck)
        x = self.up1(x, s3)
        x = self.up2(x, s2)
        x = self.up3(x, s1)
        return self.conv3(self.up4(x, s0))


class PatchTransformerEncoder(nn.Module):
    """16×16 patch embedding + learned positions + 4 post-norm transformer layers (sequence first)."""

    def __init__(self, in_channels: int, patch_size: int = PATCH_SIZE, dim: int = EMBEDDING_DIM, heads: int = 4,
                 layers: int = 4, feedforward: int = 1024):
        super().__init__()
        layer = nn.TransformerEncoderLayer(dim, heads, dim_feedforward=feedforward)
        # enable_nested_tensor only matters for padded batches, which never occur here
        self.transformer_encoder = nn.TransformerEncoder(layer, num_layers=layers, enable_nested_tensor=False)
        self.embedding_convPxP = nn.Conv2d(in_channels, dim, patch_size, stride=patch_size)
        self.positional_encodings = nn.Parameter(torch.rand(MAX_PATCHES, dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        emb = self.embedding_convPxP(x).flatten(2)                         # N, E, S
        emb = emb + self.positional_encodings[:emb.shape[2], :].T.unsqueeze(0)
        return self.transformer_encoder(emb.permute(2, 0, 1))              # S, N, E


class MiniViT(nn.Module):
    """Bin-width regression from token 0 and 128 range-attention maps from tokens 1..128 ('linear' norm)."""

    def __init__(self, in_channels: int, n_bins: int, dim: int = EMBEDDING_DIM, n_queries: int = N_QUERIES):
        super().__init__()
        self.n_queries = n_queries
        self.patch_transformer = PatchTransformerEncoder(in_channels, dim=dim)
        self.conv3x3 = nn.Conv2d(in_channels, dim, 3, padding=1)
        self.regressor = nn.Sequential(nn.Linear(dim, 256), nn.LeakyReLU(LEAKY_SLOPE), nn.Linear(256, 256),
                                       nn.LeakyReLU(LEAKY_SLOPE), nn.Linear(256, n_bins))

    def forward(self, x: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        tokens = self.patch_transformer(x)
        feats = self.conv3x3(x)
        queries = tokens[1:self.n_queries + 1].permute(1, 0, 2)          # N, Q, E
        n, c, h, w = feats.shape
        maps = torch.matmul(queries, feats.reshape(n, c, h * w)).reshape(n, queries.shape[1], h, w)
        y = torch.relu(self.regressor(tokens[0])) + 0.1                   # 'linear' norm: every bin keeps width
        return y / y.sum(dim=1, keepdim=True), maps


class AdaBins(nn.Module):
    """ImageNet-normalised NCHW in; (bin_edges N×(bins+1), depth N×1×H/2×W/2), both in metres."""

    def __init__(self, bins: int = 256, min_depth: float = 1e-3, max_depth: float = 10.0):
        super().__init__()
        if bins < 2 or not 0 < min_depth < max_depth:
            raise InputError(f"adabins needs bins >= 2 and 0 < min_depth < max_depth, got bins={bins}, "
                             f"min_depth={min_depth}, max_depth={max_depth}")
        self.bins, self.min_depth, self.max_depth = int(bins), float(min_depth), float(max_depth)
        self.encoder = Encoder()
        skips = tuple(EFFICIENTNET_B5_TF.stage_channels[i] for i in SKIP_STAGES)
        self.decoder = DecoderBN(skips)
        self.adaptive_bins_layer = MiniViT(EMBEDDING_DIM, self.bins)
        self.conv_out = nn.Sequential(nn.Conv2d(N_QUERIES, self.bins, 1), nn.Softmax(dim=1))

    def forward(self, x: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        features = self.decoder(self.encoder(x))
        widths_normed, maps = self.adaptive_bins_layer(features)
        probs = self.conv_out(maps)
        widths = (self.max_depth - self.min_depth) * widths_normed
        edges = torch.cumsum(F.pad(widths, (1, 0), value=self.min_depth), dim=1)
        centres = 0.5 * (edges[:, :-1] + edges[:, 1:])
        depth = torch.sum(probs * centres[:, :, None, None], dim=1, keepdim=True)
        return edges, depth


def build(task: Task = Task.DEPTH, bins: int = 256, min_depth: float = 1e-3, max_depth: float = 10.0,
          **_ignored) -> AdaBins:
    # Callers pass every arch's options generically; the exporter has already refused unknown ones.
    _check_task(task)
    return AdaBins(bins=bins, min_depth=min_depth, max_depth=max_depth)


def contract(task: Task, height: int, width: int, **options) -> ModelContract:
    _check_task(task)
    check_input_size(height, width)
    opts = merged_options(DEFAULT_OPTIONS, options)
    bins = opts["bins"]   # checked here too: the contract comes before the (slow) build
    if not (float(bins).is_integer() and 2 <= bins <= MAX_BINS):
        raise InputError(f"adabins bins must be a whole number between 2 and {MAX_BINS}, got {bins}")
    return ModelContract(
        arch="adabins", task=Task.DEPTH,
        input=InputSpec(name=INPUT_NAME, layout=Layout.NCHW, height=height, width=width, scale=1.0 / 255.0,
                        mean=IMAGENET_MEAN, std=IMAGENET_STD),
        depth=DepthSpec(output=OUTPUT_DEPTH, convention=DepthConvention.METRIC, min_depth=float(opts["min_depth"]),
                        max_depth=float(opts["max_depth"]), stride=2, layout=Layout.NCHW))


def output_names(task: Task) -> Tuple[str, ...]:
    _check_task(task)
    return (OUTPUT_BIN_EDGES, OUTPUT_DEPTH)


def rename_old_keys(state_dict: Dict[str, torch.Tensor]) -> Tuple[Dict[str, torch.Tensor], int]:
    """Map the module names of older AdaBins releases to the current ones; returns (state_dict, renamed)."""
    out, renamed = {}, 0
    for key, value in state_dict.items():
        for old, new in OLD_KEY_PREFIXES:
            if key.startswith(old):
                key, renamed = new + key[len(old):], renamed + 1
                break
        out[key] = value
    return out, renamed


def load_checkpoint(module: nn.Module, path) -> dict:
    """The authors' ``{'model': state_dict, 'optimizer', 'epoch'}`` (or a bare state_dict), with or without
    ``module.`` prefixes and with the older mViT module names; strict by name and shape."""
    where = str(path)
    obj = read_checkpoint(path)
    state, renamed = rename_old_keys(model_state(obj, where))
    load_state_dict_strict(module, state, where)
    info = {**source_info(Path(path)), "format": "adabins-pytorch-checkpoint", "renamed_old_keys": renamed}
    if isinstance(obj, dict) and isinstance(obj.get("epoch"), int):
        info["epoch"] = obj["epoch"]
    return info


def _check_task(task: Task) -> None:
    require_task("adabins", task, (Task.DEPTH,))


ARCH_SPEC = ArchSpec(
    name="adabins",
    paper="Bhat, Alhashim & Wonka, AdaBins: Depth Estimation using Adaptive Bins, CVPR 2021 (arXiv:2011.14141)",
    tasks=(Task.DEPTH,),
    default_task=Task.DEPTH,
    input_hw=(480, 640),
    size_multiple=SIZE_MULTIPLE,
    build=build,
    contract=contract,
    output_names=output_names,
    load_checkpoint=load_checkpoint,
    options=dict(DEFAULT_OPTIONS),
    min_hw=(320, 448),
)
