"""Geometry gives no evidence from a blank or frozen camera feed, or from texture that is only the camera's noise
(fusion.image_checks)."""
from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest

from edge_landing.runtime.fusion.image_checks import (
    ImageCheckConfig,
    along_epipolar_lines,
    moved_as_posed,
    predicted_motion_px,
    sensor_noise_grey,
    texture_masks,
    textured,
)

CFG = ImageCheckConfig()


def _texture(h: int = 60, w: int = 80, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.clip(128 + 40 * rng.standard_normal((h, w)), 0, 255).astype(np.uint8)


def test_texture_needs_gradients_in_every_direction():
    assert not textured(np.full((40, 50), 200, np.uint8), CFG).any()          # a "no signal" screen
    assert not textured(np.full((40, 50), 255, np.uint8), CFG).any()          # clipped white
    stripes = np.tile((np.arange(50) % 8 * 30).astype(np.uint8), (40, 1))      # texture across only
    assert textured(stripes, CFG).mean() < 0.05
    assert textured(_texture(), CFG).mean() > 0.99
    # One grey level of sensor-like noise is texture enough: a real camera's noise always clears the bar.
    noise = np.clip(128 + np.random.default_rng(1).standard_normal((40, 50)), 0, 255).astype(np.uint8)
    assert textured(noise, CFG).mean() > 0.9


def _noisy(img: np.ndarray, sigma: float, seed: int = 3) -> np.ndarray:
    noise = sigma * np.random.default_rng(seed).standard_normal(img.shape)
    return np.clip(img.astype(np.float64) + noise, 0, 255).astype(np.uint8)


def _ground(h: int, w: int, seed: int) -> np.ndarray:
    """Texture like a surface's (smooth at the pixel's scale, unlike white noise, which is all noise)."""
    field = cv2.GaussianBlur(np.random.default_rng(seed).standard_normal((h, w)), (0, 0), 1.5)
    return np.clip(128 + 40 * field / field.std(), 0, 255).astype(np.uint8)


def test_sensor_noise_is_measured_per_brightness_band():
    # Dark half with 2 grey levels of noise, bright half with 6 (shot noise grows with brightness).
    img = np.concatenate([_noisy(np.full((60, 80), 40), 2.0), _noisy(np.full((60, 80), 200), 6.0, seed=4)])
    sigma = sensor_noise_grey(img, CFG)
    assert np.median(sigma[:60]) == pytest.approx(2.0, rel=0.15)
    assert np.median(sigma[60:]) == pytest.approx(6.0, rel=0.15)
    # A brightness with too few pixels for a band of its own (a 10×10 spot) takes the whole image's estimate.
    spot = np.full((60, 80), 100)
    spot[45:55, 60:70] = 220
    spot = _noisy(spot, 3.0)
    whole = sensor_noise_grey(spot, replace(CFG, noise_bands=1))
    assert sensor_noise_grey(spot, CFG)[50, 65] == whole[50, 65]


def test_texture_that_is_only_noise_does_not_count_beyond_it():
    """Murky water beside its bank: a smooth surface whose only texture is the camera's noise clears the
    absolute texture floor, but not the noise-relative check, except within a few pixels of the bank."""
    bank = _ground(60, 40, seed=5)
    water = np.full((60, 80), 90, np.uint8)
    img = _noisy(np.concatenate([bank, water], axis=1), 4.0)
    tex, beyond = texture_masks(img, CFG)
    assert tex.mean() > 0.95                                  # the absolute check passes the noise
    assert beyond[:, :36].mean() > 0.99                       # the bank has texture beyond the noise
    # The water's interior: noise alone clears 1.2× its own mean energy in scattered clusters only (a 9×9 share
    # of 15 % is reached by chance here and there; a cell confirms only when all its pixels do).
    assert beyond[:, 46:].mean() < 0.3
    assert beyond[:, 40:46].mean() > 0                        # the box reaches a few pixels over the bank
    # Without any noise the estimate is zero and every textured pixel counts.
    tex0, beyond0 = texture_masks(_ground(60, 80, seed=6), CFG)
    assert beyond0.mean() > 0.99 and tex0.mean() > 0.99


def test_an_edge_along_the_epipolar_lines_cannot_confirm_one_across_them_can():
    """A bright 2-pixel line (a low wall seen along the flight) on noisy texture: when the epipolar lines run
    along it (the epipole far above the window, as in forward flight) its pixels and two either side are flagged;
    when they cross it (the epipole to the side) nothing is; plain texture is hardly ever flagged; a line in
    only one image of the pair is not flagged."""
    grey = _texture(80, 100, seed=3).astype(np.float32) * 0.25 + 96
    grey[:, 49:51] = 230
    grey = grey.astype(np.uint8)
    above, beside = np.array([50.0, -500.0, 1.0]), np.array([1.0, 0.0, 0.0])   # homogeneous; z = 0: at infinity
    along = along_epipolar_lines(grey, above, (0, 0), CFG)
    assert along[10:70, 47:53].all()
    assert along[:, :40].mean() < 0.05 and along[:, 60:].mean() < 0.05
    assert not along_epipolar_lines(grey, beside, (0, 0), CFG)[10:70, 45:55].any()
    # The window's offset in the frame counts: the same epipole seen from a window far to its right is beside.
    assert not along_epipolar_lines(grey, np.array([50.0, 40.0, 1.0]), (-2000, 0), CFG)[10:70, 45:55].any()
    assert not along_epipolar_lines(grey, above, (0, 0), replace(CFG, epipolar_edge_ratio=0.0)).any()
    # With the pair's reference: a wall is in both images (slid along itself); a rain streak, new in every frame,
    # in one only, and is no reason to refuse.
    ref = grey.copy()
    assert along_epipolar_lines(grey, above, (0, 0), CFG, ref)[10:70, 47:53].all()
    ground = (_texture(80, 100, seed=4).astype(np.float32) * 0.25 + 96).astype(np.uint8)
    assert not along_epipolar_lines(grey, above, (0, 0), CFG, ground)[10:70, 45:55].any()
    assert not along_epipolar_lines(ground, above, (0, 0), CFG, grey)[10:70, 45:55].any()
    # Beside pixels the pair measured standing out (a crown's or a car's side), the edge is that obstacle's
    # outline: the obstacle is marked, and the ground beyond it is not refused for the edge.
    standing = np.zeros(grey.shape, bool)
    standing[:, 53:57] = True
    assert along[10:70, 51:58].all()
    assert not along_epipolar_lines(grey, above, (0, 0), CFG, None, standing)[10:70, 51:70].any()


def test_predicted_motion_is_the_homography_shift():
    shift = np.array([[1.0, 0.0, 4.0], [0.0, 1.0, -3.0], [0.0, 0.0, 1.0]])
    assert predicted_motion_px(shift, slice(10, 50), slice(20, 80)) == pytest.approx(5.0)
    assert predicted_motion_px(np.eye(3), slice(0, 10), slice(0, 10)) == 0.0


def test_images_that_did_not_move_as_posed_are_caught():
    img = _texture(seed=2)
    moved = np.roll(img, 5, axis=1)
    # A frozen feed: the same image, while the poses say the ground moved 5 px.
    assert not moved_as_posed(img, img, moved, 5.0, CFG)
    # The images moved as the poses said: warping by the poses lines them up.
    assert moved_as_posed(img, moved, img, 5.0, CFG)
    # Below the checked motion the two errors differ by noise only: not judged.
    assert moved_as_posed(img, img, moved, 0.5, CFG)


def test_config_is_checked():
    from edge_landing.runtime.core.errors import InputError

    with pytest.raises(InputError, match="min_texture_grey_px"):
        ImageCheckConfig(min_texture_grey_px=float("nan"))
    with pytest.raises(InputError, match="min_textured_share"):
        ImageCheckConfig(min_textured_share=1.5)
    with pytest.raises(InputError, match="noise_texture_ratio"):
        ImageCheckConfig(noise_texture_ratio=0.0)
    with pytest.raises(InputError, match="noise_box_px"):
        ImageCheckConfig(noise_box_px=0)
    with pytest.raises(InputError, match="min_beyond_noise_share"):
        ImageCheckConfig(min_beyond_noise_share=-0.1)
    with pytest.raises(InputError, match="epipolar_edge_ratio"):
        ImageCheckConfig(epipolar_edge_ratio=1.0)
    with pytest.raises(InputError, match="epipolar_box_px"):
        ImageCheckConfig(epipolar_box_px=0)
    with pytest.raises(InputError, match="outline_min_m"):
        ImageCheckConfig(outline_min_m=0.0)


pytest.importorskip("embreex")
from edge_landing.benchmarks.lying_model import lying_prediction  # noqa: E402
from edge_landing.runtime.fusion.fuser import FusionConfig, LandingFuser  # noqa: E402
from tests.test_motion import INTR, MOUNT, _flat_world, _frames  # noqa: E402

PATH = [(-20.0 + 1.5 * k, 0.0, -30.0) for k in range(24)]


def _fly_with(images):
    """The lying model over an open field; ``images(k, rgb)`` gives the frame the stage sees."""
    world = _flat_world([[30.0, 12.0, 2.0, 1.0, 1.5]])
    fuser = LandingFuser(FusionConfig(), INTR, MOUNT)
    out = []
    for k, t, r, state in _frames(world, PATH):
        target = fuser.update(lying_prediction(INTR, MOUNT, state, k), state, t, images(k, r.rgb))
        ran = fuser.geometry_ran
        out.append((target, fuser.motion.last_reason if ran else "", ran and fuser.motion.last is not None))
    return out


def test_a_blank_feed_confirms_nothing():
    """A uniform frame gives zero flow and zero flow noise, which would read as level, clear ground."""
    blank = np.full((INTR.height, INTR.width, 3), (20, 40, 200), np.uint8)      # a capture card's blue screen
    out = _fly_with(lambda k, rgb: blank)
    assert not any(t.valid for t, _, _ in out)
    assert any("too little texture" in why for _, why, _ in out)


def test_a_frozen_feed_adds_no_evidence():
    """The same image again while the vehicle flies on: no pair after the freeze is measured."""
    frozen = {}

    def images(k, rgb):
        if k == 10:
            frozen["rgb"] = rgb
        return frozen.get("rgb", rgb)

    after = _fly_with(images)[12:]
    assert not any(measured for _, _, measured in after)
    assert sum("did not move as the vehicle did" in why for _, why, _ in after) >= 4
    normal = _fly_with(lambda k, rgb: rgb)                                        # not vacuous: it measures
    assert sum(measured for _, _, measured in normal[12:]) >= 4 and any(t.valid for t, _, _ in normal)
