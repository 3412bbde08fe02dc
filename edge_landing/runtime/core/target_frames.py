"""A landing target expressed in the frames the autopilots want (ARCHITECTURE.md §3, §8).

Body = FRD at the pose the target is expressed in (the capture's, or the newest telemetry's before sending);
world = local NED. Pure numpy, shared by fusion, the pipeline's continuity and re-expression, and the MAVLink
link (so the pipeline never reaches into the link for geometry). ``aim_from_offset`` is the one rule for the
pose-dependent fields (body vector, range, angles, sizes) on every path a target takes.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Optional

import numpy as np

from edge_landing.runtime.core.camera import Attitude, Mount
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


@dataclass(frozen=True)
class Aim:
    """A ground point as seen from one vehicle pose: the parts of LANDING_TARGET that depend on the pose.

    ``body_frd_m``: the point in the body FRD frame of that pose; ``range_m``: its norm; angles from the camera's
    optical axis (camera x right / y down; NaN without a mount); sizes: angular diameter of the clear disc,
    full across the line of sight and foreshortened along it (a disc on level ground seen from above at the
    line of sight's depression).
    """

    body_frd_m: np.ndarray
    range_m: float
    angle_x_rad: float
    angle_y_rad: float
    size_x_rad: float
    size_y_rad: float


def aim_from_offset(offset_ned_m: np.ndarray, attitude: Attitude, disc_radius_m: float,
                    mount: Optional[Mount] = None) -> Optional[Aim]:
    """The point ``offset_ned_m`` (local NED, relative to the vehicle) seen from ``attitude``; None when the
    offset is zero or not finite. One rule for every target that leaves: fused, held from memory, re-expressed
    at a newer pose (so the values sent do not depend on which path made the target)."""
    rel = np.asarray(offset_ned_m, dtype=np.float64).reshape(3)
    if not np.isfinite(rel).all():
        return None
    body = attitude.ned_from_body().T @ rel
    rng = float(np.linalg.norm(rel))
    if not np.isfinite(body).all() or rng <= 0:      # a non-finite attitude
        return None
    radius = max(float(disc_radius_m), 0.0) if math.isfinite(disc_radius_m) else 0.0
    sin_dep = abs(float(rel[2])) / rng
    size_x = 2.0 * math.atan2(radius, rng)
    size_y = 2.0 * math.atan2(radius * sin_dep, rng)
    angle_x = angle_y = float("nan")
    if mount is not None:
        cam = mount.body_from_camera().T @ body
        angle_x, angle_y = math.atan2(cam[0], cam[2]), math.atan2(cam[1], cam[2])
    return Aim(body, rng, angle_x, angle_y, size_x, size_y)


def aim_at_pose(point_ned_m: np.ndarray, state: VehicleState, disc_radius_m: float,
                mount: Optional[Mount] = None) -> Optional[Aim]:
    """A local NED point seen from ``state`` (needs the vehicle position), or None."""
    if state.position_ned_m is None:
        return None
    offset = np.asarray(point_ned_m, dtype=np.float64) - np.asarray(state.position_ned_m, dtype=np.float64)
    return aim_from_offset(offset, state.attitude, disc_radius_m, state.camera_mount or mount)


def aimed(target: Target, aim: Aim) -> Target:
    """``target`` with the pose-dependent fields of ``aim`` (angles kept when the aim has none)."""
    keep_angles = not math.isfinite(aim.angle_x_rad)
    return replace(target, position_body_frd_m=aim.body_frd_m, range_m=aim.range_m,
                   angle_x_rad=target.angle_x_rad if keep_angles else aim.angle_x_rad,
                   angle_y_rad=target.angle_y_rad if keep_angles else aim.angle_y_rad,
                   size_x_rad=aim.size_x_rad, size_y_rad=aim.size_y_rad)
