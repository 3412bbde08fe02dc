"""Rain streaks filled in before the motion stage's flow (runtime/fusion/streaks.py, ARCHITECTURE.md §11)."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.fusion.streaks import RainFilter, StreakConfig, streak_mask, suppress_streaks


def _ground(seed: int = 0, hw: tuple[int, int] = (120, 160), roughness: float = 1.0) -> np.ndarray:
    """Grass-like texture: smoothed noise at two scales around grey 125 (``roughness`` scales the fine part)."""
    rng = np.random.default_rng(seed)
    fine = cv2.GaussianBlur(rng.random(hw, dtype=np.float32), (0, 0), 1.5)
    coarse = cv2.GaussianBlur(rng.random(hw, dtype=np.float32), (0, 0), 6.0)
    g = roughness * 0.6 * (fine - fine.mean()) / fine.std() + 0.4 * (coarse - coarse.mean()) / coarse.std()
    return np.clip(125 + 14 * g, 0, 255).astype(np.uint8)


def _rain(grey: np.ndarray, strength: float, seed: int) -> np.ndarray:
    """Thin bright near-vertical anti-aliased streaks 14-38 px long (the sim's renderer at 480 rows), a new set
    per seed."""
    rng = np.random.default_rng(seed)
    h, w = grey.shape
    streaks = np.zeros((h, w), np.float32)
    n = int(strength * h * w / 250)
    slant = rng.normal(0.15, 0.05)
    for x, y, ln in zip(rng.uniform(0, w, n), rng.uniform(0, h, n), rng.uniform(14.0, 38.0, n)):
        cv2.line(streaks, (int(x), int(y)), (int(x + slant * ln), int(y + ln)), 1.0, 1, cv2.LINE_AA)
    out = grey.astype(np.float32) * (1 - 0.25 * streaks) + 0.25 * streaks * 217.0
    return np.clip(out + 0.5, 0, 255).astype(np.uint8)


def _err(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.mean(np.abs(a.astype(np.int16) - b.astype(np.int16))))


@pytest.mark.parametrize("strength", [0.7, 0.9])
def test_rain_is_filled_in_both_images_of_a_pair(strength):
    clean = _ground()
    cur, ref = _rain(clean, strength, 1), _rain(clean, strength, 2)     # new streaks in every frame
    cur2, ref2, share = suppress_streaks(cur, ref, StreakConfig())
    assert share >= StreakConfig().min_share
    for before, after in ((cur, cur2), (ref, ref2)):
        assert _err(after, clean) < 0.65 * _err(before, clean), (_err(after, clean), _err(before, clean))


@pytest.mark.parametrize("roughness", [1.0, 3.0])
def test_texture_that_persists_is_not_rain(roughness):
    """Thin bright features in both images (rough grass, a pole) stay, however many there are."""
    clean = _ground(3, roughness=roughness)
    shifted = np.roll(clean, 1, axis=1)                          # a pixel of parallax or resampling
    pole = clean.copy()
    pole[20:90, 80] = 210
    for cur, ref in ((clean, shifted), (pole, np.roll(pole, 1, axis=0))):
        out_cur, out_ref, share = suppress_streaks(cur, ref, StreakConfig())
        assert share < StreakConfig().min_share
        assert out_cur is cur and out_ref is ref                 # not copies: nothing was changed


def test_off_switch_wide_structures_and_bad_settings():
    clean = _ground(5)
    cur, ref = _rain(clean, 0.9, 3), _rain(clean, 0.9, 4)
    a, b, share = suppress_streaks(cur, ref, StreakConfig(min_share=0.0))
    assert a is cur and b is ref and share == 0.0
    # A bright bar 6 px wide (a wall's top, a road marking) is not a streak, rain or not.
    bar = cur.copy()
    bar[:, 70:76] = 230
    mask, _ = streak_mask(bar, StreakConfig())
    assert not mask[:, 71:75].any()
    out, _, _ = suppress_streaks(bar, ref, StreakConfig())
    assert np.array_equal(out[:, 71:75], bar[:, 71:75])
    with pytest.raises(InputError, match="min_share"):
        StreakConfig(min_share=1.5)


def test_moderate_rain_is_filled_once_a_recent_pair_found_rain():
    """Weather lasts: after a pair found min_share of rain, pairs with half as much are filled too."""
    clean = _ground(7)
    cur, ref = _rain(clean, 0.4, 5), _rain(clean, 0.4, 6)
    config = StreakConfig()
    a, b, share = suppress_streaks(cur, ref, config)
    assert 0.5 * config.min_share <= share < config.min_share and a is cur and b is ref
    a, b, share = suppress_streaks(cur, ref, config, raining=True)
    assert _err(a, clean) < 0.65 * _err(cur, clean) and _err(b, clean) < 0.65 * _err(ref, clean)
    with pytest.raises(InputError, match="hold_s"):
        StreakConfig(hold_s=-1.0)


def test_rain_filter_holds_for_hold_s_and_forgets_on_reset():
    clean = _ground(9)
    heavy = (_rain(clean, 0.9, 1), _rain(clean, 0.9, 2))
    moderate = (_rain(clean, 0.4, 3), _rain(clean, 0.4, 4))
    config = StreakConfig()
    rain = RainFilter(config)
    assert rain.apply(*moderate, 0.0)[2] == 0.0                   # moderate rain alone is below the threshold
    assert rain.apply(*heavy, 1.0)[2] >= config.min_share          # heavy rain is filled and remembered ...
    assert rain.apply(*moderate, 1.0 + config.hold_s - 0.5)[2] > 0.0     # ... so moderate rain is filled too
    assert rain.apply(*moderate, 1.0 + config.hold_s + 0.5)[2] == 0.0    # until the hold has passed
    rain.apply(*heavy, 20.0)
    rain.reset()
    assert rain.apply(*moderate, 21.0)[2] == 0.0
