"""A camera on a gimbal (runtime/io/gimbal.py): its reported orientation, matched to the frame, places the rays.

The expected directions are built by hand from the protocol's definition (roll and pitch relative to the horizon,
yaw relative to north or to the vehicle's heading), not with the runtime's rotation code.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from edge_landing.runtime.core.camera import Attitude, Intrinsics, Mount, ned_from_camera
from edge_landing.runtime.core.messages import VehicleState
from edge_landing.runtime.fusion.fuser import FusionConfig, LandingFuser
from edge_landing.runtime.io.gimbal import (
    FLAG_RETRACT,
    FLAG_YAW_IN_EARTH_FRAME,
    FLAG_YAW_IN_VEHICLE_FRAME,
    FLAG_YAW_LOCK,
    GimbalSeries,
    mount_from_gimbal,
)
from edge_landing.runtime.io.telemetry import TelemetryBuffer
from tests.fusion_scenes import Box, Scene, check_target_on_gt, prediction

VEHICLE = Attitude(math.radians(6.0), math.radians(-12.0), math.radians(30.0))   # banking and speeding up


def quat(roll_deg: float, pitch_deg: float, yaw_deg: float) -> tuple:
    """ZYX Euler angles to (w, x, y, z), the textbook half-angle product."""
    r, p, y = (math.radians(a) / 2.0 for a in (roll_deg, pitch_deg, yaw_deg))
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return (cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy)


def optical_axis_ned(mount: Mount, attitude: Attitude) -> np.ndarray:
    return ned_from_camera(mount, attitude) @ np.array([0.0, 0.0, 1.0])      # camera z = the optical axis


def axis(heading_deg: float, depression_deg: float) -> np.ndarray:
    h, d = math.radians(heading_deg), math.radians(depression_deg)
    return np.array([math.cos(d) * math.cos(h), math.cos(d) * math.sin(h), math.sin(d)])


@pytest.mark.parametrize("flags", [FLAG_YAW_IN_VEHICLE_FRAME, 0])      # 0: an older device without YAW_LOCK
def test_vehicle_frame_yaw_follows_the_heading_and_ignores_the_tilt(flags):
    series = GimbalSeries()
    assert series.add(quat(0.0, -45.0, 0.0), flags, 0, sample_s=10.0, arrival_s=10.0)
    mount, why = series.mount_at(10.0, VEHICLE, now_s=10.1)
    assert mount is not None, why
    np.testing.assert_allclose(optical_axis_ned(mount, VEHICLE), axis(30.0, 45.0), atol=1e-9)
    # The camera's horizontal axis stays level: a stabilised gimbal takes out the vehicle's 6° bank.
    right = ned_from_camera(mount, VEHICLE) @ np.array([1.0, 0.0, 0.0])
    assert abs(right[2]) < 1e-9
    # The fixed mount would look 12° lower and banked.
    fixed = optical_axis_ned(Mount(), VEHICLE)
    assert math.degrees(math.acos(float(fixed @ axis(30.0, 45.0)))) > 10.0


@pytest.mark.parametrize("flags", [FLAG_YAW_IN_EARTH_FRAME, FLAG_YAW_LOCK])
def test_earth_frame_yaw_is_north_whatever_the_heading(flags):
    series = GimbalSeries()
    series.add(quat(0.0, -30.0, 90.0), flags, 0, sample_s=1.0, arrival_s=1.0)
    for heading in (0.0, 30.0, -150.0):
        att = Attitude(0.0, math.radians(5.0), math.radians(heading))
        mount, _ = series.mount_at(1.0, att)
        np.testing.assert_allclose(optical_axis_ned(mount, att), axis(90.0, 30.0), atol=1e-9)


def test_a_camera_looking_straight_down_keeps_its_image_axes():
    """At -90° pitch roll and yaw turn about one axis (gimbal lock): the rotation must survive the angles."""
    series = GimbalSeries()
    series.add(quat(0.0, -90.0, 0.0), FLAG_YAW_IN_VEHICLE_FRAME, 0, sample_s=1.0, arrival_s=1.0)
    att = Attitude(0.0, 0.0, math.radians(40.0))
    mount, _ = series.mount_at(1.0, att)
    r = ned_from_camera(mount, att)
    np.testing.assert_allclose(r @ [0.0, 0.0, 1.0], [0.0, 0.0, 1.0], atol=1e-9)           # straight down
    np.testing.assert_allclose(r @ [0.0, -1.0, 0.0], axis(40.0, 0.0), atol=1e-9)          # image up = heading


def test_reports_between_frames_are_interpolated_the_short_way():
    series = GimbalSeries()
    series.add(quat(0.0, -40.0, 0.0), FLAG_YAW_IN_VEHICLE_FRAME, 0, sample_s=1.0, arrival_s=1.0)
    # The same kind of rotation sent as -q (both signs are valid): interpolation must not swing through 180°.
    series.add(tuple(-v for v in quat(0.0, -50.0, 0.0)), FLAG_YAW_IN_VEHICLE_FRAME, 0, sample_s=1.2, arrival_s=1.2)
    level = Attitude()
    mount, _ = series.mount_at(1.1, level)
    np.testing.assert_allclose(optical_axis_ned(mount, level), axis(0.0, 45.0), atol=1e-3)


@pytest.mark.parametrize("q, flags, failure, why", [
    ((float("nan"), 0.0, 0.0, 0.0), 0, 0, "not finite"),
    ((0.5, 0.0, 0.0, 0.0), 0, 0, "unit length"),
    (quat(0, -45, 0), 0, 4, "failure"),
    (quat(0, -45, 0), FLAG_RETRACT, 0, "retracted"),
    (quat(0, -45, 0), FLAG_YAW_IN_EARTH_FRAME | FLAG_YAW_IN_VEHICLE_FRAME, 0, "both yaw frames"),
])
def test_implausible_reports_are_refused_and_counted(q, flags, failure, why):
    series = GimbalSeries()
    assert not series.add(q, flags, failure, sample_s=1.0, arrival_s=1.0)
    mount, reason = series.mount_at(1.0, Attitude(), now_s=1.0)
    assert mount is None and why in reason
    assert sum(series.rejected().values()) == 1


def test_no_mount_from_a_silent_stale_or_distant_gimbal():
    series = GimbalSeries()
    assert series.mount_at(1.0, Attitude(), 1.0)[1] == "no gimbal attitude"
    series.add(quat(0, -45, 0), 0, 0, sample_s=1.0, arrival_s=1.0)
    assert series.mount_at(1.0, Attitude(), now_s=1.5)[0] is not None
    assert "stale" in series.mount_at(1.0, Attitude(), now_s=1.7)[1]                   # fresh_s 0.6
    assert "within" in series.mount_at(1.4, Attitude(), now_s=1.4)[1]                  # window 0.25 s
    assert not series.add(quat(0, -40, 0), 0, 0, sample_s=1.0, arrival_s=1.1)          # not newer


def test_a_change_of_yaw_frame_drops_the_reports_of_the_other_frame():
    series = GimbalSeries()
    series.add(quat(0, -45, 0), FLAG_YAW_IN_VEHICLE_FRAME, 0, sample_s=1.0, arrival_s=1.0)
    series.add(quat(0, -45, 90), FLAG_YAW_IN_EARTH_FRAME, 0, sample_s=1.1, arrival_s=1.1)
    att = Attitude(0.0, 0.0, 0.0)
    mount, _ = series.mount_at(1.0, att)           # the vehicle-frame report is gone; the earth one is nearest
    np.testing.assert_allclose(optical_axis_ned(mount, att), axis(90.0, 45.0), atol=1e-9)


def test_telemetry_with_a_gimbal_gives_no_match_without_its_report():
    gimbal = GimbalSeries()
    telemetry = TelemetryBuffer(gimbal=gimbal)
    telemetry.add_attitude(0.0, -0.2, 0.5, arrival_s=5.0, sample_s=5.0)
    telemetry.add_position(1.0, 2.0, -40.0, arrival_s=5.0, sample_s=5.0)
    match = telemetry.lookup(5.0, now_s=5.05)
    assert not match.fresh and match.reason == "no gimbal attitude"
    gimbal.add(quat(0, -45, 0), FLAG_YAW_IN_VEHICLE_FRAME, 0, sample_s=5.0, arrival_s=5.0)
    match = telemetry.lookup(5.0, now_s=5.05)
    assert match.fresh and match.state is not None and match.state.camera_mount is not None
    np.testing.assert_allclose(optical_axis_ned(match.state.camera_mount, match.state.attitude),
                               axis(math.degrees(0.5), 45.0), atol=1e-6)
    newest = telemetry.newest_state()
    assert newest is not None and newest.camera_mount == match.state.camera_mount
    without = TelemetryBuffer()
    without.add_attitude(0.0, -0.2, 0.5, arrival_s=5.0, sample_s=5.0)
    assert without.lookup(5.0, now_s=5.05).state.camera_mount is None      # the fixed mount applies


def test_fusion_places_the_ground_with_the_gimbal_and_misplaces_it_with_the_fixed_mount():
    intr = Intrinsics.from_hfov(160, 120)
    position = np.array([0.0, 0.0, -40.0])
    true_mount = mount_from_gimbal(np.array(quat(0.0, -45.0, 0.0)), False, VEHICLE)
    look = position + 40.0 / math.tan(math.radians(45.0)) * axis(30.0, 0.0)
    scene = Scene(boxes=(Box((look[0] - 3, look[1] - 3, -2.0), (look[0] + 3, look[1] + 3, 0.0)),))
    render = scene.render(intr, true_mount, VEHICLE, position)
    cfg = FusionConfig(allow_unconfirmed=True)

    gimballed = LandingFuser(cfg, intr, Mount()).update(
        prediction(render), VehicleState(0.0, VEHICLE, position, camera_mount=true_mount))
    assert gimballed.valid, gimballed.reason
    check_target_on_gt(gimballed, render, "with the gimbal's mount", cfg)
    cam = ned_from_camera(true_mount, VEHICLE).T @ (gimballed.position_ned_m - position)
    assert math.atan2(cam[0], cam[2]) == pytest.approx(gimballed.angle_x_rad, abs=1e-9)

    fixed = LandingFuser(cfg, intr, Mount()).update(prediction(render), VehicleState(0.0, VEHICLE, position))
    # Read with the body-fixed mount, the same depth lands 12° off: the ground comes out tilted or misplaced.
    assert not fixed.valid or float(np.linalg.norm(fixed.position_ned_m - gimballed.position_ned_m)) > 3.0


def test_only_the_first_gimbal_heard_is_read():
    """A second camera's gimbal on the same system would be mixed into the first one's orientation."""
    series = GimbalSeries()
    assert series.add(quat(0, -45, 0), 0, 0, sample_s=1.0, arrival_s=1.0, device=(154, 0))
    assert not series.add(quat(0, -90, 0), 0, 0, sample_s=1.1, arrival_s=1.1, device=(1, 2))
    assert series.add(quat(0, -45, 0), 0, 0, sample_s=1.2, arrival_s=1.2, device=(154, 0))
    assert series.rejected() == {"another gimbal's report": 1}
    assert not series.add(quat(0, -45, 0), 0, 0, sample_s=None, arrival_s=1.3, device=(154, 0))
