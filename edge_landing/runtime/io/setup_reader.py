"""The link's side of the autopilot's setup check (``autopilot_setup.py``): requests, answers, reboots, what is said.

Runs in the link's thread only. PARAM_REQUEST_READ goes to the autopilot by name; ArduPilot answers with
PARAM_VALUE, its value cast to a float whatever the parameter's type (GCS_Param.cpp), and broadcasts one when
a parameter is set. The setup is said in the log once it is read, again whenever it changes, and, when it
holds targets, once in a STATUSTEXT to the ground station.
"""
from __future__ import annotations

import logging
import time
from typing import Any, Callable, Optional, Tuple

from edge_landing.runtime.io.autopilot_setup import AutopilotSetup

__all__ = ["SetupReader"]
log = logging.getLogger(__name__)


class SetupReader:
    """Asks for the setup's parameters, takes the answers, starts over when the autopilot reboots."""

    def __init__(self, setup: AutopilotSetup, send: Callable[[Any], bool], status: Callable[[str, int], bool],
                 mavlink: Any):
        self.setup, self._send, self._status, self._m = setup, send, status, mavlink
        self._reboots: Optional[int] = None
        self._said = ""
        self._gave_up_said = False
        self._held_said = ""

    def tick(self, now_s: float, peer: Tuple[int, int], reboots: int) -> None:
        """Called from the link's loop once the autopilot is known: request what is due, notice a reboot."""
        if self._reboots is None:
            self._reboots = reboots
        elif reboots != self._reboots:
            self._reboots = reboots
            self.setup.restarted()
            self._said, self._gave_up_said, self._held_said = "", False, ""
            log.info("the autopilot rebooted: reading its precision-landing parameters again")
        for name in self.setup.due(now_s):
            self._send(self._m.MAVLink_param_request_read_message(peer[0], peer[1], name.encode("ascii"), -1))
        missing = self.setup.given_up()
        if missing and not self._gave_up_said:
            self._gave_up_said = True
            log.warning("the autopilot did not answer for %s: that part of its precision-landing setup is not "
                        "checked (firmware without precision landing, or a router that drops parameter requests)",
                        ", ".join(missing))
            self._say()

    def on_param_value(self, msg: Any) -> None:
        """A PARAM_VALUE from the autopilot."""
        name = str(msg.param_id).rstrip("\x00")
        if self.setup.on_value(name, float(msg.param_value)) and (self.setup.read_all() or self.setup.given_up()):
            self._say()

    def _say(self) -> None:
        line = self.setup.describe()
        if line != self._said:
            self._said = line
            (log.warning if self.setup.problems() else log.info)("%s", line)
        held = self.setup.hold_reason(time.monotonic())
        # Said for a setting that misplaces targets (not while the parameters are still being read): a missing one
        # must not end the link's thread.
        shorts = [p.short for p in self.setup.problems() if p.rule.misplaces]
        if held and held != self._held_said and shorts:
            self._status(f"{shorts[0]}: edge targets held", 4)   # one STATUSTEXT message (50 characters)
        self._held_said = held
