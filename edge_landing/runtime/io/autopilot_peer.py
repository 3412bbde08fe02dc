"""Which sender on the link is the autopilot, and whether its vehicle is armed (ARCHITECTURE.md §12; used by
``mavlink_link.py``).

The first HEARTBEAT of a vehicle's autopilot (``telemetry_feed.is_autopilot_heartbeat``: a vehicle's type, not a
ground station, an antenna tracker or a peripheral), of ``LinkConfig.target_system`` when one is given, names the
one autopilot. When the frames are not this flight's live view (``LinkConfig.recorded_source``: a replay, a
recorded video, the sim camera) their targets name places in another flight, so they go out only while the vehicle
is known to be disarmed: the autopilot's own HEARTBEAT, newer than ``stale_s``, says disarmed, and no vehicle-type
HEARTBEAT from its system (another flight controller component) said armed within ``stale_s``. A LANDING_TARGET
names no system, so every autopilot on the link may act on it; being unsure counts as armed.
"""
from __future__ import annotations

import logging
from typing import Any, Callable, Dict, Optional, Tuple

from edge_landing.runtime.io.link_config import Autopilot, LinkConfig
from edge_landing.runtime.io.telemetry_feed import is_autopilot_heartbeat

__all__ = ["AutopilotPeer", "HEARTBEAT_AUTOPILOTS", "SAFETY_ARMED"]
log = logging.getLogger(__name__)
HEARTBEAT_AUTOPILOTS = {3: Autopilot.ARDUPILOT, 12: Autopilot.PX4}   # MAV_AUTOPILOT_ARDUPILOTMEGA, MAV_AUTOPILOT_PX4
SAFETY_ARMED = 128                                                   # MAV_MODE_FLAG_SAFETY_ARMED in base_mode
Sender = Tuple[int, int]
MAX_COMPONENTS = 256


class AutopilotPeer:
    """``send_status(text, severity)``: a STATUSTEXT to the autopilot (the link's). ``stale_s``: a HEARTBEAT says
    what the vehicle is for this long (autopilots send one a second)."""

    def __init__(self, config: LinkConfig, send_status: Callable[[str, int], bool], stale_s: float = 3.0):
        self.config, self.stale_s = config, stale_s
        self.sender: Optional[Sender] = None
        self._armed: Dict[int, Tuple[bool, float]] = {}   # component → (armed, arrival) of its newest HEARTBEAT
        self._held_said: Optional[bool] = None
        self._send_status = send_status

    def consider(self, msg: Any, sender: Sender) -> None:
        """A HEARTBEAT before the autopilot is known: the first autopilot-type one names it."""
        if self.sender is not None or not is_autopilot_heartbeat(msg):
            return
        if self.config.target_system is not None and sender[0] != self.config.target_system:
            return
        self.sender = sender
        log.info("autopilot found: system %d component %d; telemetry from any other sender is ignored", *sender)
        said = HEARTBEAT_AUTOPILOTS.get(int(msg.autopilot))
        ours = self.config.autopilot
        if said is not None and said is not ours:
            log.warning("the autopilot's HEARTBEAT says it is %s, but edge-run was started with --autopilot %s: "
                        "targets go out in the form %s reads (%s); check --autopilot", said.value, ours.value,
                        ours.value, "LOCAL_NED positions" if ours is Autopilot.PX4 else "BODY_FRD directions")

    def heartbeat(self, msg: Any, sender: Sender, now_s: float) -> None:
        """A HEARTBEAT from the autopilot's system (call it before the link counts the autopilot heard)."""
        if self.sender is None or sender[0] != self.sender[0]:
            return
        if sender != self.sender and not is_autopilot_heartbeat(msg):
            return   # a gimbal's, a camera's: not a vehicle that can be armed
        if sender[1] in self._armed or len(self._armed) < MAX_COMPONENTS:
            self._armed[sender[1]] = (bool(int(msg.base_mode) & SAFETY_ARMED), now_s)
        self._say(now_s)

    def armed(self, now_s: float) -> Optional[bool]:
        """True when a recent vehicle HEARTBEAT of the autopilot's system says armed, False when the autopilot's
        own recent one says disarmed and none says armed, None when that cannot be told (none recent)."""
        recent = [armed for armed, t in self._armed.values() if now_s - t <= self.stale_s]
        if any(recent):
            return True
        own = self._armed.get(self.sender[1]) if self.sender is not None else None
        return False if own is not None and now_s - own[1] <= self.stale_s else None

    def holds_recorded(self, now_s: float) -> str:
        """Why a target from a recorded source is held now ('' when it may go: not recorded, or disarmed)."""
        source = self.config.recorded_source
        if not source:
            return ""
        armed = self.armed(now_s)
        if armed is False:
            return ""
        why = "is armed" if armed else f"has not said in the last {self.stale_s:g} s that it is disarmed"
        return f"held: the autopilot {why} and this target comes from the {source}, not this flight"

    def _say(self, now_s: float) -> None:
        """Say when the vehicle's state starts or stops holding a recorded source's targets."""
        if not self.config.recorded_source:
            return
        held = self.armed(now_s) is not False
        if held == self._held_said:
            return
        self._held_said = held
        if held:
            log.warning("the autopilot is armed: targets from the %s (not this flight) are held until it disarms",
                        self.config.recorded_source)
            self._send_status("edge: armed; replay targets held", 4)
        else:
            log.info("the autopilot is disarmed: targets from the %s are sent", self.config.recorded_source)
