"""Camera model and frames (ARCHITECTURE.md §3).

Camera frame: OpenCV, x right, y down, z forward (optical axis). Body frame: FRD. World: local NED.
The mount is the rotation body <- camera given by the camera's Tait-Bryan angles relative to the body
(FRD convention, positive pitch = up): a camera looking 45° below the horizon has ``pitch_rad = -pi/4``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Any, Mapping

import cv2
import numpy as np

from edge_landing.runtime.core.errors import InputError

# Camera axes expressed in body FRD for a camera looking straight ahead:
# camera z (forward) = body x, camera x (right) = body y, camera y (down) = body z.
_BODY_FROM_CAMERA_LEVEL = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
DEFAULT_HFOV_RAD = math.radians(90.0)
DEFAULT_MOUNT_PITCH_RAD = math.radians(-45.0)


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels at the image's own size, optional OpenCV distortion coefficients."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0 or self.fx <= 0 or self.fy <= 0:
            raise InputError(f"intrinsics need positive size and focal lengths, got {self.width}x{self.height}, "
                             f"fx={self.fx}, fy={self.fy}")

    @staticmethod
    def from_hfov(width: int, height: int, hfov_rad: float = DEFAULT_HFOV_RAD) -> Intrinsics:
        """Square pixels, principal point at the image centre (AirSim's camera model)."""
        if not 0 < hfov_rad < math.pi:
            raise InputError(f"horizontal field of view must be in (0, 180) degrees, got {math.degrees(hfov_rad):.1f}")
        f = (width / 2.0) / math.tan(hfov_rad / 2.0)
        return Intrinsics(width, height, f, f, width / 2.0, height / 2.0)

    @property
    def matrix(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1]], dtype=np.float64)

    @property
    def hfov_rad(self) -> float:
        return 2.0 * math.atan(self.width / (2.0 * self.fx))

    def scaled(self, width: int, height: int) -> Intrinsics:
        """The same camera at another image size (pixel-edge convention: u' = u * sx)."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(width, height, self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, self.dist)

    def pixel_rays(self) -> np.ndarray:
        """H×W×3 float32 array of K⁻¹[u+0.5, v+0.5, 1] (z = 1) for every pixel centre.

        With distortion coefficients the pixel centres are undistorted first (OpenCV's model), so every ray
        is the true direction that pixel sees. Cached per intrinsics (the per-frame stages ask for the same
        table every frame); read-only.
        """
        return _pixel_rays(self)

    def backproject(self, depth_m: np.ndarray) -> np.ndarray:
        """Planar z-depth H×W -> camera-frame points H×W×3 (NaN stays NaN)."""
        if depth_m.shape != (self.height, self.width):
            raise InputError(f"depth shape {depth_m.shape} does not match intrinsics {self.height}x{self.width}")
        points: np.ndarray = self.pixel_rays() * depth_m[..., None].astype(np.float32)
        return points

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Camera-frame points (...×3, z > 0) -> pixel coordinates (...×2), pixel-edge convention, distorted
        like the image when the intrinsics carry distortion coefficients."""
        if self.dist:
            flat = np.ascontiguousarray(points_cam.reshape(-1, 3), dtype=np.float64)
            uv, _ = cv2.projectPoints(flat, np.zeros(3), np.zeros(3), self.matrix, np.asarray(self.dist, np.float64))
            return uv.reshape(points_cam.shape[:-1] + (2,))
        z = points_cam[..., 2]
        u = self.fx * points_cam[..., 0] / z + self.cx
        v = self.fy * points_cam[..., 1] / z + self.cy
        return np.stack([u, v], axis=-1)

    def to_json(self) -> dict[str, Any]:
        return {"width": self.width, "height": self.height, "fx": self.fx, "fy": self.fy,
                "cx": self.cx, "cy": self.cy, "dist": list(self.dist)}

    @staticmethod
    def from_json(d: Mapping[str, Any]) -> Intrinsics:
        return Intrinsics(int(d["width"]), int(d["height"]), float(d["fx"]), float(d["fy"]),
                          float(d["cx"]), float(d["cy"]), tuple(float(v) for v in d.get("dist", ()) or ()))


@lru_cache(maxsize=16)
def _pixel_rays(intrinsics: Intrinsics) -> np.ndarray:
    u = (np.arange(intrinsics.width, dtype=np.float64) + 0.5 - intrinsics.cx) / intrinsics.fx
    v = (np.arange(intrinsics.height, dtype=np.float64) + 0.5 - intrinsics.cy) / intrinsics.fy
    rays = np.empty((intrinsics.height, intrinsics.width, 3), dtype=np.float32)
    rays[..., 0] = u[None, :]
    rays[..., 1] = v[:, None]
    rays[..., 2] = 1.0
    if intrinsics.dist:
        uu, vv = np.meshgrid(np.arange(intrinsics.width) + 0.5, np.arange(intrinsics.height) + 0.5)
        pixels = np.stack([uu, vv], axis=-1).reshape(-1, 1, 2)
        xy = _undistort(pixels, intrinsics.matrix, np.asarray(intrinsics.dist, np.float64))
        rays[..., :2] = xy.reshape(intrinsics.height, intrinsics.width, 2)
    rays.setflags(write=False)
    return rays


def _undistort(pixels: np.ndarray, k: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Normalised undistorted coordinates; 40 iterations (OpenCV's default 5 leaves wide lenses' corners off)."""
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10)
    if hasattr(cv2, "undistortPointsIter"):        # OpenCV 4.x
        xy: np.ndarray = cv2.undistortPointsIter(pixels, k, dist, None, None, criteria)
        return xy
    return cv2.undistortPoints(pixels, k, dist, criteria=criteria)   # OpenCV 5: the criteria overload


def rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]], dtype=np.float64)


def rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=np.float64)


def rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=np.float64)


def rotation_from_euler(roll_rad: float, pitch_rad: float, yaw_rad: float) -> np.ndarray:
    """ZYX Tait-Bryan rotation (aerospace): maps body FRD vectors into the parent (NED) frame."""
    r: np.ndarray = rot_z(yaw_rad) @ rot_y(pitch_rad) @ rot_x(roll_rad)
    return r


@dataclass(frozen=True)
class Mount:
    """Camera orientation relative to the body (radians, FRD Tait-Bryan; pitch -pi/4 = 45° down)."""

    pitch_rad: float = DEFAULT_MOUNT_PITCH_RAD
    roll_rad: float = 0.0
    yaw_rad: float = 0.0

    def body_from_camera(self) -> np.ndarray:
        """3×3 rotation: v_body = R @ v_camera."""
        r: np.ndarray = rotation_from_euler(self.roll_rad, self.pitch_rad, self.yaw_rad) @ _BODY_FROM_CAMERA_LEVEL
        return r

    @staticmethod
    def from_body_from_gimbal(r_body_gimbal: np.ndarray) -> Mount:
        """The mount whose camera FRD axes (x: the optical axis) are ``r_body_gimbal`` (v_body = R @ v_gimbal).

        ZYX angles; at ±90° pitch (a camera looking straight down) roll and yaw turn about one axis, so the turn
        is all given to yaw: the rotation is the same."""
        r = np.asarray(r_body_gimbal, dtype=np.float64)
        pitch = math.asin(max(-1.0, min(1.0, -float(r[2, 0]))))
        if math.hypot(float(r[0, 0]), float(r[1, 0])) < 1e-9:
            return Mount(pitch_rad=pitch, roll_rad=0.0, yaw_rad=math.atan2(-float(r[0, 1]), float(r[1, 1])))
        return Mount(pitch_rad=pitch, roll_rad=math.atan2(float(r[2, 1]), float(r[2, 2])),
                     yaw_rad=math.atan2(float(r[1, 0]), float(r[0, 0])))


@dataclass(frozen=True)
class Attitude:
    """Vehicle attitude (radians), body FRD relative to local NED. Level flight by default."""

    roll_rad: float = 0.0
    pitch_rad: float = 0.0
    yaw_rad: float = 0.0

    def ned_from_body(self) -> np.ndarray:
        return rotation_from_euler(self.roll_rad, self.pitch_rad, self.yaw_rad)


def ned_from_camera(mount: Mount, attitude: Attitude = Attitude()) -> np.ndarray:
    """3×3 rotation: v_ned = R @ v_camera (gravity-aligned, heading from the attitude's yaw)."""
    r: np.ndarray = attitude.ned_from_body() @ mount.body_from_camera()
    return r


def up_in_camera(mount: Mount, attitude: Attitude = Attitude()) -> np.ndarray:
    """World 'up' (NED -z) expressed in the camera frame, unit vector."""
    up: np.ndarray = ned_from_camera(mount, attitude).T @ np.array([0.0, 0.0, -1.0])
    return up
