"""Contact sheet of a scene folder: one row per frame with RGB, colour-mapped depth and coloured HVO."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from edge_landing.evaluation.scene import Scene
from edge_landing.runtime.core.errors import SceneError

# Horizontal green, vertical red, other blue, ignore (sky) black.
HVO_COLOURS = np.zeros((256, 3), np.uint8)
HVO_COLOURS[0], HVO_COLOURS[1], HVO_COLOURS[2] = (60, 200, 60), (220, 50, 50), (60, 90, 230)


def depth_colour(depth_m: np.ndarray, max_m: float | None = None) -> np.ndarray:
    """uint8 RGB: log-scaled turbo colour map, sky black."""
    import cv2

    valid = np.isfinite(depth_m) & (depth_m > 0)
    if not valid.any():
        return np.zeros(depth_m.shape + (3,), np.uint8)
    lo = float(np.log(np.nanmin(depth_m[valid])))
    hi = float(np.log(max_m if max_m else np.nanmax(depth_m[valid])))
    x = np.zeros(depth_m.shape, np.float32)
    x[valid] = (np.log(depth_m[valid]) - lo) / max(hi - lo, 1e-6)
    img = cv2.applyColorMap(np.clip(x * 255, 0, 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    img[~valid] = 0
    return img


def write_contact_sheet(scene_dir: Path, out_png: Path, rows: int = 4) -> Path:
    """Evenly spaced frames of the scene, RGB | depth | HVO per row; returns the PNG path."""
    import cv2

    scene = Scene(scene_dir)
    ids = [scene.frame_ids[i] for i in np.unique(np.linspace(0, len(scene) - 1, min(rows, len(scene))).astype(int))]
    lines = []
    for fid in ids:
        tiles = [scene.read_rgb(fid)]
        if scene.has_depth:
            tiles.append(depth_colour(scene.read_depth(fid)))
        if scene.has_hvo:
            tiles.append(HVO_COLOURS[scene.read_hvo(fid)])
        lines.append(np.concatenate(tiles, axis=1))
    sheet = np.concatenate(lines, axis=0)
    if not cv2.imwrite(str(out_png), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR)):
        raise SceneError(f"could not write the contact sheet {out_png}")
    return Path(out_png)
