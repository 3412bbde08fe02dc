"""One rule for a target's pose-dependent fields, whichever path made it (core/target_frames.py).

A target is fused from a frame, held from memory by continuity, or re-expressed at the newest telemetry
before it leaves. Body vector, range, angles and sizes must follow the same rule on each path, or what the
autopilot receives depends on which path ran.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from edge_landing.runtime.core.camera import Attitude, Mount
from edge_landing.runtime.core.messages import EVIDENCE_GEOMETRY, Target, VehicleState
from edge_landing.runtime.core.target_frames import aim_at_pose, aim_from_offset
from edge_landing.runtime.pipeline.trust import Continuity, ContinuityConfig

MOUNT = Mount(pitch_rad=math.radians(-45.0))


def test_disc_sizes_are_full_across_and_foreshortened_along_the_line_of_sight():
    below = aim_from_offset(np.array([0.0, 0.0, 30.0]), Attitude(), 3.0)        # straight down: a circle
    assert below is not None
    assert below.size_x_rad == pytest.approx(below.size_y_rad) == pytest.approx(2 * math.atan2(3.0, 30.0))
    ahead = aim_from_offset(np.array([30.0, 0.0, 30.0]), Attitude(), 3.0)       # 45° down: squashed by sin 45°
    assert ahead is not None
    assert ahead.size_x_rad == pytest.approx(2 * math.atan2(3.0, ahead.range_m))
    assert ahead.size_y_rad == pytest.approx(2 * math.atan2(3.0 * math.sqrt(0.5), ahead.range_m))
    assert math.isnan(ahead.angle_x_rad)                                           # no mount: no angles


def test_a_point_on_the_optical_axis_has_zero_angles_and_yaw_moves_it():
    on_axis = aim_from_offset(np.array([30.0, 0.0, 30.0]), Attitude(), 2.0, MOUNT)
    assert on_axis is not None
    assert on_axis.angle_x_rad == pytest.approx(0.0, abs=1e-12) and on_axis.angle_y_rad == pytest.approx(0.0, abs=1e-12)
    turned = aim_from_offset(np.array([30.0, 0.0, 30.0]), Attitude(yaw_rad=math.radians(10.0)), 2.0, MOUNT)
    assert turned is not None and turned.angle_x_rad < -0.05                      # yawed right: the spot is left
    np.testing.assert_allclose(turned.body_frd_m, Attitude(yaw_rad=math.radians(10.0)).ned_from_body().T
                               @ np.array([30.0, 0.0, 30.0]))


@pytest.mark.parametrize("offset", [np.zeros(3), np.array([np.nan, 0.0, 1.0]), np.array([np.inf, 0.0, 1.0])])
def test_no_aim_from_a_zero_or_non_finite_offset(offset):
    assert aim_from_offset(offset, Attitude(), 3.0, MOUNT) is None


def test_no_aim_without_a_vehicle_position():
    assert aim_at_pose(np.array([5.0, 0.0, 0.0]), VehicleState(0.0), 3.0, MOUNT) is None


def test_a_held_target_has_the_fields_a_fused_one_would_have_at_that_pose():
    """Continuity re-sends a committed spot with the same body vector, range, angles and sizes that fusion gives a
    spot with that clearance at that pose (before: sizes unforeshortened, angles missing)."""
    cont = Continuity(ContinuityConfig(), MOUNT)
    spot = np.array([20.0, 4.0, 0.0])
    start = VehicleState(0.0, position_ned_m=np.array([0.0, 0.0, -30.0]), agl_m=30.0)
    for i in range(3):
        offset = spot - start.position_ned_m
        cont.step(Target(i, 0.1 * i, True, position_body_frd_m=offset, position_ned_m=spot, clearance_m=3.0,
                         confidence=0.9, evidence=EVIDENCE_GEOMETRY), start, None, True)
    assert cont.spot is not None
    later = VehicleState(0.5, Attitude(0.05, -0.1, 0.3), position_ned_m=np.array([4.0, 1.0, -28.0]), agl_m=28.0)
    held, _ = cont.step(Target.none(3, 0.5, "no safe spot"), later, None, True)
    assert held.valid and held.reason.startswith("held: committed spot")
    want = aim_at_pose(spot, later, 3.0, MOUNT)
    assert want is not None
    np.testing.assert_allclose(held.position_body_frd_m, want.body_frd_m, atol=1e-12)
    for field in ("range_m", "angle_x_rad", "angle_y_rad", "size_x_rad", "size_y_rad"):
        assert getattr(held, field) == pytest.approx(getattr(want, field), abs=1e-12), field
    assert held.size_y_rad < held.size_x_rad                                       # oblique view: foreshortened
