"""Time-sorted samples of one telemetry quantity, bounded in time and in count (``telemetry.py`` keeps four)."""
from __future__ import annotations

import bisect
import math
from collections import deque
from typing import Deque, Optional

import numpy as np

__all__ = ["TimeSeries"]


class TimeSeries:
    """Time-sorted samples of one quantity (times on the local monotonic clock)."""

    def __init__(self, history_s: float, max_samples: int):
        self.history_s = history_s
        # Bounded by count as well as by time: a flood of samples within history_s cannot grow memory without end.
        self.times: Deque[float] = deque(maxlen=max_samples)
        self.values: Deque[np.ndarray] = deque(maxlen=max_samples)
        self.last_arrival_s = -math.inf

    def add(self, t_s: float, value: np.ndarray, arrival_s: float) -> bool:
        """False (not kept) for a sample no later than the newest: out of order, duplicated, or a frozen clock
        (new values under an old time would be matched to frames as if measured then)."""
        if self.times and t_s <= self.times[-1]:
            return False
        self.times.append(t_s)
        self.values.append(value)
        self.last_arrival_s = max(self.last_arrival_s, arrival_s)
        while self.times and self.times[0] < t_s - self.history_s:
            self.times.popleft()
            self.values.popleft()
        return True

    def clear(self) -> None:
        self.times.clear()
        self.values.clear()

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
            if angles:  # interpolate the short way round (yaw wraps at ±pi)
                delta = (delta + math.pi) % (2 * math.pi) - math.pi
            out: np.ndarray = v0 + w * delta
            return out
        best = min((j for j in (before, after) if j is not None), key=lambda j: abs(times[j] - t_s))
        return self.values[best] if abs(times[best] - t_s) <= window_s else None
