"""edge-run end to end: real ONNX Runtime, real video files, real overlay video, SIGINT, bad input."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from edge_landing.cli.run import main
from edge_landing.runtime.perception.calibration_file import SceneCalibration
from edge_landing.runtime.perception.contract import Task
from edge_landing.runtime.perception.inference import file_sha256
from tests.helpers import tiny_onnx_model
from tests.run_helpers import flat_assets, flat_ground_model, read_decisions, write_video

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def assets(tmp_path_factory):
    return flat_assets(tmp_path_factory.mktemp("run"), 10.0, frames=10)


def test_video_run_logs_every_decision_records_overlay_and_prints_summary(assets, tmp_path, capsys):
    log_path, rec = tmp_path / "targets.jsonl", tmp_path / "overlay.mp4"
    assert main(["--camera", assets["video"], "--model", assets["model"], "--log", str(log_path),
                 "--record", str(rec), "--vehicle-radius", "0.5", "--margin", "0.5", "--allow-unconfirmed"]) == 0
    out = capsys.readouterr().out
    assert "pipeline images/s" in out and "model-only images/s" in out and "stopped by end of input" in out
    decisions = read_decisions(log_path)
    assert [d["frame"] for d in decisions] == list(range(10))
    assert all(d["valid"] and d["reason"] == "ok" and d["clearance_m"] >= 1.0 for d in decisions)
    assert all(d["evidence"].startswith("network only") for d in decisions)  # said in the log (§11)
    assert all(d["body_frd_m"][0] > 0 and abs(d["body_frd_m"][2] - 10.0) < 0.3 for d in decisions)
    cap = cv2.VideoCapture(str(rec))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 10
    ok, img = cap.read()
    assert ok and img.shape == (96, 128, 3)


def test_max_frames_and_calibration_scale(assets, tmp_path):
    model = flat_ground_model(tmp_path / "half.onnx", agl_m=5.0)  # predicts half the true distance
    cal = SceneCalibration(2.0, 0.01, 1.98, 2.02, 5, 5, file_sha256(model), str(model), "scene", "now", 0.5, 200.0)
    cal_path = cal.save(tmp_path / "edge_landing.calibration.json")
    log_path = tmp_path / "t.jsonl"
    assert main(["--camera", assets["video"], "--model", str(model), "--calibration", str(cal_path),
                 "--max-frames", "4", "--log", str(log_path), "--allow-unconfirmed"]) == 0
    decisions = read_decisions(log_path)
    assert len(decisions) == 4
    assert all(d["scale"] == 2.0 and d["scale_source"] == "calibration" for d in decisions)
    assert all(abs(d["body_frd_m"][2] - 10.0) < 0.3 for d in decisions)


def test_depth_and_hvo_model_pair(assets, tmp_path):
    depth = tiny_onnx_model(tmp_path / "d.onnx", task=Task.DEPTH, height=24, width=32)
    hvo = tiny_onnx_model(tmp_path / "h.onnx", task=Task.HVO, height=12, width=16)
    log_path = tmp_path / "t.jsonl"
    assert main(["--camera", assets["video"], "--depth-model", str(depth), "--hvo-model", str(hvo),
                 "--max-frames", "3", "--log", str(log_path)]) == 0
    decisions = read_decisions(log_path)
    assert len(decisions) == 3 and all(d["reason"] for d in decisions)  # a decision and its reason, every frame


def test_truncated_video_ends_cleanly(assets, tmp_path, capsys):
    path = write_video(tmp_path / "t.avi", 30)
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    assert main(["--camera", str(path), "--model", assets["model"]]) == 0
    captured = capsys.readouterr()
    assert "stopped by end of input" in captured.out


@pytest.mark.parametrize("args, message", [
    (["--camera", "/dev/video93"], "/dev/video93 not found"),
    (["--camera", "/nonexistent/flight.mp4"], "video file /nonexistent/flight.mp4 does not exist"),
    (["--camera", "/nonexistent/frames/*.png"], "no images found at /nonexistent/frames/*.png"),
    (["--model", "missing.onnx"], "does not exist"),
    (["--depth-model", "x.onnx"], "not both"),
    (["--autopilot", "betaflight"], "ardupilot, px4"),
    (["--mav", "carrier-pigeon"], "unsupported MAVLink connection"),
    (["--vehicle-radius", "-1"], "--vehicle-radius"),
    (["--mav", "/dev/ttyUSB0,fast"], "bad baud rate"),
    (["--record", "/nonexistent/dir/o.mp4"], "does not exist"),
    (["--record", "o.txt"], "needs one of the suffixes"),
    (["--hold", "nan"], "--hold must be a finite number"),
    (["--margin", "inf"], "--margin must be a finite number"),
    (["--duration", "nan"], "--duration"),
    (["--mount-pitch", "1e9"], "--mount-pitch"),
    (["--obstacle-height", "nan"], "--obstacle-height"),
    (["--fps", "nan"], "--fps"),
    (["--threads", "99999999999999999999"], "--threads must be between 1 and 256"),
    (["--mav-sysid", "999", "--mav", "udpout:127.0.0.1:9"], "--mav-sysid must be a MAVLink id"),
    (["--mav-compid", "0"], "--mav-compid"),
    (["--log", "/proc/version"], "cannot write --log /proc/version"),
    (["--camera", "sim:bogusstyle"], "unsupported world style 'bogusstyle'"),
    (["--camera", "sim-follow:bogusstyle:3@udpin:127.0.0.1:9"], "unsupported world style 'bogusstyle'"),
    (["--mav", "udpout:127.0.0.1:99999"], "port 99999 is not in 1-65535"),
    (["--mav", "udpout:127.0.0.1:9", "--mav-key", "/nonexistent/key"], "signing key file /nonexistent/key"),
])
def test_bad_input_is_one_line_and_exit_2(assets, args, message, capsys):
    argv = ["--camera", assets["video"], "--model", assets["model"]]
    argv += args
    assert main(argv) == 2
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err
    if "--mav" in args or "--mav-key" in args or "--camera" in args:   # refused before the model is chosen and loaded
        assert "edge-run: model" not in captured.out, captured.out


def test_model_without_contract_is_one_line(assets, tmp_path, capsys):
    bare = tiny_onnx_model(tmp_path / "bare.onnx", contract=False)
    assert main(["--camera", assets["video"], "--model", str(bare)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no model contract" in err[0]


@pytest.mark.parametrize("sig, said", [(signal.SIGINT, "Ctrl-C"), (signal.SIGTERM, "SIGTERM")])
def test_a_stop_signal_exits_cleanly_with_summary_flushed_log_and_playable_overlay(assets, tmp_path, sig, said):
    """Ctrl-C, or SIGTERM as systemd sends it to a service: the run ends as at the end of its input."""
    log_path, rec = tmp_path / "t.jsonl", tmp_path / "overlay.mp4"
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.Popen([sys.executable, "-m", "edge_landing.cli.run", "--camera", assets["video"], "--loop",
                             "--model", assets["model"], "--log", str(log_path), "--record", str(rec),
                             "--threads", "1"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=str(tmp_path))
    try:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and (not log_path.exists() or log_path.stat().st_size < 2000):
            time.sleep(0.1)
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    assert f"stopped by {said}" in out and "pipeline images/s" in out
    assert cv2.VideoCapture(str(rec)).read()[0]          # the overlay's container was closed: it plays
    lines = log_path.read_text().splitlines()
    assert "run" in json.loads(lines[0])  # the run record, then one line per frame
    lines = lines[1:]
    assert len(lines) >= 5 and all(json.loads(line)["frame"] >= 0 for line in lines)  # every line complete


@pytest.mark.slow
def test_default_run_flies_the_synthetic_flight_with_the_shipped_model(tmp_path, capsys):
    log_path = tmp_path / "t.jsonl"
    assert main(["--max-frames", "6", "--log", str(log_path)]) == 0  # no camera, no model: sim + edgenet
    out = capsys.readouterr().out
    assert "edge-run: sim -> edgenet" in out and "pipeline images/s" in out
    decisions = read_decisions(log_path)
    assert len(decisions) == 6 and all(d["telemetry"] and d["agl_m"] > 0 for d in decisions)


def test_poses_replay_gives_ned_targets_for_a_recorded_flight(assets, tmp_path):
    """--poses: a recorded flight's poses.csv is its telemetry, one row per frame (vehicle 10 m above ground)."""
    poses = tmp_path / "poses.csv"
    rows = ["frame,t,north,east,down,roll,pitch,yaw,agl"]
    rows += [f"{k},{k / 10:.1f},{100 + k},50,-10,0,0,0,10" for k in range(10)]
    poses.write_text("\n".join(rows) + "\n")
    log_path = tmp_path / "t.jsonl"
    assert main(["--camera", assets["video"], "--model", assets["model"], "--poses", str(poses),
                 "--vehicle-radius", "0.5", "--margin", "0.5", "--log", str(log_path), "--allow-unconfirmed"]) == 0
    decisions = read_decisions(log_path)
    assert len(decisions) == 10 and all(d["valid"] for d in decisions)
    for d in decisions:
        north, east, down = d["ned_m"]
        x, y, z = d["body_frd_m"]
        assert abs(down) < 0.3                                  # on the ground (down = 0 in local NED)
        # level flight, yaw 0: local NED = the replayed vehicle position of that frame + the body vector
        np.testing.assert_allclose([north, east, down], [100 + d["frame"] + x, 50 + y, -10 + z], atol=0.05)
        assert d["scale_source"].startswith("altitude")         # the replayed height above ground gave the scale


