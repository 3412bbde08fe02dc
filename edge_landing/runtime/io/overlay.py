"""The ``--record`` overlay video: HVO colours, the landable grid (top-down inset), the target and its clear disc.

Drawing never raises into the loop: a frame that cannot be drawn is written plain and counted.
"""
from __future__ import annotations

import logging
import math
import os
from pathlib import Path
from typing import Any, Optional

import cv2
import numpy as np

from edge_landing.runtime.core.camera import Intrinsics, Mount
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.core.messages import Frame, Prediction, Target, VehicleState
from edge_landing.runtime.fusion.grid import GridView
from edge_landing.runtime.fusion.motion_grid import GeometryView

log = logging.getLogger(__name__)
# RGB colours of horizontal / vertical / other (green = landable kind of surface).
HVO_COLOURS = np.array([[40, 200, 60], [220, 50, 50], [240, 200, 40]], dtype=np.uint8)
INSET_PX = 160


def hvo_colours(rgb: np.ndarray, hvo_prob: Optional[np.ndarray], alpha: float = 0.35) -> np.ndarray:
    """Blend the argmax HVO class colours over the image."""
    if hvo_prob is None:
        plain: np.ndarray = rgb.copy()
        return plain
    labels = np.argmax(hvo_prob, axis=2).astype(np.uint8)
    labels = cv2.resize(labels, (rgb.shape[1], rgb.shape[0]), interpolation=cv2.INTER_NEAREST)
    colour = HVO_COLOURS[labels]
    out: np.ndarray = cv2.addWeighted(rgb, 1.0 - alpha, colour, alpha, 0.0)
    return out


def grid_inset(grid: Optional[GridView], target: Target, state: Optional[VehicleState],
               size_px: int = INSET_PX, geometry: Optional[GeometryView] = None) -> Optional[np.ndarray]:
    """Top-down grid (north up): unobserved grey, observed but not landable red, target ring.

    Without geometry evidence landable cells are green. With it (ARCHITECTURE.md §11): landable and
    confirmed by motion geometry green, landable by the network only (tracked, not confirmed) amber,
    cells where the parallax showed an obstacle magenta; the network's unconfirmed spot a yellow cross."""
    if grid is None:
        return None
    rows, cols = grid.shape
    img: np.ndarray = np.full((rows, cols, 3), 60, dtype=np.uint8)
    img[grid.observed] = (170, 40, 40)
    if geometry is not None and geometry.clear.shape == grid.landable.shape:
        img[grid.landable] = (215, 160, 30)
        img[grid.landable & geometry.clear] = (40, 190, 60)
        img[geometry.obstacle] = (220, 50, 220)
    else:
        img[grid.landable] = (40, 190, 60)
    img = np.ascontiguousarray(img[::-1])  # row 0 is the southmost: flip so north is up
    scale = size_px / max(rows, cols)
    img = cv2.resize(img, (max(1, int(cols * scale)), max(1, int(rows * scale))), interpolation=cv2.INTER_NEAREST)
    if target.valid and target.position_body_frd_m is not None:
        ne = _target_ne(grid, target, state)
        if ne is not None:
            col = (ne[1] - grid.east0_m) / grid.cell_m * scale
            row = (rows - (ne[0] - grid.north0_m) / grid.cell_m) * scale
            radius = max(2, int(target.clearance_m / grid.cell_m * scale)) if math.isfinite(target.clearance_m) else 3
            cv2.circle(img, (int(col), int(row)), radius, (255, 255, 255), 1)
            cv2.drawMarker(img, (int(col), int(row)), (255, 255, 255), cv2.MARKER_CROSS, 6, 1)
    if not target.valid and target.tracked_ned_m is not None and grid.frame == "ned":
        col = (target.tracked_ned_m[1] - grid.east0_m) / grid.cell_m * scale
        row = (rows - (target.tracked_ned_m[0] - grid.north0_m) / grid.cell_m) * scale
        cv2.drawMarker(img, (int(col), int(row)), (255, 230, 0), cv2.MARKER_TILTED_CROSS, 6, 1)
    return img


def evidence_line(target: Target) -> str:
    """What vouched for this frame's spot (ARCHITECTURE.md §11), for the overlay's corner."""
    if target.valid and target.evidence.startswith("geometry"):
        return (f"geometry: baseline {target.geometry_baseline_m:.0f} m, "
                f"sees >= {target.geometry_detectable_m:.2f} m")
    if target.valid and target.evidence:
        return "network only (not confirmed)"
    if target.tracked_ned_m is not None:
        return "tracked, not confirmed"
    return ""


def _target_ne(grid: GridView, target: Target, state: Optional[VehicleState]) -> Optional[np.ndarray]:
    if grid.frame == "ned":
        return None if target.position_ned_m is None else target.position_ned_m[:2]
    att = state.attitude.ned_from_body() if state is not None else np.eye(3)
    out: np.ndarray = (att @ np.asarray(target.position_body_frd_m))[:2]
    return out


