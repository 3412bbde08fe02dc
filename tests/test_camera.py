"""Intrinsics: pixel rays and projection, with and without lens distortion (OpenCV's model)."""
from __future__ import annotations

import cv2
import numpy as np

from edge_landing.runtime.core.camera import Intrinsics

PIXEL_CENTRES = np.stack(np.meshgrid(np.arange(64) + 0.5, np.arange(48) + 0.5), axis=-1)


def test_pinhole_rays_project_back_to_their_pixel_centres():
    cam = Intrinsics.from_hfov(64, 48)
    rays = cam.pixel_rays()
    assert rays.shape == (48, 64, 3) and not rays.flags.writeable and np.all(rays[..., 2] == 1)
    assert np.abs(cam.project(rays.astype(np.float64)) - PIXEL_CENTRES).max() < 1e-4


def test_distorted_rays_are_the_directions_opencv_images_them_at():
    pin = Intrinsics.from_hfov(64, 48)
    cam = Intrinsics(64, 48, pin.fx, pin.fy, pin.cx, pin.cy, (-0.25, 0.07, 0.001, -0.002, 0.0))
    rays = cam.pixel_rays().astype(np.float64)
    # Barrel distortion: a corner pixel sees further out than the pinhole ray through the same pixel.
    assert abs(rays[0, 0, 0]) > abs(pin.pixel_rays()[0, 0, 0]) * 1.05
    # OpenCV's own forward model maps every ray back onto its pixel centre.
    uv, _ = cv2.projectPoints(rays.reshape(-1, 3), np.zeros(3), np.zeros(3), cam.matrix, np.asarray(cam.dist))
    assert np.abs(uv.reshape(48, 64, 2) - PIXEL_CENTRES).max() < 1e-3
    assert np.abs(cam.project(rays) - PIXEL_CENTRES).max() < 1e-3
    # Depth back-projection follows the distorted rays.
    pts = cam.backproject(np.full((48, 64), 10.0, np.float32))
    assert np.allclose(pts[0, 0], rays[0, 0] * 10.0, rtol=1e-5)
