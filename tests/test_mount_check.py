"""The mount check (runtime/fusion/mount_check.py): the camera's orientation measured from the images of a flight.

A textured ground plane is imaged by a pinhole camera (cv2.remap of each pixel's ray onto the plane): exact
geometry, no renderer, a few milliseconds a frame. The camera is turned from the mount edge-run is given; the
check must find by how much, and say nothing when the mount is right.
"""
from __future__ import annotations

import math
import re
from typing import List, Tuple

import cv2
import numpy as np
import pytest

from edge_landing.runtime.core.camera import Attitude, Intrinsics, Mount, ned_from_camera
from edge_landing.runtime.fusion.keyframes import Keyframe
from edge_landing.runtime.fusion.mount_check import MountCheck, MountCheckConfig
from edge_landing.runtime.fusion.parallax import CameraPose
from edge_landing.runtime.pipeline.mount_watch import MountWatch

W, H = 640, 480
INTR = Intrinsics.from_hfov(W, H, math.radians(90.0))
K = np.array([[INTR.fx, 0.0, INTR.cx - 0.5], [0.0, INTR.fy, INTR.cy - 0.5], [0.0, 0.0, 1.0]])
TEXTURE_M_PER_PX, TEXTURE_PX = 0.2, 2000        # 400 m of ground around the origin


def _texture(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    out = np.zeros((TEXTURE_PX, TEXTURE_PX), np.float32)
    for sigma in (1.0, 3.0, 9.0):
        n = cv2.GaussianBlur(rng.normal(0, 1, out.shape).astype(np.float32), (0, 0), sigma)
        out += n / n.std()
    return np.clip(128 + 25 * out, 0, 255).astype(np.uint8)


def _image(texture: np.ndarray, r_nc: np.ndarray, centre: np.ndarray, slope_n: float) -> np.ndarray:
    """The ground z = -slope_n · north (NED, down positive) seen from ``centre`` with camera rotation ``r_nc``."""
    xx, yy = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    rays = np.stack([xx, yy, np.ones_like(xx)], -1) @ np.linalg.inv(K).T @ r_nc.T
    # (c + λ r)_z = -slope (c + λ r)_n  ->  λ = -(c_z + slope c_n) / (r_z + slope r_n)
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = -(centre[2] + slope_n * centre[0]) / (rays[..., 2] + slope_n * rays[..., 0])
    lam = np.where(lam > 0, lam, np.nan)
    north, east = centre[0] + lam * rays[..., 0], centre[1] + lam * rays[..., 1]
    half = TEXTURE_PX * TEXTURE_M_PER_PX / 2
    mx = ((east + half) / TEXTURE_M_PER_PX).astype(np.float32)
    my = ((north + half) / TEXTURE_M_PER_PX).astype(np.float32)
    return cv2.remap(texture, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)


def _flight(true_mount: Mount, given: Mount, headings_deg: Tuple[float, ...], slope_n: float = 0.0,
            agl_m: float = 40.0) -> List[Tuple[Keyframe, float]]:
    """Keyframes every 0.5 s of a level flight at 8 m/s, one leg per heading, posed with the ``given`` mount."""
    texture = _texture()
    out, pos, t = [], np.array([-60.0, -40.0, -agl_m]), 0.0
    for heading in headings_deg:
        yaw = math.radians(heading)
        for _ in range(14):
            att = Attitude(yaw_rad=yaw)
            grey = _image(texture, ned_from_camera(true_mount, att), pos, slope_n)
            ground_z = -slope_n * pos[0]
            pose = CameraPose(ned_from_camera(given, att), pos.copy(), float(ground_z - pos[2]))
            out.append((Keyframe(t, grey, pose), yaw))
            pos = pos + 4.0 * np.array([math.cos(yaw), math.sin(yaw), 0.0])
            t += 0.5
    return out


def _check(frames: List[Tuple[Keyframe, float]], given: Mount = Mount()) -> MountCheck:
    check = MountCheck(MountCheckConfig(min_pairs=8), K, given)
    for i in range(1, len(frames)):
        ring = [kf for kf, _ in frames[max(0, i - 8): i + 1]]
        check.add(ring, frames[i][1])
    return check


def _deg(mount: Mount) -> np.ndarray:
    return np.degrees([mount.pitch_rad, mount.roll_rad, mount.yaw_rad])


@pytest.mark.parametrize("true_deg", [(-48.0, 1.0, -1.0), (-42.0, -1.5, 2.0)])
def test_a_turned_camera_is_measured_and_said(true_deg, caplog):
    true = Mount(pitch_rad=math.radians(true_deg[0]), roll_rad=math.radians(true_deg[1]),
                 yaw_rad=math.radians(true_deg[2]))
    est = _check(_flight(true, Mount(), (30.0, 120.0))).estimate()
    assert est is not None and est.pairs >= 16 and est.headings == 2
    assert np.allclose(_deg(est.corrected()), true_deg, atol=0.3), _deg(est.corrected())
    assert est.attention and all(sigma < 0.5 for *_, sigma in est.axes())
    statuses: list = []
    watch = MountWatch(lambda text, sev: statuses.append(text) or True)
    with caplog.at_level("WARNING"):
        watch.update(est)
    suggested = re.search(r"--mount-pitch (\S+) --mount-roll (\S+) --mount-yaw (\S+)", caplog.text)
    assert suggested and np.allclose([float(v) for v in suggested.groups()], true_deg, atol=0.3)
    assert statuses and len(statuses[0]) <= 50 and "check edge mount" in statuses[0]
    assert "check the mount" in watch.line()


def test_one_heading_measures_the_pitch_and_says_what_it_cannot():
    true = Mount(pitch_rad=math.radians(-48.0))
    est = _check(_flight(true, Mount(), (30.0,))).estimate()
    assert est is not None and est.headings == 1
    (_, _, pitch, pitch_sigma), *_ = est.axes()
    assert pitch == pytest.approx(-48.0, abs=0.3) and pitch_sigma < 0.5 and est.attention


def test_a_right_mount_is_not_a_problem():
    est = _check(_flight(Mount(), Mount(), (30.0, 120.0))).estimate()
    assert est is not None and est.turn_deg < 0.3 and not est.attention
    assert MountWatch().line() == ""


@pytest.mark.parametrize("headings", [(0.0, 90.0), (0.0,), (90.0,)])
def test_sloped_ground_is_not_taken_for_a_turned_camera(headings):
    # 3° of slope to the north: it tilts the ground's normal as a turned camera would. The direction of travel
    # separates them along the track; across it a second heading does, and on one heading σ says it cannot.
    est = _check(_flight(Mount(), Mount(), headings, slope_n=math.tan(math.radians(3.0)))).estimate()
    assert est is not None and not est.attention, est.describe()
    if len(headings) == 2:
        assert est.turn_deg < 0.3 and est.ground_slope_deg == pytest.approx(3.0, abs=0.3)


def test_hovering_or_a_blank_view_gives_no_pairs():
    texture_free = np.full((H, W), 120, np.uint8)
    pose = CameraPose(ned_from_camera(Mount()), np.array([0.0, 0.0, -40.0]), 40.0)
    check = MountCheck(MountCheckConfig(min_pairs=8), K, Mount())
    hover = [Keyframe(0.5 * i, texture_free, pose) for i in range(5)]
    assert not check.add(hover, 0.0) and check.last_reason == "no keyframe at a useful baseline"
    moved = [hover[0], Keyframe(1.0, texture_free, CameraPose(pose.r_nc, np.array([8.0, 0.0, -40.0]), 40.0))]
    assert not check.add(moved, 0.0) and "features" in check.last_reason
    assert check.estimate() is None
