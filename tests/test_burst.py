"""Each motion-stage frame the median of three aligned on the ground (runtime/fusion/burst.py, ARCHITECTURE.md §11)."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from edge_landing.runtime.core.camera import Attitude, Mount
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.fusion.burst import BurstConfig, FrameBurst, median3, warp_onto
from edge_landing.runtime.fusion.parallax import CameraPose, plane_homography

H, W = 240, 320
K = np.array([[230.0, 0.0, W / 2 - 0.5], [0.0, 230.0, H / 2 - 0.5], [0.0, 0.0, 1.0]])


def _pose(north_m: float, agl_m: float = 50.0) -> CameraPose:
    return CameraPose.of(Mount(), Attitude(), np.array([north_m, 0.0, -agl_m]), agl_m)


def _ground(seed: int = 0) -> np.ndarray:
    """Grass-like texture around grey 120, smooth enough to resample without aliasing."""
    rng = np.random.default_rng(seed)
    fine = cv2.GaussianBlur(rng.random((H, W), dtype=np.float32), (0, 0), 1.5)
    coarse = cv2.GaussianBlur(rng.random((H, W), dtype=np.float32), (0, 0), 6.0)
    g = 0.6 * (fine - fine.mean()) / fine.std() + 0.4 * (coarse - coarse.mean()) / coarse.std()
    return np.clip(120 + 15 * g, 0, 255).astype(np.float32)


def _seen_from(clean_now: np.ndarray, now: CameraPose, then: CameraPose) -> np.ndarray:
    """The ground of ``clean_now`` as the camera at ``then`` saw it (float32): warping it back onto ``now`` by the
    ground plane gives ``clean_now`` again, away from the borders."""
    hom = plane_homography(K, now, then)[0]
    return cv2.warpPerspective(clean_now, np.linalg.inv(hom), (W, H), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                               borderMode=cv2.BORDER_REFLECT)


def _camera(clean: np.ndarray, seed: int, noise: float, rain: float) -> tuple[np.ndarray, np.ndarray]:
    """(uint8 frame with sensor noise and the sim's rain streaks, the streak mask)."""
    rng = np.random.default_rng(seed)
    streaks = np.zeros((H, W), np.float32)
    for x, y, ln in zip(rng.uniform(0, W, int(rain * H * W / 250)), rng.uniform(0, H, int(rain * H * W / 250)),
                        rng.uniform(7.0, 19.0, int(rain * H * W / 250))):
        cv2.line(streaks, (int(x), int(y)), (int(x + 0.15 * ln), int(y + ln)), 1.0, 1, cv2.LINE_AA)
    img = clean * (1 - 0.25 * streaks) + 0.25 * streaks * 217.0 + noise * rng.standard_normal((H, W), np.float32)
    return np.clip(img + 0.5, 0, 255).astype(np.uint8), streaks > 0.5


def _err(a: np.ndarray, b: np.ndarray, inner: tuple[slice, slice]) -> float:
    return float(np.mean(np.abs(a[inner].astype(np.float32) - b[inner].astype(np.float32))))


def test_three_frames_aligned_on_the_ground_drop_rain_and_cut_noise():
    poses = [_pose(-1.6), _pose(-0.8), _pose(0.0)]        # 0.2 s apart at 4 m/s, looking 45° down from 50 m
    clean = _ground()
    burst = FrameBurst(BurstConfig(), K)
    inner = (slice(30, H - 30), slice(30, W - 30))          # away from the warps' borders
    for k, (pose, t) in enumerate(zip(poses, (0.0, 0.2, 0.4))):
        frame, streaks = _camera(_seen_from(clean, poses[-1], pose), seed=k, noise=6.0, rain=0.9)
        out = burst.clean(frame, pose, t)
    assert out is not frame
    truth = np.clip(clean + 0.5, 0, 255).astype(np.uint8)
    before, after = _err(frame, truth, inner), _err(out, truth, inner)
    assert after < 0.7 * before, (before, after)
    # The current frame's streaks are gone: on its streak pixels the median is near the ground again.
    on = streaks & np.pad(np.ones((H - 60, W - 60), bool), 30)
    assert _err(out[on], truth[on], (slice(None),)) < 0.5 * _err(frame[on], truth[on], (slice(None),))
    assert burst.raw_at(0.4) is frame and burst.raw_at(0.2) is not None and burst.raw_at(0.0) is None


def test_a_frame_is_used_as_it_is_without_two_recent_placed_frames_before_it():
    img = _ground().astype(np.uint8)
    burst = FrameBurst(BurstConfig(), K)
    assert burst.clean(img, _pose(-1.0), 0.0) is img          # nothing before it
    assert burst.clean(img, _pose(-0.5), 0.2) is img          # one frame before it
    assert burst.clean(img, _pose(0.0), 0.4) is not img       # two
    assert burst.clean(img, _pose(3.0), 1.2) is img           # a gap: both older than span_s
    assert burst.clean(img, _pose(3.5), 1.4) is img           # one recent frame only
    unplaced = CameraPose(_pose(0.0).r_nc, np.full(3, math.nan), 50.0)   # no telemetry position
    assert burst.clean(img, unplaced, 1.6) is img
    assert burst.clean(img, _pose(4.5), 1.8) is img           # an unplaced frame among the two before
    burst.reset()
    assert burst.raw_at(1.8) is None
    off = FrameBurst(BurstConfig(frames=1), K)
    for k in range(3):
        assert off.clean(img, _pose(0.5 * k), 0.2 * k) is img


def test_median_and_warp_helpers():
    a, b, c = (np.full((2, 2), v, np.uint8) for v in (9, 200, 40))
    assert median3(a, b, c).tolist() == [[40, 40], [40, 40]]
    img = _ground().astype(np.uint8)
    assert np.array_equal(warp_onto(img, np.eye(3)), img)


@pytest.mark.parametrize("kwargs", [{"frames": 2}, {"frames": 0}, {"span_s": 0.0}, {"span_s": math.nan}])
def test_bad_burst_settings_are_refused(kwargs):
    with pytest.raises(InputError):
        BurstConfig(**kwargs)


def test_the_rain_the_median_took_out_is_measured_and_dry_noise_is_not_rain():
    from edge_landing.runtime.fusion.streaks import RainFilter, StreakConfig, removed_share

    poses = [_pose(-1.6), _pose(-0.8), _pose(0.0)]
    clean = _ground(3)
    inner = (slice(30, H - 30), slice(30, W - 30))
    shares = {}
    # The sim's heaviest sensor noise, 0.028-0.030 of full scale per channel, is about 4 grey levels in grey.
    for rain, noise in ((0.9, 2.0), (0.0, 4.0)):
        burst = FrameBurst(BurstConfig(), K)
        for k, (pose, t) in enumerate(zip(poses, (0.0, 0.2, 0.4))):
            frame, _ = _camera(_seen_from(clean, poses[-1], pose), seed=10 + k, noise=noise, rain=rain)
            out = burst.clean(frame, pose, t)
        raw_cur, cur = np.ascontiguousarray(frame[inner]), np.ascontiguousarray(out[inner])
        shares[rain] = removed_share(raw_cur, cur, StreakConfig())
        # The pair itself (two medians) shows no rain to fill in; the rain filter still reports what was taken out.
        found = RainFilter(StreakConfig()).apply(cur, cur, 0.4, raw_cur)[2]
        assert found == (shares[rain] if shares[rain] >= StreakConfig().min_share else 0.0)
        assert RainFilter(StreakConfig()).apply(cur, cur, 0.4)[2] == 0.0
    assert shares[0.9] >= StreakConfig().min_share, shares      # heavy rain: found although the median took it out
    assert shares[0.0] < 0.5 * StreakConfig().min_share, shares    # a noisy sensor in dry air: not rain
