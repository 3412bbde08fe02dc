"""Motion geometry through a real lens: frames with a wide camera's barrel distortion, measured with the
calibration (edge-run --intrinsics) and without it (a pinhole from --hfov, all edge-run had for a real camera).

The frames are the sim's pinhole renders distorted with OpenCV's model (cv2.undistortPoints gives, for every
distorted pixel, where it comes from in the pinhole image); the motion stage undoes it with its own map
(cv2.initUndistortRectifyMap), so the two sides share only OpenCV's lens model."""
import cv2
import numpy as np
import pytest

pytest.importorskip("embreex")

from edge_landing.runtime.core.camera import Intrinsics  # noqa: E402
from edge_landing.runtime.fusion.motion import CameraPose, MotionConfig, MotionStage  # noqa: E402
from tests.test_motion import INTR, MOUNT, _flat_world, _frames  # noqa: E402

DIST = (-0.25, 0.06, 0.0, 0.0, 0.0)     # barrel: 63 px at the corners of a 320×240, 90° image
LENS = Intrinsics(INTR.width, INTR.height, INTR.fx, INTR.fy, INTR.cx, INTR.cy, DIST)


def _distort_maps():
    k_cv = np.array([[INTR.fx, 0.0, INTR.cx - 0.5], [0.0, INTR.fy, INTR.cy - 0.5], [0.0, 0.0, 1.0]])
    yy, xx = np.mgrid[0:INTR.height, 0:INTR.width].astype(np.float64)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10)
    src = cv2.undistortPoints(np.stack([xx, yy], -1).reshape(-1, 1, 2), k_cv, np.asarray(DIST), R=None, P=k_cv,
                              criteria=criteria).reshape(INTR.height, INTR.width, 2).astype(np.float32)
    return src[..., 0], src[..., 1]


def _heights(intrinsics, box_ne):
    """One 12 m sideways pair at 40 m over a 2 m box, distorted frames: (result, the pinhole render)."""
    map_x, map_y = _distort_maps()
    world = _flat_world([[box_ne[0], box_ne[1], 3.0, 3.0, 2.0]])
    stage = MotionStage(MotionConfig(), intrinsics, MOUNT)
    result = render = None
    for _k, t, r, state in _frames(world, [(0.0, -6.0, -40.0), (0.0, 6.0, -40.0)]):
        pose = CameraPose.of(MOUNT, state.attitude, state.position_ned_m, state.agl_m)
        image = cv2.remap(r.rgb, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        result, render = stage.update(image, pose, t, focus_ned_m=np.array([box_ne[0], box_ne[1], 0.0])), r
    assert result is not None
    return result, render


def test_geometry_through_a_calibrated_lens_reads_level_ground_and_the_box():
    box = (40.0, 20.0)                                   # off the image's centre, where the lens bends most
    result, render = _heights(LENS, box)
    # The stage undistorts into the pinhole camera with the same matrix: its pixels are the render's pixels.
    pts = render.geometry.points_ned[result.rows, result.cols]
    h = result.height_m
    ground = (np.abs(pts[..., 2]) < 0.01) & (np.hypot(pts[..., 0] - box[0], pts[..., 1] - box[1]) > 8.0) & np.isfinite(h)
    top = (np.abs(pts[..., 2] + 2.0) < 0.01) & np.isfinite(h)
    sigma = float(np.median(result.sigma_m[ground]))
    assert ground.sum() > 2000 and top.sum() > 20 and sigma < 0.5
    assert abs(float(np.median(h[ground]))) < 0.15 and np.percentile(np.abs(h[ground]), 90) < 0.6
    assert abs(float(np.median(h[top])) - 2.0) <= 3 * float(np.median(result.sigma_m[top]))

    ignored, _ = _heights(INTR, box)                     # the same frames read as a pinhole
    g = ground & np.isfinite(ignored.height_m)
    assert np.percentile(np.abs(ignored.height_m[g]), 90) > 5.0 and float(np.median(ignored.sigma_m[g])) > 2.0
