"""Image variation: time of day (sun), haze/fog, rain, motion blur, sensor noise and exposure.

``Effects`` holds one frame's settings; ``EffectOverrides`` holds what the user fixed on the command line
(None = drawn per frame from the seeded generator). Only the RGB image changes: ground truth never does.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace
from typing import Optional

import numpy as np


@dataclass(frozen=True)
class Effects:
    """Per-frame settings. Haze is an extinction coefficient (1/m): visibility ≈ 3 / haze_per_m."""

    sun_azimuth_rad: float = math.radians(135.0)
    sun_elevation_rad: float = math.radians(45.0)
    haze_per_m: float = 0.0005
    rain: float = 0.0                    # 0 = dry, 1 = downpour
    motion_blur_px: float = 0.0          # length of the blur streak
    motion_blur_angle_rad: float = 0.0   # direction of the streak in the image (0 = along x)
    noise_sigma: float = 0.01            # Gaussian read noise, fraction of full scale
    exposure_ev: float = 0.0

    def to_json(self) -> dict:
        """Human units for scene.json: angles in degrees."""
        return {(k[:-4] + "_deg" if k.endswith("_rad") else k):
                round(math.degrees(v) if k.endswith("_rad") else float(v), 6) for k, v in asdict(self).items()}

    @property
    def sun_direction_ned(self) -> np.ndarray:
        """Unit vector towards the sun in local NED."""
        ce = math.cos(self.sun_elevation_rad)
        return np.array([ce * math.cos(self.sun_azimuth_rad), ce * math.sin(self.sun_azimuth_rad),
                         -math.sin(self.sun_elevation_rad)])


@dataclass(frozen=True)
class EffectOverrides:
    """Values fixed by the user; None fields are drawn per frame by :func:`sample_effects`."""

    sun_azimuth_rad: Optional[float] = None
    sun_elevation_rad: Optional[float] = None
    haze_per_m: Optional[float] = None
    rain: Optional[float] = None
    motion_blur_px: Optional[float] = None
    noise_sigma: Optional[float] = None
    exposure_ev: Optional[float] = None

    def to_json(self) -> dict:
        """Human units for scene.json ("random" where drawn per frame)."""
        out = {}
        for f in fields(self):
            v = getattr(self, f.name)
            key = f.name.replace("_rad", "_deg")
            out[key] = "random" if v is None else round(math.degrees(v) if f.name.endswith("_rad") else float(v), 6)
        return out


def sample_effects(rng: np.random.Generator, overrides: EffectOverrides = EffectOverrides()) -> Effects:
    """Seeded random defaults: mostly fair weather, sometimes hazy, rainy, blurred or badly exposed."""
    drawn = Effects(
        sun_azimuth_rad=rng.uniform(0.0, 2 * math.pi),
        sun_elevation_rad=math.radians(rng.uniform(15.0, 75.0)),
        haze_per_m=float(rng.choice([rng.uniform(0.0001, 0.0015), rng.uniform(0.0015, 0.008)], p=[0.7, 0.3])),
        rain=float(rng.uniform(0.3, 1.0)) if rng.random() < 0.15 else 0.0,
        motion_blur_px=float(rng.uniform(1.0, 7.0)) if rng.random() < 0.3 else 0.0,
        motion_blur_angle_rad=rng.uniform(0.0, math.pi),
        noise_sigma=float(rng.uniform(0.0, 0.03)),
        exposure_ev=float(rng.uniform(-0.6, 0.6)),
    )
    fixed = {f.name: getattr(overrides, f.name) for f in fields(overrides) if getattr(overrides, f.name) is not None}
    return replace(drawn, **fixed)


def sky_colour(dirs_unit: np.ndarray, effects: Effects) -> np.ndarray:
    """K×3 sky radiance for unit world directions: horizon-to-zenith gradient plus a glow around the sun."""
    elev = np.clip(-dirs_unit[:, 2], 0.0, 1.0)
    w = np.sqrt(np.clip(elev / 0.6, 0.0, 1.0))[:, None]
    horizon, zenith = np.array([0.78, 0.84, 0.90], np.float32), np.array([0.33, 0.50, 0.82], np.float32)
    sky = horizon * (1 - w) + zenith * w
    cos_sun = np.clip(dirs_unit @ effects.sun_direction_ned, 0.0, 1.0)
    return (sky + np.array([1.0, 0.9, 0.7], np.float32) * (0.35 * cos_sun ** 16)[:, None]).astype(np.float32)


def sun_colour(effects: Effects) -> np.ndarray:
    """Warmer and weaker light when the sun is low."""
    low = 1.0 - min(max(math.degrees(effects.sun_elevation_rad) / 50.0, 0.0), 1.0)
    return np.array([1.05, 1.0 - 0.15 * low, 0.92 - 0.35 * low], np.float32) * (1.0 - 0.3 * low)


def apply_atmosphere(rgb: np.ndarray, range_m: np.ndarray, sky: np.ndarray, effects: Effects) -> np.ndarray:
    """Haze (Koschmieder: I = I0·e^(−βr) + A·(1 − e^(−βr))) and the grey cast of rain; H×W×3 float32."""
    airlight = np.array([0.74, 0.78, 0.82], np.float32) * (1.0 - 0.3 * effects.rain)
    beta = effects.haze_per_m + 0.004 * effects.rain
    r = np.where(sky, 3.0 / max(beta, 1e-6) * 0.6, np.nan_to_num(range_m, nan=0.0))
    f = np.exp(-beta * r)[..., None].astype(np.float32)
    out = rgb * f + airlight * (1.0 - f)
    if effects.rain > 0:
        grey = out.mean(axis=-1, keepdims=True)
        out = (out * (1 - 0.4 * effects.rain) + grey * 0.4 * effects.rain) * (1.0 - 0.25 * effects.rain)
    return out


def apply_sensor(rgb: np.ndarray, effects: Effects, rng: np.random.Generator) -> np.ndarray:
    """Exposure, motion blur, rain streaks and noise; float H×W×3 in, uint8 H×W×3 out."""
    import cv2

    img = np.clip(rgb * (2.0 ** effects.exposure_ev), 0.0, 1.0).astype(np.float32)
    # Lens and demosaicing softness: also hides the aliasing of one ray per pixel.
    img = cv2.GaussianBlur(img, (3, 3), 0.55, borderType=cv2.BORDER_REFLECT)
    if effects.motion_blur_px >= 1.0:
        k = int(math.ceil(effects.motion_blur_px)) | 1
        kernel = np.zeros((k, k), np.float32)
        c = k // 2
        dx, dy = math.cos(effects.motion_blur_angle_rad), math.sin(effects.motion_blur_angle_rad)
        for s in np.linspace(-effects.motion_blur_px / 2, effects.motion_blur_px / 2, 4 * k):
            kernel[int(round(c + s * dy)) % k, int(round(c + s * dx)) % k] += 1.0
        img = cv2.filter2D(img, -1, kernel / kernel.sum(), borderType=cv2.BORDER_REFLECT)
    h, w = img.shape[:2]
    if effects.rain > 0:
        streaks = np.zeros((h, w), np.float32)
        n = int(effects.rain * h * w / 250)
        x0, y0 = rng.uniform(0, w, n), rng.uniform(0, h, n)
        length = rng.uniform(0.03, 0.08, n) * h
        slant = rng.normal(0.15, 0.05)
        for x, y, ln in zip(x0, y0, length):
            cv2.line(streaks, (int(x), int(y)), (int(x + slant * ln), int(y + ln)), 1.0, 1, cv2.LINE_AA)
        img = img * (1 - 0.25 * streaks[..., None]) + 0.25 * streaks[..., None] * 0.85
    if effects.noise_sigma > 0:
        # Shot noise grows with brightness, read noise does not.
        sigma = effects.noise_sigma * np.sqrt(0.3 + img)
        img = img + sigma * rng.standard_normal(img.shape, dtype=np.float32)
    return np.clip(img * 255.0 + 0.5, 0, 255).astype(np.uint8)
