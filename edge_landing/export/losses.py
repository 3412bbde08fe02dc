"""Training losses: DenseDepth's depth loss on valid pixels and HVO cross-entropy (reference/models.md).

Depth loss (Alhashim & Wonka 2018): 0.1·L1 + L1 of the image gradients + (1 − SSIM)/2 clipped to [0, 1],
computed in a *loss space* chosen from the model's depth convention (``DepthLossSpace``):

- ``metric`` (EdgeNet, AdaBins): normalised log depth t = (ln d − ln d_min)/(ln d_max − ln d_min) ∈ [0, 1].
  An oblique view spans 30 m to 1 km: in metres the far rows would dominate the L1; in log space relative
  errors count the same everywhere and a global scale error is a constant offset (the gradient term and
  SSIM's structure term ignore it; per-scene calibration removes it at run time).
- ``normalized`` (SafeUAV): y = d / max_depth, the authors' own target.
- ``inverse`` (DenseDepth): y = max_depth / d, rescaled by min/max into (0, 1].

Every term is averaged over valid pixels only (finite ground truth within [min, max]); sky is NaN and ignored.

    space = DepthLossSpace.from_spec(contract.depth)
    terms = depth_loss(space.output_to_loss(pred_m), space.target_to_loss(gt_m), space.valid(gt_m))
    terms["total"].backward()
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Dict

import torch
from torch.nn import functional as F

from edge_landing.runtime.core.labels import HVO_IGNORE
from edge_landing.runtime.perception.contract import (
    DepthConvention,
    DepthSpec,
)

# DenseDepth's weights: w_depth · L1 + w_grad · gradient L1 + w_ssim · (1 − SSIM)/2.
W_DEPTH, W_GRAD, W_SSIM = 0.1, 1.0, 1.0
SSIM_WINDOW = 7          # Gaussian window; 7 rather than 11 because our outputs are only 60×80 to 120×160
SSIM_SIGMA = 1.5
SSIM_C1, SSIM_C2 = 0.01 ** 2, 0.03 ** 2   # for values in [0, 1] (every loss space is)


@dataclass(frozen=True)
class DepthLossSpace:
    """Maps network outputs and metric ground truth into the space the loss is computed in."""

    convention: DepthConvention
    min_depth: float
    max_depth: float

    @staticmethod
    def from_spec(spec: DepthSpec) -> DepthLossSpace:
        return DepthLossSpace(spec.convention, spec.min_depth, spec.max_depth)

    @property
    def _log_min(self) -> float:
        return math.log(self.min_depth)

    @property
    def _log_span(self) -> float:
        return math.log(self.max_depth) - math.log(self.min_depth)

    def valid(self, depth_m: torch.Tensor) -> torch.Tensor:
        return torch.isfinite(depth_m) & (depth_m > self.min_depth) & (depth_m < self.max_depth)

    def target_to_loss(self, depth_m: torch.Tensor) -> torch.Tensor:
        """Ground truth metres -> loss space; invalid pixels become 0 (they are masked anyway)."""
        d = torch.where(self.valid(depth_m), depth_m, torch.full_like(depth_m, self.max_depth))
        if self.convention is DepthConvention.METRIC:
            y = (torch.log(d) - self._log_min) / self._log_span
        elif self.convention is DepthConvention.NORMALIZED:
            y = d / self.max_depth
        else:
            y = self.min_depth / d
        return torch.where(self.valid(depth_m), y, torch.zeros_like(y))

    def output_to_loss(self, y: torch.Tensor) -> torch.Tensor:
        """Raw network output (in its convention) -> loss space."""
        if self.convention is DepthConvention.METRIC:
            # Metric outputs should be positive; the floor only keeps log() finite for a wild net.
            return (torch.log(torch.clamp(y, min=self.min_depth * 1e-3)) - self._log_min) / self._log_span
        if self.convention is DepthConvention.NORMALIZED:
            return y
        return y * (self.min_depth / self.max_depth)

    def loss_to_metres(self, y: torch.Tensor) -> torch.Tensor:
        """Loss space -> metres (for metrics during validation)."""
        if self.convention is DepthConvention.METRIC:
            d = torch.exp(y * self._log_span + self._log_min)
        elif self.convention is DepthConvention.NORMALIZED:
            d = y * self.max_depth
        else:
            d = self.min_depth / torch.clamp(y, min=1e-6)
        return torch.clamp(d, self.min_depth, self.max_depth)


def _gaussian_window(size: int, sigma: float, channels: int, device, dtype) -> torch.Tensor:
    r = torch.arange(size, device=device, dtype=dtype) - (size - 1) / 2.0
    g = torch.exp(-(r ** 2) / (2 * sigma ** 2))
    g = g / g.sum()
    return (g[:, None] * g[None, :]).expand(channels, 1, size, size).contiguous()


def ssim_map(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Per-pixel SSIM of N×C×H×W tensors with values in [0, 1] (reflect-padded, same size as the input)."""
    c = x.shape[1]
    w = _gaussian_window(SSIM_WINDOW, SSIM_SIGMA, c, x.device, x.dtype)
    pad = SSIM_WINDOW // 2

    def blur(t: torch.Tensor) -> torch.Tensor:
        return F.conv2d(F.pad(t, (pad, pad, pad, pad), mode="reflect"), w, groups=c)

    mx, my = blur(x), blur(y)
    sxx = blur(x * x) - mx * mx
    syy = blur(y * y) - my * my
    sxy = blur(x * y) - mx * my
    num = (2 * mx * my + SSIM_C1) * (2 * sxy + SSIM_C2)
    den = (mx * mx + my * my + SSIM_C1) * (sxx + syy + SSIM_C2)
    return num / den


