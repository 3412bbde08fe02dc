"""Telemetry matched to a capture time just past the newest sample: carried along the sample's own rate (the
gyro rates, the velocity) while that rate agrees with the series, held otherwise (io.series, io.telemetry)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from edge_landing.runtime.io.telemetry import TelemetryBuffer, _euler_rates

YAW_RATE = 0.5          # rad/s
STEP_S = 0.05           # 20 Hz, edge-run's telemetry rate


def turning(rates=lambda t: (0.0, 0.0, YAW_RATE), until_s=1.0) -> TelemetryBuffer:
    buf = TelemetryBuffer()
    for k in range(int(round(until_s / STEP_S)) + 1):
        t = k * STEP_S
        assert buf.add_attitude(0.0, 0.0, YAW_RATE * t, arrival_s=t, sample_s=t, body_rates_rad_s=rates(t))
    return buf


def yaw_at(buf: TelemetryBuffer, t_s: float) -> float:
    match = buf.lookup(t_s, now_s=t_s + 0.01)
    assert match.fresh, match.reason
    return match.state.attitude.yaw_rad


def test_a_capture_past_the_newest_attitude_is_carried_along_the_gyro_rate():
    buf = turning()
    assert yaw_at(buf, 1.04) == pytest.approx(YAW_RATE * 1.04, abs=1e-9)     # held, it read 0.500
    assert buf.rates_refused() == {}


def test_between_two_samples_it_is_still_interpolated():
    buf = turning()
    assert yaw_at(buf, 0.525) == pytest.approx(YAW_RATE * 0.525, abs=1e-9)


def test_carried_for_at_most_a_tenth_of_a_second():
    buf = turning()
    assert yaw_at(buf, 1.2) == pytest.approx(YAW_RATE * (1.0 + 0.1), abs=1e-9)


@pytest.mark.parametrize("why, rates", [
    ("zeros from a partial implementation", lambda t: (0.0, 0.0, 0.0)),
    ("deg/s sent as rad/s", lambda t: (0.0, 0.0, math.degrees(YAW_RATE) / 20.0)),
    ("the wrong axis", lambda t: (YAW_RATE, 0.0, 0.0)),
])
def test_rates_that_disagree_with_the_angles_are_not_used(why, rates):
    buf = turning(rates)
    assert yaw_at(buf, 1.04) == pytest.approx(YAW_RATE * 1.0, abs=1e-9), why     # the newest sample, held
    assert buf.rates_refused()["attitude rates"] >= 19


def test_without_rates_the_newest_sample_is_held_as_before():
    buf = turning(lambda t: None)  # type: ignore[arg-type,return-value]
    assert yaw_at(buf, 1.04) == pytest.approx(YAW_RATE * 1.0, abs=1e-9)
    assert buf.rates_refused() == {}


def test_position_is_carried_along_its_velocity_and_held_when_the_velocity_is_another_frames():
    for velocity, expected_north in (((5.0, 0.0, 0.0), 5.0 * 1.04), ((0.0, 5.0, 0.0), 5.0 * 1.0)):
        buf = TelemetryBuffer()
        for k in range(21):
            t = k * STEP_S
            buf.add_attitude(0.0, 0.0, 0.0, arrival_s=t, sample_s=t)
            buf.add_position(5.0 * t, 0.0, -30.0, arrival_s=t, sample_s=t, velocity_ned_mps=velocity)
        state = buf.lookup(1.04, now_s=1.05).state
        assert state is not None and state.position_ned_m is not None
        assert state.position_ned_m[0] == pytest.approx(expected_north, abs=1e-9), velocity


def _rotation(roll: float, pitch: float, yaw: float) -> np.ndarray:
    cr, sr, cp, sp, cy, sy = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch), math.cos(yaw), math.sin(yaw)
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    return rz @ ry @ rx


def _euler(r: np.ndarray) -> np.ndarray:
    return np.array([math.atan2(r[2, 1], r[2, 2]), -math.asin(r[2, 0]), math.atan2(r[1, 0], r[0, 0])])


def test_body_rates_become_euler_rates_of_the_same_rotation():
    roll, pitch, yaw, body = 0.3, -0.2, 1.0, np.array([0.4, -0.7, 0.9])
    h = 1e-6
    skew = np.array([[0, -body[2], body[1]], [body[2], 0, -body[0]], [-body[1], body[0], 0]])
    r0 = _rotation(roll, pitch, yaw)
    r1 = r0 @ (np.eye(3) + skew * h)                         # body rates turn the body frame (right product)
    numeric = (_euler(r1) - _euler(r0)) / h
    rates = _euler_rates(roll, pitch, tuple(body), 10.0)
    assert rates is not None and np.allclose(rates, numeric, atol=1e-4)
    assert _euler_rates(roll, pitch, (float("nan"), 0.0, 0.0), 10.0) is None
    assert _euler_rates(roll, pitch, (0.0, 0.0, 11.0), 10.0) is None
