"""What the pipeline writes: the ``--log`` run record and decision lines, and the status line's target text."""
from __future__ import annotations

import math
from typing import Any, Dict, List, Optional

from edge_landing.runtime.core.messages import Prediction, Target, VehicleState


def run_record(version: str, camera: str, source_kind: str, sim_style: Optional[str], sim_seed: Optional[int],
               poses: Optional[str], model: str, autopilot: Optional[str], tlog: Optional[str] = None
               ) -> Dict[str, Any]:
    """The first line of ``--log``: where the run's frames came from (benchmarks/landing_truth.py reads it)."""
    return {"run": {"version": version, "camera": camera, "source_kind": source_kind, "sim_style": sim_style,
                    "sim_seed": sim_seed, "poses": poses, "tlog": tlog, "model": model, "autopilot": autopilot}}


def describe_target(target: Optional[Target]) -> str:
    if target is None:
        return "target: none yet"
    if not target.valid or target.position_body_frd_m is None:
        return f"target: none ({target.reason})"
    x, y, z = (float(v) for v in target.position_body_frd_m)
    held = " (held from memory)" if target.reason.startswith("held") else ""
    return (f"target FRD ({x:.1f}, {y:.1f}, {z:.1f}) m, range {target.range_m:.1f} m, "
            f"clear {target.clearance_m:.1f} m{held}")


def decision_record(target: Target, pred: Prediction, state: Optional[VehicleState], sent: bool, why: str,
                    scale_source: str, level_assumed: bool = False, committed_ned_m: Optional[Any] = None,
                    committed_odometry_m: Optional[Any] = None) -> Dict[str, Any]:
    """One ``--log`` line. ``sent`` is true only when the target really left the socket; ``not_sent_because``
    says why not; ``level_assumed`` marks an offline run without telemetry (level flight assumed); ``evidence``
    is "geometry+network" (confirmed by the drone's own motion) or "network only" (--allow-unconfirmed), with
    the baseline and detectable obstacle height of the spot's geometry cell; ``tracked_ned_m`` is the
    network's unconfirmed spot on a frame that sent none;
    ``committed_ned_m`` is the committed spot after this frame (local NED; None when there is none);
    ``committed_odometry_m`` the same for a spot kept in image odometry's frame (telemetry without position);
    ``gimbal_mount_deg`` the mount a gimbal reported for the frame (None: the fixed mount)."""
    def vec(v: Optional[Any]) -> Optional[List[float]]:
        return None if v is None else [round(float(x), 4) for x in v]

    return {"frame": target.frame_id, "capture_time_s": round(target.capture_time_s, 6), "valid": target.valid,
            "reason": target.reason or ("ok" if target.valid else pred.reason), "body_frd_m": vec(target.position_body_frd_m),
            "ned_m": vec(target.position_ned_m), "range_m": _num(target.range_m), "clearance_m": _num(target.clearance_m),
            "confidence": _num(target.confidence), "scale": _num(pred.scale), "scale_source": scale_source,
            "telemetry": state is not None, "agl_m": None if state is None else state.agl_m,
            "level_assumed": level_assumed, "sent": sent, "not_sent_because": "" if sent else why,
            "committed_ned_m": vec(committed_ned_m), "committed_odometry_m": vec(committed_odometry_m),
            "gimbal_mount_deg": _mount_deg(state),
            # Which evidence vouched for the spot and the motion-geometry figures of its cell (§11).
            "evidence": target.evidence, "geometry_baseline_m": _num(target.geometry_baseline_m),
            "geometry_detectable_m": _num(target.geometry_detectable_m),
            "geometry_age_s": _num(target.geometry_age_s), "tracked_ned_m": vec(target.tracked_ned_m)}


def _mount_deg(state: Optional[VehicleState]) -> Optional[List[float]]:
    """The camera's mount (roll, pitch, yaw relative to the body, degrees) a gimbal reported for the frame."""
    m = None if state is None else state.camera_mount
    return None if m is None else [round(math.degrees(a), 3) for a in (m.roll_rad, m.pitch_rad, m.yaw_rad)]


def _num(v: Optional[float]) -> Optional[float]:
    return round(float(v), 4) if v is not None and math.isfinite(float(v)) else None