def _masked_mean(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    m = mask.to(values.dtype)
    return (values * m).sum() / m.sum().clamp(min=1.0)


def depth_loss(pred: torch.Tensor, target: torch.Tensor, valid: torch.Tensor,
               l1_weight: float = W_DEPTH) -> Dict[str, torch.Tensor]:
    """DenseDepth's loss on N×1×H×W tensors in loss space; ``valid`` is a bool mask of the same shape.

    ``l1_weight`` is DenseDepth's λ (0.1). In log space the gradient and SSIM terms barely see a wrong global
    scale, so the L1 term alone teaches absolute depth: a larger λ weighs it more.

    Returns the weighted ``total`` and the unweighted ``l1``, ``grad`` and ``ssim`` terms.
    """
    if pred.shape != target.shape or valid.shape != target.shape:
        raise ValueError(f"depth_loss: shapes differ (pred {tuple(pred.shape)}, target {tuple(target.shape)}, "
                         f"valid {tuple(valid.shape)})")
    l1 = _masked_mean((pred - target).abs(), valid)
    vx = valid[..., :, 1:] & valid[..., :, :-1]
    vy = valid[..., 1:, :] & valid[..., :-1, :]
    gx = ((pred[..., :, 1:] - pred[..., :, :-1]) - (target[..., :, 1:] - target[..., :, :-1])).abs()
    gy = ((pred[..., 1:, :] - pred[..., :-1, :]) - (target[..., 1:, :] - target[..., :-1, :])).abs()
    grad = (_masked_mean(gx, vx) + _masked_mean(gy, vy))
    # Invalid target pixels take the (detached) prediction so they add no structure to the SSIM windows.
    filled = torch.where(valid, target, pred.detach())
    ssim = _masked_mean(torch.clamp((1.0 - ssim_map(pred, filled)) / 2.0, 0.0, 1.0), valid)
    total = l1_weight * l1 + W_GRAD * grad + W_SSIM * ssim
    return {"total": total, "l1": l1, "grad": grad, "ssim": ssim}


def hvo_loss(logits: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """Cross-entropy over N×3×H×W logits and N×H×W labels (uint8/long), ignoring label 255.

    A batch whose pixels are all ignored gives 0 (not NaN), so a sky-only crop cannot poison training.
    """
    labels = labels.long()
    if not bool((labels != HVO_IGNORE).any()):
        return logits.sum() * 0.0
    return F.cross_entropy(logits, labels, ignore_index=HVO_IGNORE)
