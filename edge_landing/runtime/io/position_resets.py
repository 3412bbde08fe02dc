"""Moves of the autopilot's frame told from flight (``telemetry.py``): a reboot, a position or heading that changed
faster than the vehicle can fly or yaw, and a small move told by the samples' own velocity.

:class:`FrameMoves` judges each new sample against the newest kept one; the buffer empties what it names.

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
buffer is told to forget (a new VelocityCheck). Pure numpy; what it finds is logged.
"""
from __future__ import annotations

import logging
import math
from collections import deque
from enum import Enum
from typing import Deque, Optional, Tuple

import numpy as np

from edge_landing.runtime.io.telemetry_config import TelemetryConfig

__all__ = ["FrameMoves", "Quantity", "Emptied", "VelocityCheck"]
log = logging.getLogger(__name__)


class Quantity(Enum):
    """The telemetry series a sample belongs to, as far as frame moves are concerned."""

    POSITION = "position"
    ATTITUDE = "attitude"
    OTHER = "other"          # heights: only a reboot moves them


class Emptied(Enum):
    """What a frame move empties."""

    NOTHING = "nothing"
    THIS_SERIES = "this series"
    ALL_SERIES = "every series"


_STARTS_OVER = "earlier samples, NED evidence and the committed spot are dropped"


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


class FrameMoves:
    """Whether a sample shows that the autopilot's frame moved since the newest sample of its kind."""

    def __init__(self, config: TelemetryConfig):
        self.config = config
        self.velocity = VelocityCheck(config)
        self._reboots = 0

    def forget(self) -> None:
        """A new autopilot, or the same one told to start over: its velocities are judged afresh."""
        self.velocity = VelocityCheck(self.config)

    def check(self, reboots: int, kind: Quantity, last: Optional[Tuple[float, np.ndarray]], t_s: float,
              value: np.ndarray, velocity: Optional[np.ndarray] = None, remote_s: Optional[float] = None
              ) -> Tuple[Emptied, str]:
        """(what to empty, the counted reason, "" when nothing moved). ``reboots``: the clock's count of restarts so
        far; ``last``: (local time, value) of the series' newest sample, None without one; ``velocity``,
        ``remote_s``: as VelocityCheck.off_m."""
        c = self.config
        if reboots != self._reboots:
            # A rebooted autopilot sets its local origin again: positions from before may name other places. Its
            # estimator started over too, and samples from before were timed with the old clock's offset: none is
            # interpolated with, or matched in place of, the new autopilot's.
            self._reboots = reboots
            self.forget()
            log.warning("the autopilot's clock restarted (a reboot): " + _STARTS_OVER)
            return Emptied.ALL_SERIES, "autopilot rebooted (its clock restarted): every earlier sample dropped"
        if kind is Quantity.OTHER or last is None or t_s <= last[0]:
            return Emptied.NOTHING, ""
        dt = t_s - last[0]
        if kind is Quantity.POSITION:
            moved = float(np.linalg.norm(value - last[1]))
            off = self.velocity.off_m(last[0], last[1], t_s, value, velocity, remote_s)
            flown = moved <= max(c.min_jump_m, c.max_speed_mps * dt)
            if flown and off is None:
                return Emptied.NOTHING, ""
            if flown:
                self.velocity.reset_seen(t_s)
                log.warning("local position moved %.1f m from where its velocity carried it in %.2f s (an EKF "
                            "reset): " + _STARTS_OVER, off, dt)
            else:
                log.warning("local position jumped %.1f m in %.2f s (EKF reset or glitch): " + _STARTS_OVER, moved, dt)
            return Emptied.THIS_SERIES, "position jumped (the autopilot's frame moved): earlier positions dropped"
        turned = abs(math.remainder(float(value[2] - last[1][2]), 2.0 * math.pi))
        if turned <= max(c.min_yaw_jump_rad, c.max_yaw_rate_rad_s * dt):
            return Emptied.NOTHING, ""
        log.warning("heading jumped %.0f° in %.2f s (an EKF yaw reset): " + _STARTS_OVER, math.degrees(turned), dt)
        return Emptied.THIS_SERIES, "heading jumped (a yaw reset): earlier attitudes dropped"
