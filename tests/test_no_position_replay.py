"""edge-run on a drone without a position (no GPS): a recorded flight replayed with a telemetry log of attitude
and rangefinder only. Geometry places the frames by the images; continuity (ARCHITECTURE.md §12) commits a spot in
the images' frame and holds it; every target points at ground-truth safe ground (ray casting) and none carries a
local NED position (the odometry's frame is not the autopilot's)."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from edge_landing.cli.run import main
from edge_landing.runtime.io.mavlink_conn import load_mavutil
from edge_landing.runtime.pipeline.trust import HELD
from tests.run_helpers import read_decisions

sim = pytest.importorskip("edge_landing.sim", reason="the sim extra (embreex) renders the test world")
from edge_landing.benchmarks.flat_model import flat_ground_model  # noqa: E402
from edge_landing.benchmarks.landing_truth import TruthConfig, check_target  # noqa: E402
from tests.test_motion import FPS, _flat_world, _frames  # noqa: E402
from tests.test_tlog import hand_made_log  # noqa: E402

AGL_M = 25.0
LEAD_S = 1.0          # the log starts this long before the first frame


def _path() -> list:
    """The low pass of tests/test_image_motion.py: 0.3 m per frame north, weaving east, 25 m up."""
    return [(-14.0 + 0.3 * k, -3.0 + 2.0 * math.sin(0.2 * k), -AGL_M) for k in range(60)]


def test_edge_run_without_a_position_holds_a_spot_in_the_images_frame(tmp_path):
    cars = [[n, e, 2.2, 0.9, 1.5] for n in np.arange(15.0, 45.0, 5.0) for e in (-12.0, -6.0, 0.0, 6.0)]
    world = _flat_world(cars + [[30.0, 18.0, 6.0, 5.0, 6.0]])
    folder = tmp_path / "frames"
    folder.mkdir()
    states = []
    for k, _t, r, state in _frames(world, _path()):
        cv2.imwrite(str(folder / f"{k:04d}.png"), cv2.cvtColor(r.rgb, cv2.COLOR_RGB2BGR))
        states.append(state)
    m = load_mavutil().mavlink       # an autopilot without GPS: its estimator has attitude and height only
    tlog = hand_made_log(tmp_path / "nogps.tlog", m.EKF_ATTITUDE | m.EKF_POS_VERT_ABS | m.EKF_POS_VERT_AGL,
                         end_s=LEAD_S + len(states) / FPS + 1.0, agl_m=AGL_M, position=False)
    model = flat_ground_model(tmp_path / "flat.onnx", agl_m=AGL_M)      # the lying network: flat ground everywhere
    log = tmp_path / "run.jsonl"
    assert main(["--camera", str(folder), "--fps", f"{FPS:g}", "--model", str(model), "--tlog", str(tlog),
                 "--tlog-video-start", f"+{LEAD_S:g}", "--log", str(log)]) == 0
    decisions = read_decisions(log)
    assert len(decisions) == len(states) and all(d["telemetry"] for d in decisions)
    valid = [d for d in decisions if d["valid"]]
    held = [d for d in valid if d["reason"].startswith(HELD)]
    assert len(valid) >= 10 and held, (len(valid), len(held), [d["reason"] for d in decisions[-5:]])
    assert any(d["committed_odometry_m"] for d in decisions) and not any(d["committed_ned_m"] for d in decisions)
    truth = TruthConfig(log="", clearance_m=2.0)
    for d in valid:
        assert d["ned_m"] is None, d
        state = states[d["frame"]]
        ned = state.position_ned_m + state.attitude.ned_from_body() @ np.asarray(d["body_frd_m"])
        ok, why = check_target(world, float(ned[0]), float(ned[1]), truth)
        assert ok, (d["frame"], d["reason"], why)
