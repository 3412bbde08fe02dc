"""The per-scene depth-scale file (ARCHITECTURE.md §7): ``scene/calibration.json``, written by ``edge-calibrate``.

It is kept outside the model and names the model's sha256, so a scale is never applied silently to a
different network. Reading it is all the drone needs::

    scale = load_calibration("scene/calibration.json", model_sha256=model.sha256)
    pred = model.predict(rgb, scale=scale)
"""
from __future__ import annotations

import json
import logging
import math
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Dict, Mapping, Optional

from edge_landing.runtime.core.errors import InputError

log = logging.getLogger(__name__)
CALIBRATION_FORMAT = "edge-landing/calibration/1"
# Above this relative spread (MAD / scale) one scale does not describe the scene's frames well.
UNRELIABLE_SPREAD = 0.1


@dataclass(frozen=True)
class SceneCalibration:
    """A scene's median scale and its spread over frames (ratios are median(gt) / median(pred) per frame)."""

    scale: float
    mad: float
    min_ratio: float
    max_ratio: float
    frames_used: int
    frames_total: int
    model_sha256: str
    model_path: str
    scene_path: str
    created_utc: str
    min_depth_m: float
    max_depth_m: Optional[float]       # None: no upper bound (JSON has no infinity)
    ratios: Dict[str, float] = field(default_factory=dict)

    @property
    def relative_spread(self) -> float:
        return self.mad / self.scale if self.scale > 0 else math.inf

    @property
    def reliable(self) -> bool:
        return self.relative_spread <= UNRELIABLE_SPREAD

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d.update(format=CALIBRATION_FORMAT, relative_spread=self.relative_spread, reliable=self.reliable,
                 method="scale = median over frames of median(gt)/median(pred) over valid pixels "
                        "(Monodepth2 median scaling); mad = median |ratio - scale|")
        return d

    @staticmethod
    def from_json(d: Mapping[str, Any]) -> SceneCalibration:
        names = SceneCalibration.__dataclass_fields__
        return SceneCalibration(**{k: d[k] for k in names if k in d})

    def save(self, path: os.PathLike[str] | str) -> Path:
        path = Path(path)
        tmp = path.with_suffix(path.suffix + ".tmp")
        try:
            tmp.write_text(json.dumps(self.to_json(), indent=2, sort_keys=True))
            os.replace(tmp, path)   # never leave a half-written calibration behind
        except OSError as exc:
            raise InputError(f"cannot write calibration file {path}: {exc.strerror}") from None
        return path


def read_calibration(path: os.PathLike[str] | str) -> SceneCalibration:
    """Parse and validate a calibration file; any problem is one InputError naming the file."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"calibration file {path} does not exist (make one with: edge-calibrate SCENE)")
    try:
        data = json.loads(path.read_text())
        cal = SceneCalibration.from_json(data)
    except json.JSONDecodeError as exc:
        raise InputError(f"calibration file {path} is not valid JSON ({exc})") from None
    except TypeError as exc:
        raise InputError(f"calibration file {path} is missing fields ({exc}); expected the output of "
                         f"edge-calibrate") from None
    if not (isinstance(cal.scale, (int, float)) and math.isfinite(cal.scale) and cal.scale > 0):
        raise InputError(f"calibration file {path}: scale {cal.scale!r} is not a positive finite number")
    return cal


def load_calibration(path: os.PathLike[str] | str, model_sha256: Optional[str] = None, strict: bool = False) -> float:
    """The scale stored in ``path``. When ``model_sha256`` is given and differs from the file's model,
    warn (or raise InputError when ``strict``): the scale belongs to another network."""
    cal = read_calibration(path)
    if model_sha256 is not None and cal.model_sha256 != model_sha256:
        msg = (f"calibration file {path} was made for model {cal.model_sha256[:12]}… ({cal.model_path}), "
               f"not for this model {model_sha256[:12]}…; its scale {cal.scale:.4g} may be wrong")
        if strict:
            raise InputError(msg + " (re-run edge-calibrate with this model)")
        log.warning(msg)
    if not cal.reliable:
        log.warning("calibration file %s: the frames disagree (MAD/scale = %.3f > %.2f); the scale is unreliable",
                    path, cal.relative_spread, UNRELIABLE_SPREAD)
    return float(cal.scale)
