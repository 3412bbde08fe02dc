"""Scene folders (ARCHITECTURE.md §4) as in-memory training sets.

The synthetic scenes are small (a few hundred 240×320 frames), so every frame is decoded once, resized to
the training size and kept as uint8/float32 arrays; batches are then cheap tensor slices, with no worker
processes competing for the two shared cores.

    data = load_scenes(["scenes/sub1", "scenes/sub2"], height=120, width=160, need_depth=True, need_hvo=True)
    for batch in data.batches(8, shuffle=True, seed=0):
        batch.rgb      # N×3×H×W float32 in [0, 1]
        batch.depth_m  # N×H×W float32 metres, NaN invalid   (None without depth)
        batch.hvo      # N×H×W int64 0/1/2/255               (None without labels)
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Iterator, List, Optional, Sequence

import cv2
import numpy as np
import torch
from tqdm import tqdm

from edge_landing.evaluation.scene import Scene
from edge_landing.runtime.core.errors import SceneError
from edge_landing.runtime.core.labels import HVO_IGNORE


@dataclass(frozen=True)
class Batch:
    rgb: torch.Tensor
    depth_m: Optional[torch.Tensor]
    hvo: Optional[torch.Tensor]


@dataclass(frozen=True)
class SceneInfo:
    """What the training record says about one scene (generator settings come from scene.json)."""

    path: str
    frames: int
    generator: dict

    def to_json(self) -> dict:
        # Per-frame generator draws (weather, sun per frame) would bloat edge.source by ~10 kB per scene.
        generator = {k: v for k, v in self.generator.items() if not k.startswith("per_frame")}
        return {"path": self.path, "frames": self.frames, "generator": generator}


@dataclass
class SceneSet:
    rgb: np.ndarray                  # N×H×W×3 uint8
    depth_m: Optional[np.ndarray]    # N×H×W float32, NaN invalid
    hvo: Optional[np.ndarray]        # N×H×W uint8
    scenes: List[SceneInfo]

    def __len__(self) -> int:
        return int(self.rgb.shape[0])

    @property
    def hw(self) -> tuple:
        return tuple(self.rgb.shape[1:3])

    def batch(self, index: Sequence[int] | np.ndarray) -> Batch:
        idx = np.asarray(index)
        rgb = torch.from_numpy(self.rgb[idx]).permute(0, 3, 1, 2).float().div_(255.0)
        depth = torch.from_numpy(self.depth_m[idx]) if self.depth_m is not None else None
        hvo = torch.from_numpy(self.hvo[idx]).long() if self.hvo is not None else None
        return Batch(rgb, depth, hvo)

    def batches(self, batch_size: int, shuffle: bool, seed: int = 0, drop_last: bool = False) -> Iterator[Batch]:
        order = np.random.default_rng(seed).permutation(len(self)) if shuffle else np.arange(len(self))
        stop = len(self) - (len(self) % batch_size if drop_last else 0)
        for start in range(0, stop, batch_size):
            chunk = order[start:start + batch_size]
            if len(chunk):
                yield self.batch(chunk)

    def steps(self, batch_size: int, drop_last: bool = False) -> int:
        return len(self) // batch_size if drop_last else -(-len(self) // batch_size)


def _resize(a: np.ndarray, height: int, width: int, nearest: bool) -> np.ndarray:
    if a.shape[:2] == (height, width):
        return a
    shrinking = a.shape[0] > height
    interp = cv2.INTER_NEAREST if nearest else (cv2.INTER_AREA if shrinking else cv2.INTER_LINEAR)
    return cv2.resize(a, (width, height), interpolation=interp)


def load_scene(path: os.PathLike | str, height: int, width: int, need_depth: bool, need_hvo: bool,
               progress: bool = True) -> SceneSet:
    """Every frame of one scene at height×width (RGB area-averaged; depth and labels nearest, never blended)."""
    scene = Scene(path)
    scene.require(depth=need_depth, hvo=need_hvo, purpose="training")
    n = len(scene)
    rgb = np.empty((n, height, width, 3), np.uint8)
    depth = np.empty((n, height, width), np.float32) if need_depth else None
    hvo = np.empty((n, height, width), np.uint8) if need_hvo else None
    for i, fid in enumerate(tqdm(scene.frame_ids, desc=f"load {scene.path.name}", disable=not progress, leave=False)):
        image = scene.read_rgb(fid)
        rgb[i] = _resize(image, height, width, nearest=False)
        if depth is not None:
            d = scene.read_depth(fid)
            if d.shape != image.shape[:2]:
                raise SceneError(f"frame {fid} of {scene.path}: depth is {d.shape[0]}x{d.shape[1]} but the image is "
                                 f"{image.shape[0]}x{image.shape[1]}; expected the same size")
            depth[i] = _resize(d, height, width, nearest=True)
        if hvo is not None:
            hvo[i] = _resize(scene.read_hvo(fid), height, width, nearest=True)
    info = SceneInfo(str(scene.path), n, dict(scene.meta.generator))
    return SceneSet(rgb, depth, hvo, [info])


# World styles kept out of training and model selection: our zero-shot test, as the paper keeps AirSimNC out.
HELD_OUT_STYLES = ("rural",)


def check_not_held_out(paths: Sequence[os.PathLike | str]) -> None:
    """Refuse scenes whose scene.json names a held-out style (edge-sim --style rural)."""
    for p in paths:
        style = Scene(p).meta.generator.get("style")
        if style in HELD_OUT_STYLES:
            raise SceneError(f"scene {p} is edge-sim style '{style}', which is held out of training and validation "
                             f"(the zero-shot test); train on suburban/urban scenes")


def load_scenes(paths: Sequence[os.PathLike | str], height: int, width: int, need_depth: bool, need_hvo: bool,
                progress: bool = True) -> SceneSet:
    """Several scenes concatenated (their frames are shuffled together during training)."""
    if not paths:
        raise SceneError("no scene given: pass at least one scene folder")
    sets = [load_scene(p, height, width, need_depth, need_hvo, progress) for p in paths]
    return SceneSet(
        rgb=np.concatenate([s.rgb for s in sets]),
        depth_m=np.concatenate([s.depth_m for s in sets]) if need_depth else None,
        hvo=np.concatenate([s.hvo for s in sets]) if need_hvo else None,
        scenes=[info for s in sets for info in s.scenes],
    )


def label_counts(hvo: np.ndarray) -> dict:
    """Pixel counts per HVO class (and ignored), for the training record."""
    values, counts = np.unique(hvo, return_counts=True)
    names = {0: "horizontal", 1: "vertical", 2: "other", HVO_IGNORE: "ignore"}
    return {names.get(int(v), str(int(v))): int(c) for v, c in zip(values, counts)}
