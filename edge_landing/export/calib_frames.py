"""The frames a static quantization calibrates on and the frames it is checked on (ARCHITECTURE.md §9): each
scene's first frames calibrate, its next ones are held out, shared evenly between scenes and interleaved; and
ONNX Runtime's calibration reader over them, preprocessed exactly as the runtime does."""
from __future__ import annotations

from typing import Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np

from edge_landing.evaluation.scene import Scene
from edge_landing.runtime.core.errors import InputError, SceneError

from .quant_check import FrameRef

__all__ = ["SceneCalibrationReader", "split_frames"]


class SceneCalibrationReader:
    """ONNX Runtime's one-method reader over scene frames, preprocessed exactly as the runtime does."""

    def __init__(self, frames: Sequence[FrameRef], prepare: Callable[[np.ndarray], np.ndarray],
                 input_name: str, progress: bool = True):
        self.frames, self.prepare, self.input_name = list(frames), prepare, input_name
        self.progress = progress
        self.rewind()

    def rewind(self) -> None:
        from tqdm import tqdm

        self._iter = iter(tqdm(self.frames, desc="calibrating", unit="frame", disable=not self.progress,
                               leave=False))

    def get_next(self) -> Optional[Dict[str, np.ndarray]]:
        ref = next(self._iter, None)
        if ref is None:
            return None
        scene, fid = ref
        return {self.input_name: self.prepare(scene.read_rgb(fid))}


def _shares(total: int, parts: int) -> List[int]:
    return [total // parts + (1 if i < total % parts else 0) for i in range(parts)]


def split_frames(scenes: Sequence[Scene], calib_frames: int, eval_frames: int) -> Tuple[List[FrameRef], List[FrameRef]]:
    """Each scene's first frames calibrate and its next ones are held out; ``calib_frames`` and ``eval_frames``
    are totals shared evenly between the scenes, and the frames are interleaved (scene 1, scene 2, ...)."""
    if calib_frames < 1 or eval_frames < 1:
        raise InputError(f"--frames and --eval-frames must be at least 1, got {calib_frames} and {eval_frames}")
    if calib_frames < len(scenes) or eval_frames < len(scenes):
        raise InputError(f"--frames {calib_frames} / --eval-frames {eval_frames} cannot cover {len(scenes)} scenes; "
                         f"expected at least one of each per scene")
    calib, held = [], []
    for scene, n_cal, n_eval in zip(scenes, _shares(calib_frames, len(scenes)), _shares(eval_frames, len(scenes))):
        if len(scene) <= n_cal:
            raise SceneError(f"scene {scene.path} has {len(scene)} frame(s); calibrating on {n_cal} of them needs "
                             f"at least {n_cal + 1} so that some are held out for the accuracy check (lower --frames, "
                             f"e.g. --frames {max(1, len(scene) * 2 // 3 * len(scenes))}, or make a longer scene with "
                             f"edge-sim --frames)")
        calib.append([(scene, f) for f in scene.frame_ids[:n_cal]])
        held.append([(scene, f) for f in scene.frame_ids[n_cal:n_cal + n_eval]])
    return _interleave(calib), _interleave(held)


def _interleave(groups: List[List[FrameRef]]) -> List[FrameRef]:
    out: List[FrameRef] = []
    for i in range(max(len(g) for g in groups)):
        out.extend(g[i] for g in groups if i < len(g))
    return out
