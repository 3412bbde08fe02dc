"""Settings of the telemetry buffer (``telemetry.py``): matching, clock and plausibility (seconds, metres, radians).

Each limit's reason is beside it; ARCHITECTURE.md §12 gives the trust rules they serve.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from edge_landing.runtime.io.timesync import TimeSyncConfig

__all__ = ["TelemetryConfig"]


@dataclass(frozen=True)
class TelemetryConfig:
    """Matching, clock and plausibility settings (seconds, metres, radians)."""

    window_s: float = 0.25      # how far from the capture time a sample may be and still count
    history_s: float = 5.0      # how much history to keep
    reboot_jump_s: float = 2.0  # a remote clock that goes back this much (for clock_window_s) means a reboot
    fresh_s: float = 0.4        # the newest attitude must have arrived at most this long ago
    clock_window_s: float = 2.0  # the clock offset is re-estimated from the fastest sample of each window
    # How fast the autopilot's clock may fall behind this one (seconds per second): a window's fastest sample may
    # raise the offset by no more than this × the window. ArduPilot's JitterCorrection also moves a sample that is
    # more than 500 ms late forward to 500 ms, and its offset with it; that made telemetry delivered 0.7-1.7 s
    # late, in bursts, look fresh (99 targets sent from it in 3 s). A crystal drifts 1e-4; 0.1 leaves room for a
    # simulator's clock running at 90 % of real time (and the 5 % slow clock of tests/test_trust.py).
    max_drift: float = 0.1
    # A sample stamped further than this in the future of the offset is dropped (unless the clock stays ahead for
    # clock_window_s): adopted, one such glitch put every later sample that far in the past, beyond window_s, and
    # telemetry was lost for 2.7 s (0.5 s: one sample 0.45 s ahead). Up to this much it only shifts the matching.
    max_future_s: float = 0.15
    clock_memory_windows: int = 10  # "from the future" is judged against the fastest sample of this many windows
    max_tilt_rad: float = math.radians(60.0)  # |roll|, |pitch| beyond this are not a multicopter in flight
    max_agl_m: float = 1000.0   # relative altitude above this is not believed
    max_position_m: float = 1.0e5
    max_samples: int = 4096     # per quantity, whatever the rate (a flood of messages cannot grow memory)
    # A local position that moves faster than this (and by more than max(min_jump_m, speed × interval)) did not
    # fly there: the autopilot's frame moved (an EKF reset, a GPS glitch). The earlier positions are dropped and
    # a new position epoch starts: NED evidence and a committed spot from before mean nothing in the new frame.
    max_speed_mps: float = 40.0
    min_jump_m: float = 5.0
    # Where the samples carry the autopilot's own velocity (LOCAL_POSITION_NED does), a smaller move of the frame is
    # caught too (position_resets.py): metres in one step while the velocity stays smooth (an EKF lane switch, a
    # GPS glitch's recovery), which 5 m at 40 m/s let by. Over more than velocity_check_s only max_speed_mps judges;
    # distrust_after such resets within distrust_s mean the velocities do not describe the positions (not used).
    min_reset_m: float = 1.0
    max_accel_mps2: float = 15.0
    velocity_error_mps: float = 1.0
    velocity_check_s: float = 1.0
    distrust_after: int = 3
    distrust_s: float = 10.0
    # A heading that turns faster than this (and by more than min_yaw_jump_rad) was reset, not flown (an EKF yaw
    # reset): everything placed in NED with the old heading is rotated about the vehicle, so a new epoch starts.
    max_yaw_rate_rad_s: float = 2.0 * math.pi
    min_yaw_jump_rad: float = math.radians(15.0)
    # A capture time with telemetry on one side only (the next sample not yet arrived) takes the nearest sample
    # moved along its own rate (ATTITUDE's gyro rates, LOCAL_POSITION_NED's velocity) for at most this long,
    # instead of holding it: 50 ms of a 30 deg/s turn is 1.5 deg, 1.3 m on the ground at 50 m range.
    max_extrapolation_s: float = 0.1
    max_body_rate_rad_s: float = 10.0   # gyro rates beyond this are not believed (nor used)
    # A sample's rate is used only while it agrees with how its value actually changed since the sample before
    # (within abs + rel x the larger of the two, per component): a unit slip (deg/s sent as rad/s), a frame slip
    # or a partial implementation sending zeros while the angles move falls back to holding the nearest sample.
    rate_tolerance_rad_s: float = 0.2
    rate_tolerance_mps: float = 1.0
    rate_tolerance_share: float = 0.3
    # The autopilot's own estimator status (EKF_STATUS_REPORT, ESTIMATOR_STATUS) counts for this long after it
    # arrived; without one the estimate is taken as good (autopilots that do not send it).
    estimator_status_s: float = 3.0
    timesync: TimeSyncConfig = TimeSyncConfig()
