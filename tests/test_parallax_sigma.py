"""A pair's height uncertainty (fusion.parallax.height_sigma): from the flow noise at the plane's range, widened
by the heights' own spread when that is larger (ARCHITECTURE.md §11)."""
from __future__ import annotations

import numpy as np

from edge_landing.runtime.fusion.parallax import height_sigma, range_gain

D_M, NOISE_RAD = 60.0, 0.2 / 320.0          # plane 60 m below, 0.2 px of flow noise at f = 320 px


def _sigma_at_plane(shape: tuple[int, ...]) -> np.ndarray:
    return np.full(shape, D_M * NOISE_RAD / 0.5)          # (d - 0)^2 / d · noise / |∇| with |∇| = 0.5


def test_heights_that_agree_with_the_flow_noise_keep_its_sigma():
    rng = np.random.default_rng(0)
    base = _sigma_at_plane((40, 50))
    local = 0.5 * base * rng.standard_normal(base.shape)   # half the predicted spread
    sigma, widened, usable = height_sigma(range_gain(D_M, np.zeros(base.shape)), NOISE_RAD, np.full(base.shape, 0.5), local,
                                          np.ones(base.shape, bool))
    assert widened == 1.0 and usable.all()
    np.testing.assert_allclose(sigma, base)


def test_heights_spread_wider_than_the_flow_noise_widen_it_by_their_robust_spread():
    rng = np.random.default_rng(1)
    base = _sigma_at_plane((40, 50))
    local = 3.0 * base * rng.standard_normal(base.shape)
    local[:2] = 40.0                                        # an obstacle: a minority, it can only widen the spread
    sigma, widened, _ = height_sigma(range_gain(D_M, np.zeros(base.shape)), NOISE_RAD, np.full(base.shape, 0.5), local,
                                     np.ones(base.shape, bool))
    assert 2.7 < widened < 3.6
    np.testing.assert_allclose(sigma, base * widened)


def test_too_few_reliable_heights_do_not_widen_and_ground_below_the_plane_is_measured_at_its_own_range():
    base = _sigma_at_plane((10, 9))                         # 90 pixels: fewer than 100
    sigma, widened, _ = height_sigma(range_gain(D_M, np.zeros(base.shape)), NOISE_RAD, np.full(base.shape, 0.5),
                                     10.0 * base, np.ones(base.shape, bool))
    assert widened == 1.0
    below, _, _ = height_sigma(range_gain(D_M, np.full(base.shape, -30.0)), NOISE_RAD, np.full(base.shape, 0.5),
                               np.zeros(base.shape), np.ones(base.shape, bool))
    np.testing.assert_allclose(below, base * (90.0 / 60.0) ** 2)   # (d - h)^2 / d with h = -30 m
