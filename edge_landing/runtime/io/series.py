"""Time-sorted samples of one telemetry quantity, bounded in time and in count (``telemetry.py`` keeps four).

A sample may carry its quantity's own rate of change (an attitude's Euler rates from the gyros, a position's
velocity). A capture time with samples on both sides is interpolated; one with a sample on one side only (the
usual case right after capture: the next sample is still on its way) takes the nearest sample moved along its
own rate for at most ``max_extrapolation_s``, or the nearest sample as it is when it carries no rate."""
from __future__ import annotations

import bisect
import math
from collections import deque
from typing import Deque, Optional

import numpy as np

__all__ = ["TimeSeries", "wrap_angles"]


def wrap_angles(delta: np.ndarray) -> np.ndarray:
    """Angle differences (rad) taken the short way round, in [-pi, pi) (yaw wraps at ±pi)."""
    wrapped: np.ndarray = (delta + math.pi) % (2 * math.pi) - math.pi
    return wrapped


class TimeSeries:
    """Time-sorted samples of one quantity (times on the local monotonic clock)."""

    def __init__(self, history_s: float, max_samples: int, max_extrapolation_s: float = 0.0):
        self.history_s = history_s
        self.max_extrapolation_s = max_extrapolation_s
        # Bounded by count as well as by time: a flood of samples within history_s cannot grow memory without end.
        self.times: Deque[float] = deque(maxlen=max_samples)
        self.values: Deque[np.ndarray] = deque(maxlen=max_samples)
        self.rates: Deque[Optional[np.ndarray]] = deque(maxlen=max_samples)   # per unit time; None: not known
        self.last_arrival_s = -math.inf

    def rate_agrees(self, t_s: float, value: np.ndarray, rate: np.ndarray, max_gap_s: float, tolerance: float,
                    tolerance_share: float, angles: bool) -> Optional[bool]:
        """Whether ``rate`` (per second) agrees with how the value changed since the newest sample: the mean of both
        samples' rates (``rate`` alone when the newest has none) against the difference quotient, within
        ``tolerance`` + ``tolerance_share`` × the larger of the two. None when it cannot be told (no sample before,
        ``t_s`` not after the newest, or the newest more than ``max_gap_s`` before). ``angles``: the values are
        angles (differences wrap)."""
        if not self.times or not 0 < t_s - self.times[-1] <= max_gap_s:
            return None
        delta = value - self.values[-1]
        seen = (wrap_angles(delta) if angles else delta) / (t_s - self.times[-1])
        last = self.rates[-1]
        said = rate if last is None else 0.5 * (rate + last)
        allowed = tolerance + tolerance_share * np.maximum(np.abs(seen), np.abs(said))
        return bool(np.all(np.abs(seen - said) <= allowed))

    def add(self, t_s: float, value: np.ndarray, arrival_s: float, rate: Optional[np.ndarray] = None) -> bool:
        """False (not kept) for a sample no later than the newest: out of order, duplicated, or a frozen clock
        (new values under an old time would be matched to frames as if measured then). ``rate``: the value's
        own rate of change at the sample (None when not known or not trusted)."""
        if self.times and t_s <= self.times[-1]:
            return False
        self.times.append(t_s)
        self.values.append(value)
        self.rates.append(rate)
        self.last_arrival_s = max(self.last_arrival_s, arrival_s)
        while self.times and self.times[0] < t_s - self.history_s:
            self.times.popleft()
            self.values.popleft()
            self.rates.popleft()
        return True

    def clear(self) -> None:
        self.times.clear()
        self.values.clear()
        self.rates.clear()

    def at(self, t_s: float, window_s: float, angles: bool = False) -> Optional[np.ndarray]:
        if not self.times:
            return None
        times = list(self.times)
        i = bisect.bisect_left(times, t_s)
        before = i - 1 if i > 0 else None
        after = i if i < len(times) else None
        if before is not None and after is not None and times[after] - times[before] <= 2 * window_s:
            t0, t1 = times[before], times[after]
            v0, v1 = self.values[before], self.values[after]
            w = 0.0 if t1 == t0 else (t_s - t0) / (t1 - t0)
            delta = v1 - v0
            if angles:  # interpolate the short way round
                delta = wrap_angles(delta)
            out: np.ndarray = v0 + w * delta
            return out
        best = min((j for j in (before, after) if j is not None), key=lambda j: abs(times[j] - t_s))
        dt = t_s - times[best]
        if abs(dt) > window_s:
            return None
        rate = self.rates[best]
        if rate is None or self.max_extrapolation_s <= 0:
            return self.values[best]
        reach = min(max(dt, -self.max_extrapolation_s), self.max_extrapolation_s)
        moved: np.ndarray = self.values[best] + rate * reach
        return moved
