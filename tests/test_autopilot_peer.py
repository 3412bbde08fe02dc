"""Whether the vehicle is armed, as the link judges it for targets from a recorded source (io/autopilot_peer.py)."""
from __future__ import annotations

from edge_landing.runtime.io.autopilot_peer import SAFETY_ARMED, AutopilotPeer
from edge_landing.runtime.io.link_config import LinkConfig
from edge_landing.runtime.io.mavlink_conn import load_mavutil


def beat(mav_type: int = 2, armed: bool = False, autopilot: int = 3):
    m = load_mavutil().mavlink
    return m.MAVLink_heartbeat_message(mav_type, autopilot, SAFETY_ARMED if armed else 0, 0, 4, 3)


def peer_for(source: str = "--tlog replay") -> AutopilotPeer:
    said: list = []
    peer = AutopilotPeer(LinkConfig("udpout:127.0.0.1:1", recorded_source=source), lambda t, s: said.append(t) or True)
    peer.said = said   # type: ignore[attr-defined]
    return peer


def test_only_a_recent_disarmed_heartbeat_lets_a_recorded_sources_targets_go():
    peer = peer_for()
    peer.consider(beat(), (1, 1))
    assert peer.holds_recorded(0.0).startswith("held: the autopilot has not said in the last 3 s")   # not known yet
    peer.heartbeat(beat(), (1, 1), 10.0)
    assert peer.holds_recorded(10.5) == ""
    # Its HEARTBEATs stop (other messages may still come): after 3 s being unsure counts as armed.
    assert peer.holds_recorded(13.5).startswith("held: the autopilot has not said in the last 3 s")
    peer.heartbeat(beat(armed=True), (1, 1), 14.0)
    assert "is armed" in peer.holds_recorded(14.1) and "--tlog replay" in peer.holds_recorded(14.1)
    assert peer.said == ["edge: armed; replay targets held"]   # type: ignore[attr-defined]


def test_another_flight_controller_of_the_system_that_is_armed_holds_too():
    """LANDING_TARGET names no system: every autopilot on the link may act on it."""
    peer = peer_for()
    peer.consider(beat(), (1, 1))
    peer.heartbeat(beat(), (1, 1), 10.0)
    peer.heartbeat(beat(mav_type=26, armed=True), (1, 154), 10.1)   # a gimbal's HEARTBEAT is not a vehicle's
    assert peer.holds_recorded(10.2) == ""
    peer.heartbeat(beat(armed=True), (1, 2), 10.3)                  # a second flight controller, armed
    assert "is armed" in peer.holds_recorded(10.4)
    peer.heartbeat(beat(armed=True), (2, 1), 10.5)                  # another system's: not ours to judge
    assert peer.armed(14.0) is None


def test_a_live_camera_is_never_held_and_peripherals_are_not_autopilots():
    peer = peer_for("")
    peer.consider(beat(mav_type=5), (2, 1))            # ArduPilot's AntennaTracker: says ArduPilot, is no vehicle
    peer.consider(beat(mav_type=49), (3, 1))           # a type newer than the list: not taken either
    assert peer.sender is None
    peer.consider(beat(armed=True), (1, 1))
    peer.heartbeat(beat(armed=True), (1, 1), 1.0)
    assert peer.sender == (1, 1) and peer.holds_recorded(1.0) == ""
