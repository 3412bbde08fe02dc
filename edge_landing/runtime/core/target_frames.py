"""A landing target expressed in the frames the autopilots want (ARCHITECTURE.md §3, §8).

Body = FRD at the capture time; world = local NED. Pure numpy, shared by fusion's callers, the pipeline's
continuity and the MAVLink link (so the pipeline never reaches into the link for geometry).
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from edge_landing.runtime.core.messages import Target, VehicleState


def target_ned(target: Target, state: Optional[VehicleState]) -> Optional[np.ndarray]:
    """Absolute local NED of the target: vehicle position at capture + body vector rotated by the attitude."""
    if target.position_ned_m is not None:
        return np.asarray(target.position_ned_m, dtype=np.float64)
    if state is None or state.position_ned_m is None or target.position_body_frd_m is None:
        return None
    out: np.ndarray = np.asarray(state.position_ned_m, dtype=np.float64) + \
        state.attitude.ned_from_body() @ np.asarray(target.position_body_frd_m, dtype=np.float64)
    return out


def body_from_ned(point_ned_m: np.ndarray, state: VehicleState) -> Optional[np.ndarray]:
    """A local NED point in the body FRD frame of ``state`` (needs the vehicle position), or None."""
    if state.position_ned_m is None:
        return None
    rel = np.asarray(point_ned_m, dtype=np.float64) - np.asarray(state.position_ned_m, dtype=np.float64)
    out: np.ndarray = state.attitude.ned_from_body().T @ rel
    return out
