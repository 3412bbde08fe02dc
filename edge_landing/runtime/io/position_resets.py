"""A small move of the autopilot's local frame told from flight by the samples' own velocity (``telemetry.py``).

An estimator's position and velocity are one state: between two LOCAL_POSITION_NED samples the position moves as
the velocities say, to centimetres. An EKF lane switch or a GPS glitch's recovery moves the position alone, by a
metre or a few in one step, well inside what the vehicle's top speed allows. A position farther than
max(``min_reset_m``, ``max_accel_mps2`` × dt² / 2 + ``velocity_error_mps`` × dt) from where the two samples' mean
velocity carried the last one is such a reset (TelemetryConfig). dt is the difference of the autopilot's own time
stamps where both samples have one: the local times they are mapped to move with the clock offset's steps (up to a
few tenths of a second when a faster sample comes), which at 10 m/s is a metre.

A source whose velocities do not describe its positions (zeros from a partial MAVLink implementation) would show
a "reset" on every step and start fusion over for good: after ``distrust_after`` of them within ``distrust_s``
the velocities are no longer used (said once), and only the speed rule is left, until the autopilot reboots or the
buffer is told to forget (a new VelocityCheck). Pure numpy.
"""
from __future__ import annotations

import logging
from collections import deque
from typing import Deque, Optional, Tuple

import numpy as np

from edge_landing.runtime.io.telemetry_config import TelemetryConfig

__all__ = ["VelocityCheck"]
log = logging.getLogger(__name__)


class VelocityCheck:
    def __init__(self, config: TelemetryConfig):
        self.config = config
        self.trusted = True
        # (local time, NED m/s, the autopilot's time or None) of the newest position sample
        self._last: Optional[Tuple[float, np.ndarray, Optional[float]]] = None
        self._resets: Deque[float] = deque(maxlen=max(1, config.distrust_after))

    def off_m(self, last_t_s: float, last_ned_m: np.ndarray, t_s: float, ned_m: np.ndarray,
              velocity: Optional[np.ndarray], remote_s: Optional[float] = None) -> Optional[float]:
        """How far (m) ``ned_m`` lies from where the velocities carried the last sample (at local ``last_t_s``),
        when that is more than flying allows; None when it is not, or cannot be told. ``remote_s``: the sample's
        time on the autopilot's clock, when it has one."""
        c, last = self.config, self._last
        if not self.trusted or velocity is None or last is None or last[0] != last_t_s:
            return None
        dt = remote_s - last[2] if remote_s is not None and last[2] is not None else t_s - last_t_s
        if not 0 < dt <= c.velocity_check_s:
            return None
        off = float(np.linalg.norm(ned_m - (last_ned_m + 0.5 * (last[1] + velocity) * dt)))
        allowed = max(c.min_reset_m, 0.5 * c.max_accel_mps2 * dt * dt + c.velocity_error_mps * dt)
        return off if off > allowed else None

    def kept(self, t_s: float, velocity: Optional[np.ndarray], remote_s: Optional[float] = None) -> None:
        """A position sample at local ``t_s`` (``remote_s`` on the autopilot's clock) was kept, with its velocity
        (None: it had none)."""
        self._last = None if velocity is None else (t_s, velocity, remote_s)

    def reset_seen(self, t_s: float) -> None:
        """``off_m`` found a reset at ``t_s``: too many too close together and the velocities are not believed."""
        self._resets.append(t_s)
        c = self.config
        if len(self._resets) == self._resets.maxlen and t_s - self._resets[0] <= c.distrust_s:
            self.trusted = False
            log.warning("the local position's velocity does not describe its positions (%d resets in %.0f s): "
                        "resets under %g m are no longer detected", len(self._resets), t_s - self._resets[0],
                        c.min_jump_m)