def test_poses_file_errors_are_one_line(assets, tmp_path, capsys):
    bad = tmp_path / "poses.csv"
    bad.write_text("frame,t,north\n0,0,1\n")
    assert main(["--camera", assets["video"], "--model", assets["model"], "--poses", str(bad)]) == 2
    assert "missing column(s)" in capsys.readouterr().err


def test_outputs_never_overwrite_inputs(assets, tmp_path, capsys):
    """--log or --record naming the model, the poses or each other is refused before anything is written."""
    model = tmp_path / "copy.onnx"
    model.write_bytes(Path(assets["model"]).read_bytes())
    before = model.read_bytes()
    assert main(["--camera", assets["video"], "--model", str(model), "--log", str(model)]) == 2
    assert "is the same file as --model" in capsys.readouterr().err
    assert model.read_bytes() == before
    log = tmp_path / "run.mp4"
    assert main(["--camera", assets["video"], "--model", str(model), "--log", str(log), "--record", str(log)]) == 2
    assert "--record" in capsys.readouterr().err and not log.exists()


def test_a_poses_file_without_rows_is_refused(assets, tmp_path, capsys):
    empty = tmp_path / "poses.csv"
    empty.write_text("frame,t,north,east,down,roll,pitch,yaw,agl\n")
    assert main(["--camera", assets["video"], "--model", assets["model"], "--poses", str(empty)]) == 2
    assert "has no rows" in capsys.readouterr().err
