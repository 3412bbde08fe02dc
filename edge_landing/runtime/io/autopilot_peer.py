"""Which sender on the link is the autopilot, and what its HEARTBEAT says (ARCHITECTURE.md §12; used by
``mavlink_link.py``).

The first HEARTBEAT of a vehicle's autopilot (``telemetry_feed.is_autopilot_heartbeat``: not a ground station, an
antenna tracker or a peripheral), of ``LinkConfig.target_system`` when one is given, names the one autopilot. Its
later HEARTBEATs say whether it is armed: targets made from telemetry that is not its own (a replay, the sim
camera: ``LinkConfig.replayed_telemetry``) are held while it is.
"""
from __future__ import annotations

import logging
from typing import Any, Callable, Optional, Tuple

from edge_landing.runtime.io.link_config import Autopilot, LinkConfig
from edge_landing.runtime.io.telemetry_feed import is_autopilot_heartbeat

__all__ = ["AutopilotPeer", "HEARTBEAT_AUTOPILOTS", "SAFETY_ARMED"]
log = logging.getLogger(__name__)
HEARTBEAT_AUTOPILOTS = {3: Autopilot.ARDUPILOT, 12: Autopilot.PX4}   # MAV_AUTOPILOT_ARDUPILOTMEGA, MAV_AUTOPILOT_PX4
SAFETY_ARMED = 128                                                   # MAV_MODE_FLAG_SAFETY_ARMED in base_mode
Sender = Tuple[int, int]


class AutopilotPeer:
    """``send_status(text, severity)``: a STATUSTEXT to the autopilot (the link's)."""

    def __init__(self, config: LinkConfig, send_status: Callable[[str, int], bool]):
        self.config = config
        self.sender: Optional[Sender] = None
        self.armed = False
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

    def heartbeat(self, msg: Any) -> None:
        """The autopilot's own HEARTBEAT: said when being (dis)armed holds or frees replayed targets."""
        armed = bool(int(msg.base_mode) & SAFETY_ARMED)
        replayed = self.config.replayed_telemetry
        if armed != self.armed and replayed:
            if armed:
                log.warning("the autopilot is armed: targets made from the %s's telemetry (another flight's poses) "
                            "are held until it disarms", replayed)
                self._send_status("edge: armed; replayed poses, targets held", 4)
            else:
                log.info("the autopilot is disarmed: targets made from the %s's telemetry are sent again", replayed)
        self.armed = armed

    def holds_replayed(self) -> str:
        """Why a target is held because it was made from replayed telemetry and the autopilot is armed ('' if not)."""
        if not (self.config.replayed_telemetry and self.armed):
            return ""
        return (f"held: the autopilot is armed and this target was made from the "
                f"{self.config.replayed_telemetry}'s telemetry, not its own")
