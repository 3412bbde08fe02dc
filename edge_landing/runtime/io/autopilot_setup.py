"""The autopilot's precision-landing setup, read over MAVLink, and what edge-run does about it (ARCHITECTURE.md §12).

ArduPilot uses a LANDING_TARGET only as its PLND_* parameters say (libraries/AC_PrecLand):
- ``PLND_ENABLED`` other than 1, or ``PLND_TYPE`` other than 1 (MAVLink): every target is ignored. Harmless,
  but nothing edge-run finds is used, so it is said.
- ``PLND_ORIENT`` other than 25 (down), or ``PLND_YAW_ALIGN`` other than 0: ArduPilot turns each body-frame
  direction once more (for a camera looking forward or back, or yawed on the frame), so the copter would fly
  to another place than the one edge-run confirmed. edge-run's directions already hold the camera's mounting.
  Such a target is *held* (``SetupCheck.HOLD``, the default): not sent, with the reason in the log. So are
  targets before the parameters are read (milliseconds after the autopilot is found), for at most
  ``read_wait_s`` (an autopilot that never answers is then asked on, and said, but not waited for).
- ``PLND_LAG`` is only read: the run's summary compares it with the latency measured.

``PLND_TYPE``, ``PLND_ORIENT`` and ``PLND_LAG`` take effect at the autopilot's next boot (PLND_ORIENT's
direction check is made at boot too). A value that changes after it was first read (ArduPilot broadcasts
PARAM_VALUE when a parameter is set) is therefore not yet the one the autopilot runs with: for PLND_ORIENT the
targets are held until it reboots. A value changed before edge-run first read it cannot be told from the one
it booted with.

Pure state, thread-safe, no I/O: the link (``mavlink_link.py``) sends PARAM_REQUEST_READ for the names ``due``
returns and hands each PARAM_VALUE to ``on_value``. ArduPilot answers a name it does not have with nothing
(GCS_Param.cpp), so names still unanswered after ``attempts`` requests are reported, and hold nothing. PX4's
parameters are not read.
"""
from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from typing import Dict, List, Optional, Tuple

from edge_landing.runtime.core.choices import ChoiceEnum

__all__ = ["ARDUPILOT_RULES", "AutopilotSetup", "ParamRule", "Problem", "SetupCheck", "SetupConfig"]


class SetupCheck(ChoiceEnum):
    HOLD = "hold"    # read the parameters; hold targets the autopilot would misplace (default)
    WARN = "warn"    # read them and say what is wrong, send anyway
    OFF = "off"      # do not read them

    @classmethod
    def _label(cls) -> str:
        return "--autopilot-check"


@dataclass(frozen=True)
class ParamRule:
    """One parameter: the value edge-run needs (None: only read), and what another value does."""

    name: str
    needed: Optional[float]
    misplaces: bool       # another value moves the target (held); else the autopilot only ignores targets
    on_reboot: bool       # ArduPilot applies a change at its next boot
    effect: str           # what another value does, said in the one line


ARDUPILOT_RULES: Tuple[ParamRule, ...] = (
    ParamRule("PLND_ENABLED", 1, False, False, "ArduPilot ignores every LANDING_TARGET"),
    ParamRule("PLND_TYPE", 1, False, True, "ArduPilot takes its landing target from another sensor, not from "
              "LANDING_TARGET (1 = MAVLink)"),
    ParamRule("PLND_ORIENT", 25, True, True, "ArduPilot would turn each target's direction again, as if the camera "
              "did not look down, and fly to another place"),
    ParamRule("PLND_YAW_ALIGN", 0, True, False, "ArduPilot would turn each target's direction about the vertical, "
              "and fly to another place (edge-run's directions already hold the camera's mounting)"),
    ParamRule("PLND_LAG", None, False, True, ""),
)


@dataclass(frozen=True)
class Problem:
    """A setting that keeps targets from being used as sent: the log's line and a STATUSTEXT-sized one."""

    rule: ParamRule
    line: str
    short: str


@dataclass(frozen=True)
class SetupConfig:
    check: SetupCheck = SetupCheck.HOLD
    retry_s: float = 1.0     # an unanswered name is asked again after this long ...
    attempts: int = 5        # ... at most this many times (ArduPilot queues 20 requests and drops the rest)
    # Targets wait for the answers this long after the first request (ArduPilot answers in milliseconds); an
    # autopilot or router that never answers is not made to cost more than that.
    read_wait_s: float = 1.0


