"""ArduPilot's answers to PARAM_REQUEST_READ, for the autopilot TEST DOUBLES of the tests and benchmarks.

A real autopilot cannot be installed here; the doubles that stand in for ArduPilot answer as its GCS_Param.cpp
does: PARAM_VALUE for a name it has, the value cast to a float whatever its type, ``param_index`` -1 (a uint16
on the wire: 65535); nothing for a name it lacks. Their parameters are a precision-landing setup that is right
for a MAVLink companion (README, "ArduPilot setup"), unless a test says otherwise.
"""
from __future__ import annotations

from typing import Any, Dict, Mapping

__all__ = ["PRECLAND_PARAMS", "PARAM_TYPES", "answer_param_request", "send_param"]

PRECLAND_PARAMS: Dict[str, float] = {"PLND_ENABLED": 1.0, "PLND_TYPE": 1.0, "PLND_ORIENT": 25.0,
                                     "PLND_YAW_ALIGN": 0.0, "PLND_LAG": 0.02}
PARAM_TYPES = {"PLND_ENABLED": 2, "PLND_TYPE": 2, "PLND_ORIENT": 2, "PLND_YAW_ALIGN": 4, "PLND_LAG": 9}  # MAV_PARAM_TYPE


def send_param(mav: Any, name: str, params: Mapping[str, float]) -> None:
    """One PARAM_VALUE, as ArduPilot sends it (an answer, or its broadcast after a parameter was set)."""
    mav.param_value_send(name.encode("ascii"), float(params[name]), PARAM_TYPES.get(name, 9), len(params), 65535)


def answer_param_request(mav: Any, msg: Any, params: Mapping[str, float] = PRECLAND_PARAMS) -> bool:
    """Answer ``msg`` when it is a PARAM_REQUEST_READ by name; True when it was one (answered or not)."""
    if msg.get_type() != "PARAM_REQUEST_READ":
        return False
    name = str(msg.param_id).rstrip("\x00")
    if name in params:
        send_param(mav, name, params)
    return True
