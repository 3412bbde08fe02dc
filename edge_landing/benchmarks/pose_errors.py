"""Telemetry as a real autopilot gives it: the simulator's exact pose with an estimator's errors added.

The replay benchmarks feed fusion the simulator's exact pose; a real EKF's differs, and motion geometry reads
every pose error between two frames as parallax. What matters for geometry is the *relative* error between
frames a fraction of a second apart, which comes from four sources (typical multirotor EKF figures):

- a slowly varying attitude error (accelerometer bias, mount misalignment): a few tenths of a degree, over
  tens of seconds; it nearly cancels between frames but tilts the ground plane seen by the camera;
- a slowly varying position error (GPS): decimetres over tens of seconds, so centimetres between frames;
- the camera's and the telemetry's clocks disagreeing: the pose matched to a frame is the pose a few tens of
  milliseconds away, so its error is the vehicle's speed and rotation rate times that skew;
- white noise on position, attitude and the height above ground (rangefinder).

Slow errors are smooth: each axis is a sum of a few sinusoids with seeded random periods (around the
configured one) and phases, so the error drifts at about 2π σ / period (a first-order Gauss-Markov process
would jitter from frame to frame, which an estimator's integrated output does not). Pure numpy; the errors are
applied to what the runtime sees, never to what the judge ray-casts against.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Optional

import numpy as np

from edge_landing.runtime.core.camera import Attitude
from edge_landing.runtime.core.choices import ChoiceEnum
from edge_landing.runtime.core.messages import VehicleState


@dataclass(frozen=True)
class PoseErrorConfig:
    """Degrees, metres, seconds."""

    attitude_deg: float = 0.0          # slow attitude error, 1 σ per axis ...
    attitude_period_s: float = 120.0   # ... drifting over about this long (0.5° / 120 s: 0.03°/s, a residual
                                       # gyro bias; 0.013° between frames 0.5 s apart is 0.1 px at 640 px)
    position_m: float = 0.0            # slow position error (GPS through the EKF), 1 σ per axis ...
    position_period_s: float = 60.0    # ... drifting over about this long (0.5 m / 60 s: 5 cm/s)
    clock_skew_s: float = 0.0          # telemetry matched this much late (its pose is this much older)
    attitude_white_deg: float = 0.0    # white noise per sample, 1 σ per axis
    position_white_m: float = 0.0
    agl_white_m: float = 0.0           # rangefinder noise
    seed: int = 0


class PoseErrors(ChoiceEnum):
    NONE = "none"
    TYPICAL = "typical"
    HARSH = "harsh"

    @classmethod
    def _label(cls) -> str:
        return "pose error model"

    def config(self, seed: int = 0) -> PoseErrorConfig:
        if self is PoseErrors.NONE:
            return PoseErrorConfig(seed=seed)
        k = 1.0 if self is PoseErrors.TYPICAL else 3.0    # harsh: three times the errors, nine times the drift
        return PoseErrorConfig(attitude_deg=0.5 * k, attitude_period_s=120.0 / k, position_m=0.5 * k,
                               position_period_s=60.0 / k, clock_skew_s=0.02 * k, attitude_white_deg=0.01 * k,
                               position_white_m=0.01 * k, agl_white_m=0.03 * k, seed=seed)


class NoisyTelemetry:
    """Turns the simulator's exact states, one per frame in time order, into what an autopilot would report."""

    def __init__(self, config: PoseErrorConfig):
        self.config = config
        self._rng = np.random.default_rng(config.seed)
        self._attitude = SlowError(math.radians(config.attitude_deg), config.attitude_period_s, self._rng)
        self._position = SlowError(config.position_m, config.position_period_s, self._rng)
        self._last: Optional[VehicleState] = None
        self.exact = config == PoseErrorConfig(seed=config.seed)

    def __call__(self, state: VehicleState) -> VehicleState:
        """The state as reported (``state`` itself when the errors are all zero)."""
        if self.exact:
            return state
        cfg, last = self.config, self._last
        self._last = state
        seen = _back_in_time(last, state, cfg.clock_skew_s)
        att = seen.attitude
        d_rad = self._attitude.at(state.time_s) + self._rng.normal(0.0, math.radians(cfg.attitude_white_deg), 3)
        attitude = Attitude(att.roll_rad + d_rad[0], att.pitch_rad + d_rad[1], att.yaw_rad + d_rad[2])
        position = None
        if seen.position_ned_m is not None:
            position = (seen.position_ned_m + self._position.at(state.time_s)
                        + self._rng.normal(0.0, cfg.position_white_m, 3))
        agl = None if seen.agl_m is None else max(seen.agl_m + self._rng.normal(0.0, cfg.agl_white_m), 0.0)
        return replace(state, attitude=attitude, position_ned_m=position, agl_m=agl)



class SlowError:
    """A smooth, zero-mean error per axis with standard deviation ``sigma``: ``waves`` sinusoids per axis with
    periods between half and twice ``period_s`` and random phases."""

    waves = 3

    def __init__(self, sigma: float, period_s: float, rng: np.random.Generator, axes: int = 3):
        self._amplitude = sigma * math.sqrt(2.0 / self.waves)
        self._omega = math.tau / (period_s * rng.uniform(0.5, 2.0, (axes, self.waves)))
        self._phase = rng.uniform(0.0, math.tau, (axes, self.waves))

    def at(self, t_s: float) -> np.ndarray:
        return self._amplitude * np.sin(self._omega * t_s + self._phase).sum(axis=1)


def _back_in_time(last: Optional[VehicleState], state: VehicleState, skew_s: float) -> VehicleState:
    """The state ``skew_s`` before ``state``, interpolated from the one before (held at the first sample)."""
    if last is None or skew_s <= 0 or state.time_s <= last.time_s:
        return state
    w = min(skew_s / (state.time_s - last.time_s), 1.0)   # weight of the earlier state
    a, b = last.attitude, state.attitude
    yaw_step = math.remainder(b.yaw_rad - a.yaw_rad, math.tau)
    attitude = Attitude(b.roll_rad + w * (a.roll_rad - b.roll_rad), b.pitch_rad + w * (a.pitch_rad - b.pitch_rad),
                        b.yaw_rad - w * yaw_step)
    position = state.position_ned_m
    if position is not None and last.position_ned_m is not None:
        position = position + w * (last.position_ned_m - position)
    agl = state.agl_m
    if agl is not None and last.agl_m is not None:
        agl = agl + w * (last.agl_m - agl)
    return replace(state, attitude=attitude, position_ned_m=position, agl_m=agl)
