"""What a frame pair must show before its flow counts as evidence (ARCHITECTURE.md §11).

Motion geometry reads "no parallax" as "level ground". Two inputs give no parallax without being ground:
- **No texture.** Where the image is uniform (a capture card's "no signal" screen, a lens cap, pixels clipped
  at black or white, a digitally smooth region) DIS has nothing to match and fills the flow in from around:
  zero residual parallax, zero flow noise, read as flat and clear. A pixel is *textured* when the weakest
  direction of its local image gradient (the smaller eigenvalue of the structure tensor over a small box, as
  RMS grey levels per pixel) reaches ``min_texture_grey_px``. Ground of any kind seen by a real camera, and
  every rendered ground material of the sim, clears it many times over.
- **Texture that is only the sensor's noise.** A smooth surface seen by a noisy camera (murky or calm water,
  a wet road's sheen) clears that absolute floor, and next to textured ground DIS fills its flow in from the
  bank, metres in: it read as level ground. So a pixel may confirm only where its neighbourhood has texture
  beyond the noise: at least ``min_beyond_noise_share`` of the pixels within ``noise_box_px`` have a weakest
  gradient direction ``noise_texture_ratio`` times what the noise alone gives. The noise is measured on each
  image (robust spread of a Laplacian, per brightness band: shot noise grows with brightness). On the sim's
  flights (120×160 windows, every 20th frame of six flights) 97–100 % of ground pixels pass in clear air and
  90–98 % in heavy rain with sensor noise; murky water 38–49 %, mostly the pixels within a few of its bank. At
  a ratio of 1.5 pure noise almost never passed, but faint urban paving under noise lost a third of its
  confirmations; at 1.2 noise passes in scattered clusters, and a cell confirms only when all its pixels do.
  Pixels failing either check may still report an obstacle (a smooth wall's face reads partly high) but cannot
  confirm, like a pixel whose DIS patch is too large (fusion.motion).
- **Texture that runs along the parallax.** Parallax moves a point along its epipolar line (away from the
  image of the other camera's centre). An edge lying along that line (a low wall, a kerb or a fence seen along
  the flight's direction) looks the same wherever it slides along it: the aperture problem. DIS then takes the
  flow of the ground around it, and a 0.87 m wall 0.24 m thick running along the flight read as level ground
  (sent targets beside it on a generated flight; benchmarks/narrow_obstacles.py). A pixel within
  ``epipolar_edge_grow_px`` of one whose neighbourhood (``epipolar_box_px``, long enough that grass texture
  averages out) has less than ``epipolar_edge_ratio`` of its gradient energy along the epipolar line, and a
  clear edge across it, may not confirm in that pair; a pair with another baseline direction can. The edges are
  looked for in the darker of the two images at each pixel (the reference warped onto the current one): a wall
  is in both, where it slides along itself; a rain streak, bright, new in every frame and itself a line along
  the epipolar lines of forward flight, is in one only, and the darker image does not show it. An edge within
  ``epipolar_box_px`` // 2 of a pixel the same pair measured standing out (``outline_min_m`` and 3σ) is that
  obstacle's outline (a crown's side, a car's): the obstacle is marked and grown, and the ground beyond it may
  confirm as before the check.
- **Images that did not move as the vehicle did.** A frozen feed (the camera or its driver repeating the last
  image) or telemetry that does not belong to the frames: the poses predict that the ground moved by a pixel or
  more, yet the reference image matches the current one better where it was than where the poses put it.

Pure numpy/OpenCV, no I/O.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np

from edge_landing.runtime.core.errors import InputError


@dataclass(frozen=True)
class ImageCheckConfig:
    """Texture and pose-consistency thresholds (grey levels of 8-bit images, pixels)."""

    min_texture_grey_px: float = 0.25   # weakest-direction RMS gradient a pixel needs to carry evidence
    texture_box_px: int = 5             # the box it is measured over (about a DIS patch with its overlap)
    min_textured_share: float = 0.2     # a window with less textured ground gives no evidence at all
    noise_texture_ratio: float = 1.2    # weakest-direction gradient energy over the noise's own, to count
    noise_box_px: int = 9               # the neighbourhood whose share of such pixels is checked
    min_beyond_noise_share: float = 0.15   # share of that neighbourhood a pixel needs to confirm
    noise_bands: int = 8                # brightness bands the noise is measured in
    min_band_px: int = 300              # a band with fewer pixels takes the whole image's noise
    epipolar_box_px: int = 9            # an edge's direction is judged over this box (a wall's length, not grass)
    epipolar_edge_ratio: float = 0.15   # gradient energy along the epipolar line below this share of that across
    epipolar_edge_floor: float = 10.0   # ... and that across at least this (grey levels² per pixel²): an edge
    epipolar_edge_grow_px: int = 2      # pixels this close to one may not confirm either (DIS's patch reach)
    outline_min_m: float = 1.0          # an edge beside a pixel measured this high (and 3σ) is its outline
    min_predicted_motion_px: float = 1.0   # below this the two errors differ by noise only: not checked
    still_match_ratio: float = 0.5      # unwarped error below this share of the warped one: images did not move

    def __post_init__(self) -> None:
        for name in ("min_texture_grey_px", "min_predicted_motion_px", "still_match_ratio", "noise_texture_ratio",
                     "outline_min_m"):
            if not getattr(self, name) > 0:
                raise InputError(f"image check {name} must be > 0, got {getattr(self, name)}")
        if not 0 <= self.epipolar_edge_ratio < 1 or not self.epipolar_edge_floor >= 0 \
                or self.epipolar_edge_grow_px < 0:
            raise InputError(f"image check epipolar_edge_ratio must be in [0, 1), epipolar_edge_floor and "
                             f"epipolar_edge_grow_px >= 0, got {self.epipolar_edge_ratio}, "
                             f"{self.epipolar_edge_floor}, {self.epipolar_edge_grow_px}")
        for name in ("texture_box_px", "noise_box_px", "noise_bands", "min_band_px", "epipolar_box_px"):
            if getattr(self, name) < 1:
                raise InputError(f"image check {name} must be >= 1, got {getattr(self, name)}")
        for name in ("min_textured_share", "min_beyond_noise_share"):
            if not 0 <= getattr(self, name) <= 1:
                raise InputError(f"image check {name} must be in [0, 1], got {getattr(self, name)}")


def _structure(grey: np.ndarray, box_px: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The structure tensor's entries (Σgx², Σgx·gy, Σgy² as box means, grey levels² per pixel²)."""
    f = grey.astype(np.float32)
    gx = cv2.Sobel(f, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)     # grey levels per pixel
    gy = cv2.Sobel(f, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
    box = (box_px, box_px)
    return cv2.boxFilter(gx * gx, -1, box), cv2.boxFilter(gx * gy, -1, box), cv2.boxFilter(gy * gy, -1, box)


def _textured(a: np.ndarray, b: np.ndarray, c: np.ndarray, config: ImageCheckConfig) -> np.ndarray:
    # Smaller eigenvalue of [[a, b], [b, c]] >= t²  <=>  (a - t²)(c - t²) >= b² with a, c >= t².
    t2 = np.float32(config.min_texture_grey_px ** 2)
    out: np.ndarray = (a >= t2) & (c >= t2) & ((a - t2) * (c - t2) >= b * b)
    return out


def textured(grey: np.ndarray, config: ImageCheckConfig) -> np.ndarray:
    """H×W bool: pixels whose neighbourhood has texture in every direction (see the module docstring)."""
    return _textured(*_structure(grey, config.texture_box_px), config)


# The Laplacian-like kernel below has Σk² = 36: on white noise of σ its response has σ·6.
_NOISE_KERNEL = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
_NOISE_LEVELS = 256
# Sobel's x (or y) derivative scaled by 1/8 has Σk² = 12/64: white noise of σ gives gx² a mean of 0.1875 σ².
_NOISE_GRADIENT_ENERGY = 12.0 / 64.0


def sensor_noise_grey(grey: np.ndarray, config: ImageCheckConfig) -> np.ndarray:
    """H×W float32: the image noise's σ (grey levels) at each pixel, from the median |Laplacian| of the pixels in
    its brightness band (the median ignores the minority of edges; texture can only raise it, the safe way)."""
    # Integer responses: per-band medians from one histogram instead of a sort per band. Clipped at 255 (σ of
    # 60 grey levels): a larger median is no image a check could use, and the clip only raises the floor there.
    resp = np.minimum(np.abs(cv2.filter2D(grey, cv2.CV_16S, _NOISE_KERNEL, borderType=cv2.BORDER_REFLECT)), 255)
    bands, levels = config.noise_bands, _NOISE_LEVELS
    # Banded by the neighbourhood's brightness, not the pixel's own: a pixel's own value carries its noise, and
    # the bands at the edges of a surface's brightness would collect its noisiest pixels.
    band = (cv2.blur(grey, (5, 5), borderType=cv2.BORDER_REFLECT).astype(np.intp) * bands) >> 8
    hist = np.bincount((band * levels + resp).ravel(), minlength=bands * levels).reshape(bands, levels)
    whole = _median_of_histogram(hist.sum(axis=0, keepdims=True))[0]
    counts = hist.sum(axis=1)
    table = np.where(counts >= config.min_band_px, _median_of_histogram(hist), whole)
    out: np.ndarray = (np.float32(1.4826 / 6.0) * table.astype(np.float32))[band]
    return out


def _median_of_histogram(hist: np.ndarray) -> np.ndarray:
    """Per row of a histogram over the values 0, 1, ...: the lower median (0 for an empty row)."""
    cum = np.cumsum(hist, axis=1)
    half = (cum[:, -1] + 1) // 2
    out: np.ndarray = np.argmax(cum >= np.maximum(half, 1)[:, None], axis=1)
    return out


def texture_masks(grey: np.ndarray, config: ImageCheckConfig) -> tuple[np.ndarray, np.ndarray]:
    """(textured, beyond noise): H×W bool masks of the module docstring's two texture checks."""
    a, b, c = _structure(grey, config.texture_box_px)
    tex = _textured(a, b, c, config)
    # The smaller eigenvalue, in grey levels² per pixel², against the energy the noise alone gives.
    lam = 0.5 * (a + c) - np.sqrt(0.25 * (a - c) ** 2 + b * b)
    sigma = sensor_noise_grey(grey, config)
    floor = np.float32(config.noise_texture_ratio * _NOISE_GRADIENT_ENERGY) * sigma * sigma
    beyond = (lam >= floor).astype(np.float32)
    box = (config.noise_box_px, config.noise_box_px)
    share = cv2.boxFilter(beyond, -1, box, borderType=cv2.BORDER_REFLECT)
    return tex, share >= np.float32(config.min_beyond_noise_share)


def along_epipolar_lines(grey: np.ndarray, epipole: np.ndarray, origin_xy: tuple[int, int],
                         config: ImageCheckConfig, ref: Optional[np.ndarray] = None,
                         standing: Optional[np.ndarray] = None) -> np.ndarray:
    """H×W bool: pixels of the window ``grey`` at or near an edge that runs along the pair's epipolar lines (the
    module docstring). ``epipole``: the reference camera's centre in the current frame, homogeneous pixel
    coordinates (3,; z = 0 when it lies at infinity); ``origin_xy``: the window's top-left pixel in the frame.
    ``ref``: the pair's reference warped onto the window; given, edges are looked for in the darker of the two
    at each pixel (bright rain streaks in one image only do not count). ``standing``: pixels the pair measured
    standing out (``outline_min_m``); edges beside them are their outline, not flagged."""
    if config.epipolar_edge_ratio <= 0:
        return np.zeros(grey.shape, dtype=bool)
    a, b, c = _structure(grey if ref is None else np.minimum(grey, ref), config.epipolar_box_px)
    h, w = grey.shape
    x = np.arange(w, dtype=np.float32) + np.float32(origin_xy[0])
    y = np.arange(h, dtype=np.float32) + np.float32(origin_xy[1])
    ex, ey, ez = (np.float32(v) for v in epipole)
    dx = np.broadcast_to(ex - ez * x[None, :], (h, w))
    dy = np.broadcast_to(ey - ez * y[:, None], (h, w))
    with np.errstate(invalid="ignore", divide="ignore"):
        inv = np.float32(1.0) / np.sqrt(dx * dx + dy * dy)
    ux, uy = dx * inv, dy * inv                           # NaN at the epipole itself: no direction, not blind
    along = a * ux * ux + 2 * b * ux * uy + c * uy * uy   # gradient energy along the epipolar line ...
    across = a * uy * uy - 2 * b * ux * uy + c * ux * ux  # ... and across it (an edge along the line)
    edge = (along < np.float32(config.epipolar_edge_ratio) * across) & (across >= np.float32(config.epipolar_edge_floor))
    if standing is not None and standing.any():
        box = 2 * (config.epipolar_box_px // 2) + 1
        edge &= ~cv2.dilate(standing.view(np.uint8), np.ones((box, box), np.uint8)).astype(bool)
    k = 2 * config.epipolar_edge_grow_px + 1
    out: np.ndarray = cv2.dilate(edge.view(np.uint8), np.ones((k, k), np.uint8)).astype(bool)
    return out


def predicted_motion_px(hom: np.ndarray, rows: slice, cols: slice) -> float:
    """Median distance (pixels) that the plane homography ``hom`` (current pixel -> reference pixel) moves the
    window's corners and centre: how far the poses say the ground moved between the two images."""
    u = np.array([cols.start, cols.stop - 1, cols.start, cols.stop - 1, 0.5 * (cols.start + cols.stop - 1)])
    v = np.array([rows.start, rows.start, rows.stop - 1, rows.stop - 1, 0.5 * (rows.start + rows.stop - 1)])
    q = hom @ np.vstack([u, v, np.ones(5)])
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.hypot(q[0] / q[2] - u, q[1] / q[2] - v)
    d = np.where(q[2] > 0, d, np.inf)
    return float(np.median(d))


def moved_as_posed(cur: np.ndarray, ref_same_place: np.ndarray, ref_warped: np.ndarray, motion_px: float,
                   config: ImageCheckConfig) -> bool:
    """False when the poses moved the ground by at least ``min_predicted_motion_px`` but the reference image
    matches the current one better unmoved (``ref_same_place``: the same pixels) than moved by the poses
    (``ref_warped``). All three are the window's grey images (uint8)."""
    if not motion_px >= config.min_predicted_motion_px:
        return True
    still = float(cv2.absdiff(cur, ref_same_place).mean())
    posed = float(cv2.absdiff(cur, ref_warped).mean())
    return not still < config.still_match_ratio * posed
