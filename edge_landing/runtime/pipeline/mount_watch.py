"""What the mount check found, said to the people flying (fusion.mount_check, ARCHITECTURE.md §11).

The check measures from the images how the camera is turned against what the mount (``--mount-pitch``,
``--mount-roll``, ``--mount-yaw``) and the autopilot's attitude say. A camera turned by a degree or two places
targets metres off and leaves motion geometry unable to confirm; the log's "unconfirmed" reasons would then point
at the baseline. So: one log line when the first estimate is there, a warning (and one STATUSTEXT) when the camera
is turned more than the check's ``warn_deg``, again when that changes by more than ``RESAY_DEG``, and a line in the
run's summary. Nothing is held: the check is evidence for a person to act on, not a trust rule.
"""
from __future__ import annotations

import logging
import math
from typing import Callable, Optional

from edge_landing.runtime.fusion.mount_check import MountEstimate

__all__ = ["MountWatch"]
log = logging.getLogger(__name__)
RESAY_DEG = 0.5
SUGGEST_SIGMA_DEG = 0.5     # an angle is suggested as measured only when known this well


class MountWatch:
    """Follows the fused frames' mount estimates; says them when they first come and when they matter."""

    def __init__(self, status: Optional[Callable[[str, int], bool]] = None):
        self._status = status
        self.last: Optional[MountEstimate] = None
        self._said: Optional[MountEstimate] = None
        self._status_sent = False

    def update(self, est: Optional[MountEstimate]) -> None:
        if est is None or est is self.last:
            return
        self.last = est
        said = self._said
        if said is not None and said.attention == est.attention \
                and abs(est.turn_deg - said.turn_deg) <= RESAY_DEG:
            return
        self._said = est
        if not est.attention:
            log.info("%s", est.describe())
            return
        # Only what was measured is suggested: an angle still uncertain (roll about the direction of flight, on
        # one heading) keeps the value given.
        flags = " ".join(f"--mount-{name} {measured if sigma <= SUGGEST_SIGMA_DEG else given:.1f}"
                         for name, given, measured, sigma in est.axes())
        log.warning("%s: targets are placed off by about %.0f %% of their range and motion geometry may confirm "
                    "nothing; if the camera is fixed to the frame, run with %s (angles measured to within %.1f°; "
                    "or fix the mount, or the autopilot's level calibration)",
                    est.describe(), 100.0 * math.radians(est.turn_deg), flags, SUGGEST_SIGMA_DEG)
        if self._status is not None and not self._status_sent:
            self._status_sent = True
            self._status(f"{est.turn_deg:.1f}deg camera turn: check edge mount", 4)   # one STATUSTEXT message (50 characters)

    def line(self) -> str:
        """For the run's summary ("" when the check never had enough frame pairs)."""
        if self.last is None:
            return ""
        verdict = "check the mount (see the log)" if self.last.attention else "agrees with the mount"
        return f"{self.last.describe()}: {verdict}"