def draw_target(img: np.ndarray, target: Target, intrinsics: Intrinsics, mount: Mount) -> None:
    """The target point and its clear disc, projected into the image (in place)."""
    if not target.valid or target.position_body_frd_m is None:
        cv2.putText(img, f"no target: {target.reason}"[:60], (6, img.shape[0] - 8), cv2.FONT_HERSHEY_SIMPLEX,
                    0.4, (255, 80, 80), 1, cv2.LINE_AA)
        return
    k = intrinsics.scaled(img.shape[1], img.shape[0])
    p_cam = mount.body_from_camera().T @ np.asarray(target.position_body_frd_m, dtype=np.float64)
    if p_cam[2] <= 0:
        return
    u, v = k.project(p_cam)
    size = target.size_x_rad if math.isfinite(target.size_x_rad) else 0.0
    radius = max(3, int(k.fx * math.tan(size / 2.0)))
    centre = (int(round(u)), int(round(v)))
    cv2.circle(img, centre, radius, (255, 255, 255), 2, cv2.LINE_AA)
    cv2.drawMarker(img, centre, (255, 255, 255), cv2.MARKER_CROSS, 12, 2)
    cv2.putText(img, f"range {target.range_m:.1f} m  clear {target.clearance_m:.1f} m", (6, img.shape[0] - 8),
                cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)


class OverlayRecorder:
    """Writes the overlay video; opened at the first frame (its size), closed by ``close``."""

    def __init__(self, path: os.PathLike[str] | str, intrinsics: Intrinsics, mount: Mount, fps: float = 10.0):
        self.path = Path(path)
        if not self.path.parent.is_dir() or not os.access(self.path.parent, os.W_OK):
            raise InputError(f"cannot record to {self.path}: folder {self.path.parent} does not exist or is not writable")
        self.intrinsics, self.mount, self.fps = intrinsics, mount, fps
        self.frames = 0
        self.failures = 0
        self._writer: Optional[Any] = None

    def write(self, frame: Frame, pred: Prediction, target: Target, state: Optional[VehicleState] = None,
              grid: Optional[GridView] = None, geometry: Optional[GeometryView] = None) -> None:
        """One overlay frame; ``grid`` is the fusion grid this frame was judged on (FusionResult.grid),
        ``geometry`` the motion-geometry evidence on its cells (FusionResult.geometry)."""
        try:
            img = self.render(frame, pred, target, state, grid, geometry)
        except Exception as exc:  # a drawing bug must not stop the flight loop: record the plain frame
            self.failures += 1
            log.debug("overlay failed on frame %d: %s", frame.frame_id, exc)
            img = frame.rgb
        if self._writer is None:
            h, w = img.shape[:2]
            self._writer = cv2.VideoWriter(str(self.path), cv2.VideoWriter.fourcc(*"mp4v"), self.fps, (w, h))
            if not self._writer.isOpened():
                log.error("cannot open %s for writing; recording is off", self.path)
                self._writer = _NullWriter()
        self._writer.write(cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        self.frames += 1

    def render(self, frame: Frame, pred: Prediction, target: Target, state: Optional[VehicleState],
               grid: Optional[GridView] = None, geometry: Optional[GeometryView] = None) -> np.ndarray:
        img = hvo_colours(frame.rgb, pred.hvo_prob)
        draw_target(img, target, self.intrinsics, self.mount if state is None else state.mount_of(self.mount))
        inset = grid_inset(grid, target, state,
                           size_px=min(INSET_PX, img.shape[0] // 2, img.shape[1] // 2), geometry=geometry)
        said = evidence_line(target)
        if said:
            cv2.putText(img, said, (6, img.shape[0] - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (255, 255, 255), 1,
                        cv2.LINE_AA)
        if inset is not None:
            h, w = inset.shape[:2]
            x0 = img.shape[1] - w
            img[:h, x0:] = inset
            # Frame the inset and say what it is, so it does not read as part of the camera image.
            cv2.rectangle(img, (x0, 0), (img.shape[1] - 1, h - 1), (255, 255, 255), 1)
            cv2.putText(img, "grid N^", (x0 + 3, h - 4), cv2.FONT_HERSHEY_SIMPLEX, 0.33, (255, 255, 255), 1,
                        cv2.LINE_AA)
        cv2.putText(img, f"#{frame.frame_id}", (6, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
        if pred.hvo_prob is not None:  # legend of the blended class colours: horizontal, vertical, other
            cv2.rectangle(img, (3, 18), (44, 32), (30, 30, 30), -1)  # dark backing: the colours sit on the same hues
            x = 6
            for letter, colour in zip("HVO", HVO_COLOURS):
                cv2.putText(img, letter, (x, 28), cv2.FONT_HERSHEY_SIMPLEX, 0.4, tuple(int(c) for c in colour), 1,
                            cv2.LINE_AA)
                x += 12
        return img

    def close(self) -> None:
        if self._writer is not None:
            self._writer.release()


class _NullWriter:
    def write(self, _img: np.ndarray) -> None:
        pass

    def release(self) -> None:
        pass
