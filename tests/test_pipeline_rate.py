"""PipelineOptions.fusion_max_hz (edge-run --fusion-hz): every frame is inferred, only frames at most that often
are fused, on the frames' capture clock. Real Grabber, real ONNX Runtime session, real fusion."""
from __future__ import annotations

import io
import json
from typing import Optional

import numpy as np
import pytest

from edge_landing.cli.run import config_from_args
from edge_landing.runtime.core.camera import Intrinsics, Mount
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.fusion.fuser import FusionConfig, LandingFuser
from edge_landing.runtime.io.grabber import Grabber
from edge_landing.runtime.io.sources import Reader, SourceConfig, SourceKind
from edge_landing.runtime.perception.inference import OnnxModel
from edge_landing.runtime.perception.scale import AltitudeScaleEstimator
from edge_landing.runtime.pipeline import JointInference, Pipeline, PipelineOptions, ScaleStage
from tests.run_helpers import flat_ground_model

CAMERA_HZ = 50.0


class StampedReader(Reader):
    """Grey frames stamped as a 50 Hz camera would stamp them."""

    name = "stamped"

    def __init__(self, frames: int):
        self.frames, self.i = frames, 0

    def read(self) -> Optional[np.ndarray]:
        if self.i >= self.frames:
            return None
        self.capture_time_s = 100.0 + self.i / CAMERA_HZ
        self.i += 1
        return np.full((48, 64, 3), 128, np.uint8)


def run_pipeline(tmp_path, fusion_hz: float, frames: int = 20):
    model = JointInference(OnnxModel.load(str(flat_ground_model(tmp_path / "flat.onnx")), threads=1))
    grabber = Grabber(SourceConfig("stamped", SourceKind.FILE), opener=lambda c: StampedReader(frames)).start()
    intrinsics, mount = Intrinsics.from_hfov(64, 48), Mount()
    log = io.StringIO()
    pipe = Pipeline(grabber, model, ScaleStage(None, AltitudeScaleEstimator(), intrinsics, mount),
                    LandingFuser(FusionConfig(), intrinsics, mount).fuse,
                    options=PipelineOptions(status_period_s=1e9, fusion_max_hz=fusion_hz), decision_log=log,
                    out=io.StringIO())
    try:
        summary = pipe.run()
    finally:
        grabber.stop()
    return summary, [json.loads(line) for line in log.getvalue().splitlines()]


def test_every_frame_is_fused_by_default(tmp_path):
    summary, decisions = run_pipeline(tmp_path, 0.0)
    assert summary.frames == 20 and summary.not_fused == 0
    assert [d["frame"] for d in decisions] == list(range(20))


def test_a_fusion_cap_fuses_at_that_rate_on_the_capture_clock_and_infers_every_frame(tmp_path):
    summary, decisions = run_pipeline(tmp_path, 10.0)
    assert summary.frames == 20 and summary.times.count("inference") == 20
    assert [d["frame"] for d in decisions] == [0, 5, 10, 15]   # 50 Hz camera, 10 Hz fusion
    assert summary.not_fused == 16 and "16 inferred but not fused" in summary.table()


@pytest.mark.parametrize("hz", ["5", "-1", "2000"])
def test_fusion_rate_below_the_autopilots_need_is_refused(hz):
    with pytest.raises(InputError, match="--fusion-hz"):
        config_from_args(["--fusion-hz", hz])
