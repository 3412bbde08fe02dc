"""Rain streaks out of a frame pair before the motion stage's flow (ARCHITECTURE.md §11).

Rain draws thin, bright, near-vertical streaks that land somewhere else in every frame. DIS matches them as
texture: on rainy sim flights the flow noise doubled, open fields read as metres high and geometry confirmed
nothing. A streak pixel is brighter than its row neighbours (a grey top-hat over three columns) and has such
pixels above and below it (a run along a near-vertical line). Ground texture has such features too (grass
blades, markings, a pole); what tells rain apart is that it does not persist. The pair is compared after the
reference was warped onto the ground plane: thin bright features of one image with none within
``persist_px`` in the other are rain. When rain covers at least ``min_share`` of the window (in clear air only
the few thin features that parallax moved are unmatched; half of it within ``hold_s`` of a pair that found
rain), the rain of each image takes its row neighbours' level; otherwise the pair is left exactly as it is.
Only unmatched features are filled: filling every thin feature in rain also erased the texture of obstacles
(a bush) and let geometry confirm ground beside them. A thin obstacle whose parallax exceeds ``persist_px``
still looks like rain in a rainy pair; thin walls and poles are below what DIS resolves anyway (docs §11).

Pure OpenCV on uint8, no I/O.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np

from edge_landing.runtime.core.errors import InputError


@dataclass(frozen=True)
class StreakConfig:
    """Grey levels and pixels at the motion stage's size."""

    contrast: int = 8          # a streak pixel is this much brighter than the darker of its row neighbours
    run_px: int = 6            # of the 3×7 pixels around it, at least this many are streak-bright too
    persist_px: int = 2        # a thin feature with one in the other image this close is texture, not rain
    min_share: float = 0.03    # pairs with less rain than this share of the window are left alone (0: off) ...
    hold_s: float = 10.0       # ... or half of it, within this time of a pair that found min_share (weather lasts)

    def __post_init__(self) -> None:
        if not (0 < self.contrast <= 255 and 1 <= self.run_px <= 21 and self.persist_px >= 0):
            raise InputError(f"streak settings out of range: contrast {self.contrast}, run {self.run_px}, "
                             f"persist {self.persist_px}")
        if not 0 <= self.min_share <= 1:
            raise InputError(f"streak min_share must be in [0, 1], got {self.min_share}")
        if not self.hold_s >= 0:
            raise InputError(f"streak hold_s must be >= 0, got {self.hold_s}")


_ROW3 = np.ones((1, 3), np.uint8)


def streak_mask(grey: np.ndarray, config: StreakConfig) -> tuple[np.ndarray, np.ndarray]:
    """(thin bright near-vertical pixels, uint8 0/1; the grey top-hat: how much brighter than the opening)."""
    tophat = cv2.morphologyEx(grey, cv2.MORPH_TOPHAT, _ROW3)           # grey - opening, >= 0
    bright = (tophat >= config.contrast).view(np.uint8)
    run = cv2.boxFilter(bright, -1, (3, 7), normalize=False, borderType=cv2.BORDER_CONSTANT)
    mask = bright & (run >= config.run_px).view(np.uint8)
    return mask, tophat


def suppress_streaks(cur: np.ndarray, ref: np.ndarray, config: StreakConfig, raining: bool = False
                     ) -> tuple[np.ndarray, np.ndarray, float]:
    """(cur, ref with their rain filled in, share of the window found to be rain in either image).

    ``cur`` and ``ref``: uint8 H×W, the reference already warped onto ``cur`` by the ground plane. Returned
    unchanged (the same arrays) when the share is below ``min_share`` (half of it when ``raining``: a recent
    pair found rain; moderate rain straddles the threshold from pair to pair).
    """
    if config.min_share <= 0:
        return cur, ref, 0.0
    m_cur, top_cur = streak_mask(cur, config)
    m_ref, top_ref = streak_mask(ref, config)
    rain_cur, rain_ref = _not_in(m_cur, m_ref, config), _not_in(m_ref, m_cur, config)
    share = (cv2.countNonZero(rain_cur) + cv2.countNonZero(rain_ref)) / float(2 * cur.size)
    if not fills(share, config, raining):
        return cur, ref, share
    return _fill(cur, rain_cur, top_cur), _fill(ref, rain_ref, top_ref), share


def removed_share(raw: np.ndarray, cleaned: np.ndarray, config: StreakConfig) -> float:
    """Share of ``raw`` (uint8 H×W) that is a thin bright feature with none within ``persist_px`` in ``cleaned``, the
    same view with rain taken out (fusion.burst's median of three aligned frames): the rain that was taken out."""
    return cv2.countNonZero(_not_in(streak_mask(raw, config)[0], streak_mask(cleaned, config)[0], config)) / float(raw.size)


def _not_in(mask: np.ndarray, other: np.ndarray, config: StreakConfig) -> np.ndarray:
    """The pixels of ``mask`` (uint8 0/1) with none of ``other`` within ``persist_px``: features that did not persist."""
    near = np.ones((2 * config.persist_px + 1, 2 * config.persist_px + 1), np.uint8)
    out: np.ndarray = mask & (1 - cv2.dilate(other, near))
    return out


def fills(share: float, config: StreakConfig, raining: bool) -> bool:
    """Whether a pair with this rain ``share`` is filled in (half the threshold while ``raining``)."""
    return config.min_share > 0 and share >= (0.5 if raining else 1.0) * config.min_share


def _fill(grey: np.ndarray, rain: np.ndarray, tophat: np.ndarray) -> np.ndarray:
    """``grey`` with its rain pixels at the opening's level (grey - top-hat), only when there is rain to fill."""
    out: np.ndarray = grey.copy()
    cv2.copyTo(cv2.subtract(grey, tophat), cv2.dilate(rain, _ROW3), out)   # anti-aliased: the dimmer rim goes too
    return out


class RainFilter:
    """``suppress_streaks`` with the memory of when a pair last found rain (``hold_s``), for one keyframe ring."""

    def __init__(self, config: StreakConfig):
        self.config = config
        self.found_s = -math.inf

    def reset(self) -> None:
        self.found_s = -math.inf

    def apply(self, cur: np.ndarray, ref: np.ndarray, time_s: float, raw_cur: Optional[np.ndarray] = None
              ) -> tuple[np.ndarray, np.ndarray, float]:
        """(cur, ref, share of the window found to be rain: 0 when none was).

        ``raw_cur``: ``cur`` as the camera gave it, when ``cur`` is fusion.burst's median of three, which takes
        streaks out before the pair sees them: when the pair finds no rain to fill in, the rain the median took
        out (:func:`removed_share`) counts as found, so that what is off in rain (fusion.residual) stays off.
        """
        cfg = self.config
        out_cur, out_ref, share = suppress_streaks(cur, ref, cfg, self._raining(time_s))
        found = self._found(share, time_s)
        if found == 0.0 and raw_cur is not None and cfg.min_share > 0:
            found = self._found(removed_share(raw_cur, cur, cfg), time_s)
        return out_cur, out_ref, found

    def _raining(self, time_s: float) -> bool:
        return 0.0 <= time_s - self.found_s <= self.config.hold_s

    def _found(self, share: float, time_s: float) -> float:
        """``share`` when it counts as rain (half the threshold while raining), else 0; remembers when it did."""
        raining = self._raining(time_s)
        if fills(share, self.config, False):
            self.found_s = time_s
        return share if fills(share, self.config, raining) else 0.0