class AutopilotSetup:
    """What was read of the autopilot's PLND_* parameters since it booted, and whether targets are held."""

    def __init__(self, config: SetupConfig = SetupConfig(), rules: Tuple[ParamRule, ...] = ARDUPILOT_RULES):
        self.config, self.rules = config, rules
        self._lock = threading.Lock()
        self._asked: Dict[str, Tuple[int, float]] = {}       # name -> (requests sent, when last)
        self._boot: Dict[str, float] = {}                    # the first value read since the autopilot booted
        self._now: Dict[str, float] = {}                     # the newest value read
        self._given_up: List[str] = []                       # names never answered after every attempt
        self._first_ask_s: Optional[float] = None            # the first request since the autopilot booted

    # -- reading (link thread) ----------------------------------------------------------------------------
    def due(self, now_s: float) -> List[str]:
        """The names to request now: never answered since boot, not asked within ``retry_s``, attempts left."""
        out = []
        with self._lock:
            if self._first_ask_s is None:
                self._first_ask_s = now_s
            for rule in self.rules:
                sent, last = self._asked.get(rule.name, (0, -math.inf))
                if rule.name in self._boot or rule.name in self._given_up or now_s - last < self.config.retry_s:
                    continue
                if sent >= self.config.attempts:      # the last request had its retry_s to be answered
                    self._given_up.append(rule.name)
                    continue
                self._asked[rule.name] = (sent + 1, now_s)
                out.append(rule.name)
        return out

    def on_value(self, name: str, value: float) -> bool:
        """A PARAM_VALUE from the autopilot (an answer, or a broadcast after a parameter was set). True when it
        is one of ours and changed what is known (the link then says where the setup stands)."""
        rule = self._rule(name)
        if rule is None or not math.isfinite(value):
            return False
        with self._lock:
            if self._now.get(name) == value:
                return False
            self._boot.setdefault(name, value)
            self._now[name] = value
        return True

    def restarted(self) -> None:
        """The autopilot rebooted: what it runs with now is read again."""
        with self._lock:
            self._asked.clear()
            self._given_up.clear()
            self._first_ask_s = None
            self._boot.clear()
            self._now.clear()

    # -- what follows (any thread) ----------------------------------------------------------------------------
    def read_all(self) -> bool:
        with self._lock:
            return all(r.name in self._boot for r in self.rules)

    def given_up(self) -> List[str]:
        """Names never answered after every attempt (the firmware lacks them, or the link drops requests)."""
        with self._lock:
            return [name for name in self._given_up if name not in self._boot]

    def value(self, name: str) -> Optional[float]:
        """The value the autopilot runs with: for one applied at boot, the one first read since then."""
        rule = self._rule(name)
        with self._lock:
            if rule is not None and rule.on_reboot:
                return self._boot.get(name)
            return self._now.get(name)

    def problems(self) -> List[Problem]:
        """Each setting that keeps edge-run's targets from being used as sent."""
        out = []
        with self._lock:
            for rule in self.rules:
                boot, now = self._boot.get(rule.name), self._now.get(rule.name)
                if boot is None or now is None:
                    continue
                if rule.on_reboot and now != boot:
                    out.append(Problem(rule, f"{rule.name} changed from {_num(boot)} to {_num(now)} since the "
                                             f"autopilot booted: ArduPilot applies it at the next boot; reboot the "
                                             f"autopilot", f"{rule.name} changed: reboot"))
                elif rule.needed is not None and now != rule.needed:
                    fix = " and reboot" if rule.on_reboot else ""
                    out.append(Problem(rule, f"{rule.name} is {_num(now)}: {rule.effect}; set {rule.name}="
                                             f"{_num(rule.needed)}{fix}",
                                       f"{rule.name} {_num(now)} not {_num(rule.needed)}"))
        return out

    def hold_reason(self, now_s: float) -> str:
        """Why targets are held at ``now_s`` (the clock ``due`` is given; "" when they may be sent)."""
        if self.config.check is not SetupCheck.HOLD:
            return ""
        with self._lock:
            pending = [r.name for r in self.rules if r.name not in self._boot and r.name not in self._given_up]
            waiting = self._first_ask_s is None or now_s - self._first_ask_s < self.config.read_wait_s
        if pending and waiting:
            return f"held: reading the autopilot's precision-landing setup ({', '.join(pending)})"
        for p in self.problems():
            if p.rule.misplaces:
                return f"held: the autopilot's {p.line}"
        return ""

    def describe(self) -> str:
        """One line: every value read, then what is wrong (or that the setup is right)."""
        with self._lock:
            values = " ".join(f"{r.name}={_num(self._now[r.name])}" for r in self.rules if r.name in self._now)
        problems, missing = self.problems(), self.given_up()
        unread = f" ({', '.join(missing)} not answered)" if missing else ""
        if not values:
            return f"autopilot setup: nothing read{unread}"
        if not problems:
            return f"autopilot setup: {values}{unread}: LANDING_TARGET is used as edge-run sends it"
        return f"autopilot setup: {values}{unread}: " + "; ".join(p.line for p in problems)

    def report(self) -> Dict[str, object]:
        """For the run's summary: the values read, the problems and the names never answered."""
        with self._lock:
            values = {r.name: self._now[r.name] for r in self.rules if r.name in self._now}
        return {"values": values, "problems": [p.line for p in self.problems()], "unanswered": self.given_up(),
                "check": self.config.check.value}

    def _rule(self, name: str) -> Optional[ParamRule]:
        return next((r for r in self.rules if r.name == name), None)


def _num(value: float) -> str:
    return f"{value:g}"
