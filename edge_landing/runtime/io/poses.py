"""Recorded vehicle poses: the ``poses.csv`` of a scene folder or of an ``edge-sim --flight`` (ARCHITECTURE.md §4).

The drone side reads them to replay a recorded flight's telemetry (``edge-run --poses``); the scene reader
in ``edge_landing.evaluation.scene`` uses the same rows.
"""
from __future__ import annotations

import csv
import os
from dataclasses import dataclass
from pathlib import Path
from typing import List, Tuple

from edge_landing.runtime.core.errors import SceneError

POSE_FIELDS = ("frame", "t", "north", "east", "down", "roll", "pitch", "yaw", "agl")


@dataclass(frozen=True)
class Pose:
    """Vehicle pose at a frame: local NED position (m), attitude (rad), height above ground (m)."""

    frame: int
    t_s: float
    ned_m: Tuple[float, float, float]
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    agl_m: float



def read_poses_csv(path: os.PathLike[str] | str) -> List[Pose]:
    """The rows of a poses.csv (ARCHITECTURE.md §4) in file order; a missing column or bad row is a SceneError."""
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"poses file {path} does not exist (expected a poses.csv: {','.join(POSE_FIELDS)})")
    out = []
    with open(path, newline="") as fh:
        reader = csv.DictReader(fh)
        missing = [f for f in POSE_FIELDS if f not in (reader.fieldnames or [])]
        if missing:
            raise SceneError(f"{path}: missing column(s) {', '.join(missing)}; expected {','.join(POSE_FIELDS)}")
        for line, row in enumerate(reader, start=2):
            try:
                out.append(Pose(int(row["frame"]), float(row["t"]),
                                (float(row["north"]), float(row["east"]), float(row["down"])),
                                float(row["roll"]), float(row["pitch"]), float(row["yaw"]), float(row["agl"])))
            except (TypeError, ValueError) as exc:
                raise SceneError(f"{path}:{line}: malformed pose row ({exc})") from None
    return out
