"""The MAVLink link's settings, its choice of autopilot dialect and its thread-safe counters (``mavlink_link.py``)."""
from __future__ import annotations

import threading
from collections import Counter
from dataclasses import dataclass
from typing import Dict, Optional

from edge_landing.runtime.core.choices import ChoiceEnum
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.io.autopilot_setup import SetupCheck
from edge_landing.runtime.io.send_rate import check_cap_hz

__all__ = ["Autopilot", "LinkConfig", "LinkCounts"]


class Autopilot(ChoiceEnum):
    ARDUPILOT = "ardupilot"
    PX4 = "px4"

    @classmethod
    def _label(cls) -> str:
        return "autopilot"


@dataclass(frozen=True)
class LinkConfig:
    url: str
    autopilot: Autopilot = Autopilot.ARDUPILOT
    system_id: int = 1             # companion computers share the vehicle's system id
    component_id: int = 191        # MAV_COMP_ID_ONBOARD_COMPUTER
    key_path: Optional[str] = None
    target_system: Optional[int] = None  # take telemetry only from this system id (else: first autopilot heard)
    heartbeat_period_s: float = 1.0
    telemetry_rate_hz: float = 20.0
    error_quiet_s: float = 2.0     # the link counts as up again after this long without a send error
    heard_within_s: float = 1.5    # the autopilot counts as heard while a message came within this
    max_target_age_s: float = 1.0  # an older target is dropped, never queued
    max_unsent_bytes: int = 512    # TCP or serial: a longer send queue means the peer is not reading (or too slowly)
    max_target_hz: float = 20.0    # LANDING_TARGET at most this often on average (0: every target; io.send_rate)
    connect_timeout_s: float = 2.0
    reconnect_min_s: float = 0.5
    reconnect_max_s: float = 5.0
    tlog_out: str = ""             # write every packet received here as a .tlog (edge-run --flight-record)
    setup_check: SetupCheck = SetupCheck.HOLD   # ArduPilot's PLND_* parameters: read, and hold misplaced targets
    # What the frames are when they are not this flight's live view ("--tlog replay", "recorded video", "sim
    # camera", ...; '' for a camera): their targets name places in another flight, so they go out only while the
    # vehicle is known to be disarmed (autopilot_peer.py).
    recorded_source: str = ""

    def __post_init__(self) -> None:
        # MAVLink packs ids in one byte: a larger one would kill the link thread at its first heartbeat.
        for name, value in (("system id", self.system_id), ("component id", self.component_id),
                            ("target system", self.target_system)):
            if value is not None and not 1 <= value <= 255:
                raise InputError(f"MAVLink {name} must be between 1 and 255, got {value}")
        check_cap_hz(self.max_target_hz, "LANDING_TARGET rate cap")


class LinkCounts:
    """Thread-safe counters (the pipeline thread sends, the link thread receives)."""

    KEYS = ("targets", "heartbeats", "statustext", "received", "send_errors", "reconnects",
            "skipped_px4_no_position", "dropped_old_targets", "dropped_backed_up", "dropped_not_heard",
            "other_senders", "before_autopilot", "bad_signature", "timesync_requests", "timesync_answers", "noise_bytes",
            "gimbal_reports", "held_setup", "rate_capped", "held_recorded_armed")

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._c: Counter[str] = Counter({k: 0 for k in self.KEYS})

    def add(self, key: str, n: int = 1) -> None:
        with self._lock:
            self._c[key] += n

    def __getitem__(self, key: str) -> int:
        with self._lock:
            return self._c[key]

    def snapshot(self) -> Dict[str, int]:
        with self._lock:
            return dict(self._c)
