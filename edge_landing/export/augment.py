"""Training-time augmentation on batches (torch, in place of a data-loader pipeline: the cores are shared).

Photometric changes (colour jitter, blur, sensor noise) touch the image only; the horizontal flip is the one
geometric change and is applied to image, depth and HVO labels together. A horizontal flip keeps planar
z-depth and the H/V/O classes valid (the principal point is central and gravity stays "down"); vertical flips
and rotations would not (the camera's pitch is part of what the net must learn).

    aug = Augmenter(AugmentConfig(), seed=0)
    rgb01, depth, hvo = aug(rgb01, depth, hvo)      # rgb01: N×3×H×W float in [0, 1]
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Tuple

import torch
from torch.nn import functional as F

# ITU-R BT.601 luma weights, for saturation and contrast around the grey level.
LUMA = (0.299, 0.587, 0.114)


@dataclass(frozen=True)
class AugmentConfig:
    flip_p: float = 0.5
    brightness: float = 0.25        # multiplicative factor in [1 − b, 1 + b]
    contrast: float = 0.25
    saturation: float = 0.3
    channel_gain: float = 0.08      # per-channel white-balance drift
    blur_p: float = 0.3
    blur_sigma_max_px: float = 1.2
    noise_p: float = 0.5
    noise_std_max: float = 0.03     # in [0, 1] intensity units

    @staticmethod
    def none() -> AugmentConfig:
        return AugmentConfig(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


def _uniform(gen: torch.Generator, n: int, low: float, high: float, device) -> torch.Tensor:
    return (torch.rand(n, generator=gen) * (high - low) + low).to(device)


def _gaussian_blur(x: torch.Tensor, sigma: float) -> torch.Tensor:
    radius = max(1, int(round(2.5 * sigma)))
    r = torch.arange(-radius, radius + 1, dtype=x.dtype, device=x.device)
    g = torch.exp(-(r ** 2) / (2 * sigma ** 2))
    g = g / g.sum()
    c = x.shape[1]
    x = F.conv2d(F.pad(x, (radius, radius, 0, 0), mode="reflect"), g.view(1, 1, 1, -1).expand(c, 1, 1, -1), groups=c)
    return F.conv2d(F.pad(x, (0, 0, radius, radius), mode="reflect"), g.view(1, 1, -1, 1).expand(c, 1, -1, 1), groups=c)


class Augmenter:
    """Seeded, so a run (and a resumed run) is reproducible."""

    def __init__(self, config: AugmentConfig = AugmentConfig(), seed: int = 0):
        self.config = config
        self.gen = torch.Generator().manual_seed(int(seed))

    def __call__(self, rgb: torch.Tensor, depth: Optional[torch.Tensor] = None,
                 hvo: Optional[torch.Tensor] = None) -> Tuple[torch.Tensor, Optional[torch.Tensor], Optional[torch.Tensor]]:
        """rgb N×3×H×W in [0, 1]; depth N×H×W; hvo N×H×W. Returns new tensors (inputs are not modified)."""
        c, n, dev = self.config, rgb.shape[0], rgb.device
        if c.flip_p > 0:
            flip = (torch.rand(n, generator=self.gen) < c.flip_p).to(dev)
            if bool(flip.any()):
                rgb = torch.where(flip[:, None, None, None], rgb.flip(-1), rgb)
                if depth is not None:
                    depth = torch.where(flip[:, None, None], depth.flip(-1), depth)
                if hvo is not None:
                    hvo = torch.where(flip[:, None, None], hvo.flip(-1), hvo)
        rgb = self.photometric(rgb)
        return rgb, depth, hvo

    def photometric(self, rgb: torch.Tensor) -> torch.Tensor:
        c, n, dev = self.config, rgb.shape[0], rgb.device
        luma = torch.tensor(LUMA, dtype=rgb.dtype, device=dev).view(1, 3, 1, 1)
        if c.brightness > 0:
            rgb = rgb * _uniform(self.gen, n, 1 - c.brightness, 1 + c.brightness, dev).view(n, 1, 1, 1)
        if c.contrast > 0:
            mean = (rgb * luma).sum(1, keepdim=True).mean((2, 3), keepdim=True)
            k = _uniform(self.gen, n, 1 - c.contrast, 1 + c.contrast, dev).view(n, 1, 1, 1)
            rgb = (rgb - mean) * k + mean
        if c.saturation > 0:
            grey = (rgb * luma).sum(1, keepdim=True)
            k = _uniform(self.gen, n, 1 - c.saturation, 1 + c.saturation, dev).view(n, 1, 1, 1)
            rgb = (rgb - grey) * k + grey
        if c.channel_gain > 0:
            gains = (torch.rand(n, 3, generator=self.gen) * 2 - 1).to(dev) * c.channel_gain + 1
            rgb = rgb * gains.view(n, 3, 1, 1)
        if c.blur_p > 0 and float(torch.rand(1, generator=self.gen)) < c.blur_p:
            # One sigma per batch: per-sample kernels would cost a conv per image for little gain.
            sigma = 0.3 + float(torch.rand(1, generator=self.gen)) * max(0.0, c.blur_sigma_max_px - 0.3)
            rgb = _gaussian_blur(rgb, sigma)
        if c.noise_p > 0:
            on = (torch.rand(n, generator=self.gen) < c.noise_p).to(dev).to(rgb.dtype)
            std = _uniform(self.gen, n, 0.0, c.noise_std_max, dev) * on
            noise = torch.randn(rgb.shape, generator=self.gen).to(dev)
            rgb = rgb + noise * std.view(n, 1, 1, 1)
        return rgb.clamp(0.0, 1.0)
