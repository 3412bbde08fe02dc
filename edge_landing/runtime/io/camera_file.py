"""A real camera's calibrated intrinsics from a file (``edge-run --intrinsics``).

Motion geometry measures parallax to a fraction of a pixel, so a real lens's distortion (a wide USB camera's
barrel, k1 around -0.3) must be known: read as a pinhole, it bends level ground into false heights towards the
image's edges. Three formats are read:

- JSON, the project's own (``Intrinsics.to_json``: width, height, fx, fy, cx, cy, dist), at the top level,
  under ``"camera"`` (a scene folder's ``scene.json``) or under ``"intrinsics"``. Pixel-edge convention, like
  the runtime.
- OpenCV's FileStorage YAML or XML, as ``cv::calibrateCamera`` tools write it: ``camera_matrix`` (or
  ``cameraMatrix``, ``K``), ``distortion_coefficients`` (or ``dist_coeffs``, ``distCoeffs``, ``D``),
  ``image_width`` and ``image_height``.
- ROS ``camera_info`` YAML (``camera_matrix``/``distortion_coefficients`` with ``data`` lists, the
  ``plumb_bob`` or ``rational_polynomial`` model, which are OpenCV's).

OpenCV and ROS put pixel centres at integers; the runtime at +0.5, so their principal point moves by half a
pixel on reading. Every problem is one ``InputError`` line naming the file and the value.
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, List, Optional, Sequence

from edge_landing.runtime.core.camera import Intrinsics
from edge_landing.runtime.core.errors import InputError

__all__ = ["load_intrinsics", "fit_to_frame"]

MATRIX_KEYS = ("camera_matrix", "cameraMatrix", "K")
DIST_KEYS = ("distortion_coefficients", "dist_coeffs", "distCoeffs", "D")
OPENCV_MODELS = ("plumb_bob", "rational_polynomial", "")   # OpenCV's own distortion model, by ROS's names
DIST_LENGTHS = (0, 4, 5, 8, 12, 14)                          # what OpenCV's distortion model accepts


def load_intrinsics(path: str) -> Intrinsics:
    """The intrinsics in ``path`` (JSON, OpenCV YAML/XML, ROS camera_info YAML), checked."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"--intrinsics file {path} does not exist")
    if p.suffix.lower() == ".json":
        intr = _from_json(p)
    elif p.suffix.lower() in (".yaml", ".yml", ".xml"):
        intr = _from_filestorage(p)
    else:
        raise InputError(f"--intrinsics {path}: expected a .json, .yaml/.yml or .xml file")
    return _checked(intr, path)


def fit_to_frame(intr: Intrinsics, width: int, height: int, path: str) -> Intrinsics:
    """The calibration at the camera's frame size; a different aspect ratio is another image (a crop or
    another mode of the camera) that the calibration does not describe."""
    if abs(intr.width / intr.height - width / height) > 0.01 * width / height:
        raise InputError(f"--intrinsics {path} was calibrated at {intr.width}x{intr.height}, but the camera gives "
                         f"{width}x{height} frames (another aspect ratio: calibrate at this size)")
    return intr.scaled(width, height)


def _from_json(p: Path) -> Intrinsics:
    try:
        d = json.loads(p.read_text())
    except (OSError, ValueError) as exc:
        raise InputError(f"--intrinsics {p}: not readable JSON ({exc})") from None
    for key in ("camera", "intrinsics"):   # a scene folder's scene.json keeps them under "camera"
        if isinstance(d, dict) and isinstance(d.get(key), dict):
            d = d[key]
    try:
        return Intrinsics.from_json(d)
    except InputError as exc:
        raise InputError(f"--intrinsics {p}: {exc}") from None
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"--intrinsics {p}: needs width, height, fx, fy, cx, cy (and optional dist): {exc}") from None


def _from_filestorage(p: Path) -> Intrinsics:
    import cv2

    try:
        fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError):   # OpenCV's parser error (surfacing as SystemError from the constructor)
        raise InputError(f"--intrinsics {p}: not an OpenCV or ROS calibration file (its parser refused it)") from None
    try:
        if not fs.isOpened():
            raise InputError(f"--intrinsics {p}: not an OpenCV or ROS calibration file")
        k = _numbers(fs, MATRIX_KEYS)
        if k is None or len(k) != 9:
            raise InputError(f"--intrinsics {p}: no 3x3 camera matrix ({', '.join(MATRIX_KEYS)})")
        dist = _numbers(fs, DIST_KEYS) or []
        model = fs.getNode("distortion_model").string() if not fs.getNode("distortion_model").empty() else ""
        width, height = _number(fs, ("image_width", "width")), _number(fs, ("image_height", "height"))
    finally:
        fs.release()
    if model not in OPENCV_MODELS:
        raise InputError(f"--intrinsics {p}: distortion model '{model}' is not OpenCV's pinhole model "
                         f"({', '.join(m for m in OPENCV_MODELS if m)})")
    if width is None or height is None:
        raise InputError(f"--intrinsics {p}: needs image_width and image_height (the size it was calibrated at)")
    try:
        return Intrinsics(int(width), int(height), k[0], k[4], k[2] + 0.5, k[5] + 0.5, tuple(dist))
    except InputError as exc:
        raise InputError(f"--intrinsics {p}: {exc}") from None


def _numbers(fs: Any, keys: Sequence[str]) -> Optional[List[float]]:
    for key in keys:
        node = fs.getNode(key)
        if node.empty():
            continue
        mat = node.mat() if not node.isMap() or not node.getNode("dt").empty() else None
        if mat is not None:
            return [float(v) for v in mat.ravel()]
        data = node.getNode("data") if node.isMap() else node
        if data.isSeq():
            return [data.at(i).real() for i in range(data.size())]
    return None


def _number(fs: Any, keys: Sequence[str]) -> Optional[float]:
    for key in keys:
        node = fs.getNode(key)
        if not node.empty() and (node.isInt() or node.isReal()):
            return float(node.real())
    return None


def _checked(intr: Intrinsics, path: str) -> Intrinsics:
    values = (intr.fx, intr.fy, intr.cx, intr.cy) + tuple(intr.dist)
    if not all(math.isfinite(v) for v in values):
        raise InputError(f"--intrinsics {path}: a value is not finite")
    if not (0 < intr.cx < intr.width and 0 < intr.cy < intr.height):
        raise InputError(f"--intrinsics {path}: principal point ({intr.cx:g}, {intr.cy:g}) outside the "
                         f"{intr.width}x{intr.height} image")
    if len(intr.dist) not in DIST_LENGTHS:
        raise InputError(f"--intrinsics {path}: {len(intr.dist)} distortion coefficients (OpenCV takes "
                         f"{', '.join(str(n) for n in DIST_LENGTHS[1:])})")
    if not 10.0 < math.degrees(intr.hfov_rad) < 170.0:
        raise InputError(f"--intrinsics {path}: fx {intr.fx:g} px gives a {math.degrees(intr.hfov_rad):.0f}° "
                         f"field of view at width {intr.width}")
    return intr
