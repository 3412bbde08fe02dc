"""The telemetry's rotation drift between a frame pair, measured from the flow (fusion.rotation_fit)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from edge_landing.runtime.fusion.rotation_fit import RotationFitConfig, fit_rotation, rotation_flow


def window(seed: int = 0, n: int = 4000):
    """Normalised points of an oblique window and their parallax directions, radiating from an epipole above."""
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(-0.3, 0.3, n), rng.uniform(0.1, 0.5, n)
    gx, gy = (x - 0.05) * 0.02, (y + 0.4) * 0.02      # away from the focus of expansion at (0.05, -0.4)
    return rng, (x, y), gx, gy


def test_the_rotation_across_the_epipolar_lines_is_recovered_and_parallax_does_not_move_it():
    rng, (x, y), gx, gy = window()
    omega = np.array([0.0003, -0.0017, 0.0012])            # 0.1° about y and 0.07° about z: about a pixel
    fx, fy = rotation_flow(x, y, omega)
    noise = 0.2 / 554.0                                    # 0.2 px at 640 px across
    rx, ry = fx + rng.normal(0, noise, x.size), fy + rng.normal(0, noise, x.size)
    use = np.ones(x.size, bool)
    fit = fit_rotation((x, y), rx, ry, gx, gy, use)
    # What the window can see: the flow across the epipolar lines left after the correction is the noise only.
    before, after = across_rms(x, y, rx, ry, gx, gy, fit)
    assert before > 3 * noise and after < 1.2 * noise, (before / noise, after / noise)
    # Obstacles on a fifth of the points, with parallax along their epipolar lines up to 10 px: the same fit.
    tall = rng.random(x.size) < 0.2
    s = np.where(tall, rng.uniform(0.5, 10.0, x.size) / 554.0 / np.hypot(gx, gy), 0.0)
    with_obstacles = fit_rotation((x, y), rx + s * gx, ry + s * gy, gx, gy, use)
    assert np.allclose(with_obstacles, fit, atol=2e-5)


def test_no_fit_without_enough_points_or_beyond_a_plausible_drift():
    _, (x, y), gx, gy = window(n=100)
    fx, fy = rotation_flow(x, y, np.array([0.0, 0.001, 0.0]))
    assert not fit_rotation((x, y), fx, fy, gx, gy, np.ones(x.size, bool)).any()       # 100 < min_points
    _, (x, y), gx, gy = window()
    fx, fy = rotation_flow(x, y, np.array([0.0, math.radians(3.0), 0.0]))
    assert not fit_rotation((x, y), fx, fy, gx, gy, np.ones(x.size, bool)).any()       # 3° is not a drift
    allowed = fit_rotation((x, y), fx, fy, gx, gy, np.ones(x.size, bool), RotationFitConfig(max_rad=0.1))
    before, after = across_rms(x, y, fx, fy, gx, gy, allowed)
    assert after < 0.05 * before


def across_rms(x, y, rx, ry, gx, gy, omega):
    """RMS of the residual across the epipolar lines before and after removing ``omega``'s flow."""
    ex, ey = gy / np.hypot(gx, gy), -gx / np.hypot(gx, gy)
    cx, cy = rotation_flow(x, y, omega)
    return (float(np.sqrt(np.mean((rx * ex + ry * ey) ** 2))),
            float(np.sqrt(np.mean(((rx - cx) * ex + (ry - cy) * ey) ** 2))))


def test_a_pair_with_a_tenth_of_a_degree_of_attitude_drift_still_measures_the_box():
    """The box scene of test_motion, two seconds apart, the first frame's reported attitude off by 0.15° in pitch
    and yaw (an autopilot's drift, 0.1°/s): with the fit, the flow noise stays near its floor and the box reads
    2 m; without it, the drift is read as flow noise (about a pixel at 320 px across). The same error between
    frames 0.1 s apart is a drift of 1.5°/s: that attitude is not trusted, and the pair gives no evidence."""
    pytest.importorskip("edge_landing.sim", reason="the sim extra (embreex) renders the test world")
    from dataclasses import replace

    from edge_landing.runtime.core.camera import Attitude
    from edge_landing.runtime.fusion.motion import CameraPose, MotionConfig, MotionStage
    from tests.test_motion import INTR, MOUNT, _flat_world, _frames

    box_n, box_e, height = 40.0, 0.0, 2.0
    world = _flat_world([[box_n, box_e, 3.0, 3.0, height]])
    frames = list(_frames(world, [(0.0, -6.0, -40.0), (0.0, 6.0, -40.0)]))
    drift = math.radians(0.15)
    results = {}
    for fit, apart_s in ((True, 2.0), (False, 2.0), ("fast", 0.1)):
        stage = MotionStage(replace(MotionConfig(), rotation_fit=RotationFitConfig(enabled=bool(fit))), INTR, MOUNT)
        for k, _t, r, state in frames:
            att = state.attitude if k else Attitude(0.0, drift, drift)
            pose = CameraPose.of(MOUNT, att, state.position_ned_m, state.agl_m)
            results[fit] = stage.update(r.rgb, pose, k * apart_s, focus_ned_m=np.array([box_n, box_e, 0.0]))
        if fit == "fast":
            assert results[fit] is None and "attitude moved 0.19° in 0.1 s" in stage.last_reason, stage.last_reason
            assert "more than an estimator drifts" in stage.last_reason
    fitted, raw = results[True], results[False]
    assert fitted is not None and raw is not None
    assert fitted.flow_noise_px < 0.5 < raw.flow_noise_px, (fitted.flow_noise_px, raw.flow_noise_px)
    pts = frames[-1][2].geometry.points_ned[fitted.rows, fitted.cols]
    top = (np.abs(pts[..., 2] + height) < 0.01) & (np.abs(pts[..., 0] - box_n) < 2.0) & (np.abs(pts[..., 1] - box_e) < 2.0)
    h_top = fitted.height_m[top & np.isfinite(fitted.height_m)]
    sigma = float(np.median(fitted.sigma_m[top]))
    assert h_top.size > 20 and abs(float(np.median(h_top)) - height) <= 3 * sigma, (np.median(h_top), sigma)
