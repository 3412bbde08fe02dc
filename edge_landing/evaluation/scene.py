"""Scene folders (ARCHITECTURE.md §4): reading and writing frames with their ground truth.

```
scene/
  scene.json            camera, mount, depth units, HVO thresholds, generator and seed, frame count
  rgb/000000.png        8-bit RGB (PNG or JPG)
  depth/000000.npy      float32 z-depth in metres, NaN where invalid
  hvo/000000.png        uint8 labels 0/1/2, 255 = ignore
  normals/000000.npy    optional float16 unit normals, camera frame
  poses.csv             optional: frame, t, north, east, down, roll, pitch, yaw, agl (m, rad)
```
Any folder with ``rgb/`` is a scene. Readers name the missing or malformed file in their error.
"""
from __future__ import annotations

import csv
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional

import numpy as np

from edge_landing.runtime.core.camera import Intrinsics, Mount
from edge_landing.runtime.core.errors import SceneError
from edge_landing.runtime.core.geometry import HvoThresholds
from edge_landing.runtime.io.poses import POSE_FIELDS, Pose, read_poses_csv

RGB_SUFFIXES = (".png", ".jpg", ".jpeg")


@dataclass(frozen=True)
class SceneMeta:
    """The contents of ``scene.json`` (angles stored in degrees there, radians here)."""

    intrinsics: Intrinsics
    mount: Mount = Mount()
    hvo_thresholds: HvoThresholds = HvoThresholds()
    depth_units: str = "m"
    generator: dict = field(default_factory=dict)
    frame_count: int = 0

    def to_json(self) -> dict:
        return {
            "camera": self.intrinsics.to_json(),
            "mount": {"pitch_deg": math.degrees(self.mount.pitch_rad), "roll_deg": math.degrees(self.mount.roll_rad),
                      "yaw_deg": math.degrees(self.mount.yaw_rad),
                      "convention": "camera relative to body FRD, Tait-Bryan ZYX, pitch negative = below the horizon"},
            "depth_units": self.depth_units,
            "depth_kind": "planar z-depth along the optical axis, NaN = invalid (sky)",
            "hvo": {**self.hvo_thresholds.to_json(), "labels": {"0": "horizontal", "1": "vertical", "2": "other",
                                                                 "255": "ignore"}},
            "generator": self.generator,
            "frame_count": self.frame_count,
        }

    @staticmethod
    def from_json(d: dict) -> SceneMeta:
        mount = d.get("mount", {})
        return SceneMeta(
            intrinsics=Intrinsics.from_json(d["camera"]),
            mount=Mount(math.radians(float(mount.get("pitch_deg", -45.0))), math.radians(float(mount.get("roll_deg", 0.0))),
                        math.radians(float(mount.get("yaw_deg", 0.0)))),
            hvo_thresholds=HvoThresholds.from_json(d.get("hvo", {})),
            depth_units=str(d.get("depth_units", "m")),
            generator=dict(d.get("generator", {})),
            frame_count=int(d.get("frame_count", 0)),
        )


class Scene:
    """Read access to a scene folder. Frame ids are the file stems under ``rgb/`` (sorted)."""

    def __init__(self, path: os.PathLike | str):
        self.path = Path(path)
        if not self.path.is_dir():
            raise SceneError(f"scene folder {self.path} does not exist or is not a folder")
        rgb_dir = self.path / "rgb"
        if not rgb_dir.is_dir():
            raise SceneError(f"{self.path} is not a scene: it has no rgb/ folder (expected rgb/000000.png, ...)")
        self._rgb = {p.stem: p for p in sorted(rgb_dir.iterdir()) if p.suffix.lower() in RGB_SUFFIXES}
        if not self._rgb:
            raise SceneError(f"scene {self.path} is empty: no .png or .jpg images in {rgb_dir}")
        self.frame_ids: List[str] = sorted(self._rgb)
        self.meta = self._read_meta()

    def __len__(self) -> int:
        return len(self.frame_ids)

    def _read_meta(self) -> SceneMeta:
        meta_path = self.path / "scene.json"
        if not meta_path.exists():
            h, w = self.read_rgb(self.frame_ids[0]).shape[:2]
            return SceneMeta(intrinsics=Intrinsics.from_hfov(w, h), frame_count=len(self.frame_ids))
        try:
            return SceneMeta.from_json(json.loads(meta_path.read_text()))
        except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
            raise SceneError(f"{meta_path} is malformed ({exc!r}); expected the scene.json of ARCHITECTURE.md §4") from None

    @property
    def has_depth(self) -> bool:
        return (self.path / "depth").is_dir()

    @property
    def has_hvo(self) -> bool:
        return (self.path / "hvo").is_dir()

    def read_rgb(self, frame_id: str) -> np.ndarray:
        """uint8 H×W×3 RGB."""
        import cv2

        path = self._rgb.get(frame_id)
        if path is None:
            raise SceneError(f"scene {self.path}: no rgb image for frame {frame_id}")
        bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if bgr is None:
            raise SceneError(f"frame {frame_id}: {path} is not a readable image (corrupt or not PNG/JPG)")
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)

    def read_depth(self, frame_id: str) -> np.ndarray:
        """float32 H×W planar depth in metres, NaN where invalid (zeros become NaN)."""
        path = self.path / "depth" / f"{frame_id}.npy"
        depth = _load_npy(path, frame_id, "float32 H×W depth in metres")
        if depth.ndim != 2:
            raise SceneError(f"frame {frame_id}: {path} has shape {depth.shape}; expected H×W depth")
        depth = depth.astype(np.float32, copy=True)
        depth[depth <= 0] = np.nan
        return depth

    def read_hvo(self, frame_id: str) -> np.ndarray:
        """uint8 H×W labels 0/1/2/255."""
        import cv2

        path = self.path / "hvo" / f"{frame_id}.png"
        if not path.exists():
            raise SceneError(f"frame {frame_id}: missing {path} (expected uint8 HVO labels 0/1/2/255)")
        labels = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if labels is None or labels.ndim != 2 or labels.dtype != np.uint8:
            raise SceneError(f"frame {frame_id}: {path} is not a single-channel uint8 label image")
        return labels

    def read_normals(self, frame_id: str) -> Optional[np.ndarray]:
        """float32 H×W×3 camera-frame normals, or None when the scene has none."""
        path = self.path / "normals" / f"{frame_id}.npy"
        if not path.exists():
            return None
        return _load_npy(path, frame_id, "float16 H×W×3 normals").astype(np.float32)

    def poses(self) -> dict:
        """frame id (str, zero-padded like the files) -> Pose; empty when there is no poses.csv."""
        path = self.path / "poses.csv"
        return {f"{p.frame:06d}": p for p in read_poses_csv(path)} if path.exists() else {}

    def require(self, depth: bool = False, hvo: bool = False, purpose: str = "this command") -> None:
        """Fail fast when ground truth that ``purpose`` needs is missing."""
        for needed, name, what in ((depth, "depth", "depth/000000.npy"), (hvo, "hvo", "hvo/000000.png")):
            if needed and not (self.path / name).is_dir():
                raise SceneError(f"scene {self.path} has no {name}/ folder, which {purpose} needs "
                                 f"(expected {what}, ... beside rgb/)")


