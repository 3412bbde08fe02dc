"""Domain randomisation of the look (``edge-sim --randomise``): material palettes, textures, camera.

Without it every world has one look per material (the same grass, the same asphalt), and the net can learn
"this green is horizontal". With it:

- :class:`Palette`, one per scene: an RGB gain per material (grass from green to straw to brown, roads from
  dark to pale, markings white or yellow, roofs and walls of any hue), a per-object colour jitter (cars,
  trees, roofs, walls, containers: hashed from the triangle, so one object keeps one colour), and an extra
  procedural texture per material (noise amplitude and scale drawn per scene);
- :class:`CameraLook`, one per frame: white balance, vignetting, defocus blur, extra sensor noise, JPEG
  compression. Ground truth never changes.

All draws come from seeded generators, and both records go to scene.json (``generator.randomise``).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import cv2
import numpy as np

from .textures import _sample
from .world import Material

N_MAT = int(max(Material)) + 1
# Per-object colour jitter for these (hashed per triangle group: one object, one colour).
_OBJECT_MATERIALS = (Material.CAR_PAINT, Material.FOLIAGE, Material.ROOF_TILE, Material.ROOF_FLAT, Material.WALL,
                     Material.FACADE, Material.CLUTTER)
# Materials whose base colour may move far (ground covers and paint), the rest only a little.
_WIDE = (Material.ROOF_TILE, Material.ROOF_FLAT, Material.WALL, Material.FACADE, Material.CLUTTER, Material.CAR_PAINT)
# Ground covers: brightness moves a lot, hue a little (no purple concrete).
_GROUND = (Material.SOIL, Material.ASPHALT, Material.CONCRETE, Material.PAVING, Material.WATER)
_MARKING_COLOURS = np.array([[1.0, 1.0, 1.0], [1.05, 0.85, 0.25], [0.9, 0.9, 0.85]], np.float32)


@dataclass(frozen=True)
class Palette:
    """Per-scene material look: ``gain`` N_MAT×3, ``texture_amp``/``texture_cells_per_m`` N_MAT, object jitter."""

    gain: np.ndarray
    texture_amp: np.ndarray
    texture_cells_per_m: np.ndarray
    object_jitter: float

    def to_json(self) -> dict:
        return {"gain": {Material(m).name.lower(): [round(float(x), 4) for x in self.gain[m]] for m in range(N_MAT)},
                "texture_amp": [round(float(x), 4) for x in self.texture_amp],
                "texture_cells_per_m": [round(float(x), 4) for x in self.texture_cells_per_m],
                "object_jitter": round(self.object_jitter, 4)}

    def apply(self, albedo: np.ndarray, material: np.ndarray, tri: np.ndarray, points: np.ndarray) -> np.ndarray:
        """K×3 albedo re-coloured: material gain × object jitter × (1 + extra texture), clipped to [0, 1]."""
        out = albedo * self.gain[material]
        obj = np.isin(material, np.asarray(_OBJECT_MATERIALS, np.uint8))
        if obj.any():
            # Triangles of one object are consecutive: group by index // 64 (≥ one car/crown's triangles).
            h = (tri[obj] // 64).astype(np.int64)
            rgb = np.stack([((h * k) ^ (h >> 3)) % 997 / 997.0 for k in (73856093, 19349663, 83492791)], -1)
            out[obj] *= (1.0 + self.object_jitter * (2.0 * rgb.astype(np.float32) - 1.0))
        amp = self.texture_amp[material]
        cells = self.texture_cells_per_m[material]
        tex = np.zeros(len(material), np.float32)
        for c in np.unique(cells):
            sel = cells == c
            tex[sel] = _sample(int(c * 7) % 3, points[sel, 0] + points[sel, 2], points[sel, 1], float(c))
        out *= (1.0 + amp * tex)[:, None]
        return np.clip(out, 0.0, 1.0).astype(np.float32)


def sample_palette(rng: np.random.Generator) -> Palette:
    gain = np.exp(rng.normal(0.0, 0.08, (N_MAT, 3))).astype(np.float32)          # small hue/brightness shifts
    for m in _WIDE:
        gain[m] = np.exp(rng.normal(0.0, 0.3, 3)) * math.exp(rng.normal(0.0, 0.25))  # hue and brightness
    for m in _GROUND:
        gain[m] = np.exp(rng.normal(0.0, 0.08, 3)) * math.exp(rng.normal(0.0, 0.3))
    gain[Material.GRASS] = _grass(rng)
    gain[Material.TERRAIN] = gain[Material.GRASS]
    gain[Material.MARKING] = _MARKING_COLOURS[rng.integers(len(_MARKING_COLOURS))]
    amp = rng.uniform(0.0, 0.35, N_MAT).astype(np.float32)
    cells = rng.choice(np.array([0.3, 1.0, 3.0, 8.0], np.float32), N_MAT)
    return Palette(gain, amp, cells, float(rng.uniform(0.1, 0.45)))


def _grass(rng: np.random.Generator) -> np.ndarray:
    """Lush green to dry straw to brown (gains on the base grass colour 0.30, 0.44, 0.17)."""
    t = rng.uniform(0.0, 1.0)
    lush, straw, brown = np.array([0.8, 1.05, 0.9]), np.array([2.0, 1.5, 1.7]), np.array([1.5, 0.95, 1.2])
    g = lush + (straw - lush) * t if rng.random() < 0.7 else brown
    return (g * math.exp(rng.normal(0.0, 0.15))).astype(np.float32)


@dataclass(frozen=True)
class CameraLook:
    """Per-frame camera rendition: white balance gains, vignetting strength, defocus sigma (px), extra noise
    sigma (fraction of full scale), JPEG quality (0 = none)."""

    white_balance: tuple[float, float, float] = (1.0, 1.0, 1.0)
    vignetting: float = 0.0
    defocus_px: float = 0.0
    noise_sigma: float = 0.0
    jpeg_quality: int = 0

    def to_json(self) -> dict:
        d = asdict(self)
        d["white_balance"] = [round(float(x), 4) for x in self.white_balance]
        return {k: round(v, 4) if isinstance(v, float) else v for k, v in d.items()}


def sample_look(rng: np.random.Generator) -> CameraLook:
    wb = np.exp(rng.normal(0.0, 0.07, 3))
    return CameraLook(white_balance=(float(wb[0]), float(wb[1]), float(wb[2])),
                      vignetting=float(rng.uniform(0.0, 0.5)),
                      defocus_px=float(rng.uniform(0.5, 1.6)) if rng.random() < 0.35 else 0.0,
                      noise_sigma=float(rng.uniform(0.0, 0.02)),
                      jpeg_quality=int(rng.integers(25, 95)) if rng.random() < 0.6 else 0)


def apply_look(rgb: np.ndarray, look: CameraLook, rng: np.random.Generator) -> np.ndarray:
    """uint8 H×W×3 in and out: white balance, vignetting, defocus, noise, then JPEG (last, as a camera does)."""
    h, w = rgb.shape[:2]
    img = rgb.astype(np.float32) / 255.0 * np.asarray(look.white_balance, np.float32)
    if look.vignetting > 0:
        y, x = np.mgrid[0:h, 0:w].astype(np.float32)
        r2 = ((x - w / 2) / (w / 2)) ** 2 + ((y - h / 2) / (h / 2)) ** 2
        img *= (1.0 - look.vignetting * r2 / 2.0)[..., None]
    if look.defocus_px > 0:
        img = np.asarray(cv2.GaussianBlur(img, (0, 0), look.defocus_px, borderType=cv2.BORDER_REFLECT), np.float32)
    if look.noise_sigma > 0:
        img = img + look.noise_sigma * rng.standard_normal(img.shape, dtype=np.float32)
    out = np.clip(img * 255.0 + 0.5, 0, 255).astype(np.uint8)
    if look.jpeg_quality > 0:
        ok, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, look.jpeg_quality])
        if ok:
            out = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    return out
