"""The replay benchmarks' telemetry errors (benchmarks.pose_errors): what an autopilot's estimator adds."""
from __future__ import annotations

import math

import numpy as np
import pytest

from edge_landing.benchmarks.pose_errors import NoisyTelemetry, PoseErrorConfig, PoseErrors
from edge_landing.runtime.core.camera import Attitude
from edge_landing.runtime.core.messages import VehicleState


def flight(frames: int = 600, fps: float = 10.0, speed_mps: float = 5.0, yaw_rate: float = 0.1):
    """Level flight north at ``speed_mps``, turning at ``yaw_rate`` rad/s, 40 m up."""
    for k in range(frames):
        t = k / fps
        yield VehicleState(t, Attitude(0.0, 0.0, math.remainder(yaw_rate * t, math.tau)),
                           np.array([speed_mps * t, 0.0, -40.0]), 40.0, "sim")


def test_no_errors_gives_the_state_itself():
    reported = NoisyTelemetry(PoseErrors.NONE.config())
    for s in flight(5):
        assert reported(s) is s


def test_clock_skew_reports_the_pose_that_much_older():
    reported = NoisyTelemetry(PoseErrorConfig(clock_skew_s=0.03))
    states = list(flight(3))
    seen = [reported(s) for s in states]
    assert seen[0].position_ned_m[0] == pytest.approx(0.0)          # nothing older to go back to
    assert seen[2].position_ned_m[0] == pytest.approx(5.0 * (0.2 - 0.03))
    assert seen[2].attitude.yaw_rad == pytest.approx(0.1 * (0.2 - 0.03))
    assert seen[2].time_s == states[2].time_s                        # stamped as the frame, as a skew would be


def test_typical_errors_are_slow_so_frames_close_in_time_agree_far_better_than_the_absolute_error():
    cfg = PoseErrors.TYPICAL.config(seed=3)
    reported = NoisyTelemetry(replace_skew(cfg))
    states = list(flight())
    seen = [reported(s) for s in states]
    pos_err = np.array([b.position_ned_m - s.position_ned_m for s, b in zip(states, seen)])
    att_err = np.array([[b.attitude.roll_rad - s.attitude.roll_rad, b.attitude.pitch_rad - s.attitude.pitch_rad]
                        for s, b in zip(states, seen)])
    # absolute: of the configured size (one σ, 600 samples of a slowly varying process: loose bounds)
    assert 0.1 < np.abs(pos_err).max() < 4 * cfg.position_m
    assert math.radians(0.05) < np.abs(att_err).max() < 4 * math.radians(cfg.attitude_deg)
    # between frames 0.5 s apart: an order of magnitude smaller
    assert np.abs(pos_err[5:] - pos_err[:-5]).std() < 0.2 * pos_err.std()
    assert np.abs(att_err[5:] - att_err[:-5]).std() < 0.2 * att_err.std()
    again = NoisyTelemetry(replace_skew(cfg))
    assert all(np.array_equal(again(s).position_ned_m, b.position_ned_m) for s, b in zip(states, seen))  # seeded


def test_harsh_is_three_times_typical():
    typical, harsh = PoseErrors.TYPICAL.config(), PoseErrors.from_string("harsh").config()
    assert harsh.attitude_deg == pytest.approx(3 * typical.attitude_deg)
    assert harsh.clock_skew_s == pytest.approx(3 * typical.clock_skew_s)


def replace_skew(cfg: PoseErrorConfig) -> PoseErrorConfig:
    """Without the clock skew, so the error is the estimator's alone."""
    from dataclasses import replace

    return replace(cfg, clock_skew_s=0.0)