class SceneWriter:
    """Writes a scene folder frame by frame; ``close()`` writes scene.json and poses.csv last."""

    def __init__(self, path: os.PathLike | str, meta: SceneMeta, rgb_format: str = "png"):
        self.path = Path(path)
        self.meta = meta
        self.rgb_format = rgb_format
        self._poses: List[Pose] = []
        self._count = 0
        try:
            for sub in ("rgb", "depth", "hvo"):
                (self.path / sub).mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise SceneError(f"cannot create scene folder {self.path}: {exc.strerror}") from None
        if not os.access(self.path, os.W_OK):
            raise SceneError(f"scene folder {self.path} is not writable")

    def write(self, index: int, rgb: np.ndarray, depth_m: Optional[np.ndarray] = None,
              hvo: Optional[np.ndarray] = None, normals: Optional[np.ndarray] = None,
              pose: Optional[Pose] = None) -> str:
        import cv2

        fid = f"{index:06d}"
        ok = cv2.imwrite(str(self.path / "rgb" / f"{fid}.{self.rgb_format}"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        if not ok:
            raise SceneError(f"could not write {self.path / 'rgb' / fid}.{self.rgb_format}")
        if depth_m is not None:
            np.save(self.path / "depth" / f"{fid}.npy", depth_m.astype(np.float32))
        if hvo is not None:
            cv2.imwrite(str(self.path / "hvo" / f"{fid}.png"), hvo.astype(np.uint8))
        if normals is not None:
            (self.path / "normals").mkdir(exist_ok=True)
            np.save(self.path / "normals" / f"{fid}.npy", normals.astype(np.float16))
        if pose is not None:
            self._poses.append(pose)
        self._count += 1
        return fid

    def close(self) -> None:
        from dataclasses import replace

        meta = replace(self.meta, frame_count=self._count)
        (self.path / "scene.json").write_text(json.dumps(meta.to_json(), indent=2, sort_keys=True))
        if self._poses:
            with open(self.path / "poses.csv", "w", newline="") as fh:
                w = csv.writer(fh)
                w.writerow(POSE_FIELDS)
                for p in self._poses:
                    w.writerow([p.frame, f"{p.t_s:.6f}", *(f"{v:.6f}" for v in p.ned_m),
                                f"{p.roll_rad:.8f}", f"{p.pitch_rad:.8f}", f"{p.yaw_rad:.8f}", f"{p.agl_m:.6f}"])


NPY_MAGIC = b"\x93NUMPY"


def _load_npy(path: Path, frame_id: str, expected: str) -> np.ndarray:
    if not path.exists():
        raise SceneError(f"frame {frame_id}: missing {path} (expected {expected})")
    try:
        with open(path, "rb") as f:
            if f.read(6) != NPY_MAGIC:  # numpy's own message for this talks about pickles
                raise SceneError(f"frame {frame_id}: {path} is not a .npy file (no NumPy header); expected {expected}")
        return np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise SceneError(f"frame {frame_id}: {path} is not a readable .npy file ({exc}); expected {expected}") from None
