"""Bad input to the ``python -m edge_landing.benchmarks.*`` entry points: ONE stderr line naming the flag and
value, exit 2, no traceback, checked before the long work starts, and nothing already written is lost.
Every case here fails in the argument checks: none renders, loads a world or starts a process."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from edge_landing.benchmarks import (
    bench_fusion,
    bench_motion,
    bench_pipeline,
    bench_sim,
    check_shipped,
    closed_loop,
    frame_cost,
    fusion_ab,
    honest_report,
    landing_truth,
    lying_model,
    nadir_depth,
    narrow_obstacles,
    quant_variants,
    resolution_sweep,
    soak,
)
from tests.helpers import one_line_error, tiny_onnx_model

KEEP = "known text that must survive\n"


@pytest.fixture
def files(tmp_path):
    """A regular file (a folder cannot be made under it), a folder, a file with known text, a garbage .onnx."""
    (tmp_path / "regfile").write_text("x")
    (tmp_path / "adir").mkdir()
    (tmp_path / "keep.txt").write_text(KEEP)
    (tmp_path / "bad.onnx").write_text("not an onnx file")
    return tmp_path


def tiny_scene(path: Path, frames: int = 3) -> Path:
    """A scene folder with only rgb/ (what the --calib checks read): no scene.json, the camera from the image."""
    (path / "rgb").mkdir(parents=True)
    for i in range(frames):
        cv2.imwrite(str(path / "rgb" / f"{i:06d}.png"), np.full((16, 24, 3), 100 + i, np.uint8))
    return path


# --- narrow_obstacles ----------------------------------------------------------------------------------------

@pytest.mark.parametrize("argv,expected", [
    (["--heights", "5"], "--heights"),
    (["--heights", "40", "nan"], "--heights"),
    (["--box", "0", "0.3", "1.7"], "--box"),
    (["--spacing", "0.2"], "--spacing"),
    (["--frames", "1"], "--frames"),
    (["--material", "water"], "--material"),
    (["--top", "nothing"], "--top"),
    (["--colour", "2", "0", "0"], "--colour"),
    (["--size", "10", "480"], "--size W"),
    (["--json", "{t}/adir"], "--json"),
])
def test_narrow_obstacles(capsys, files, argv, expected):
    one_line_error(capsys, narrow_obstacles.main, [a.format(t=files) for a in argv], expected)


# --- lying_model ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("argv,expected", [
    (["--size", "0", "0"], "--size"),
    (["--seed", "-1"], "--seed"),
    (["--frames", "0"], "--frames"),
    (["--style", "bogus"], "--style"),
    (["--obstacle-height", "nan"], "--obstacle-height"),
    (["--json", "{t}/adir"], "--json"),
    (["--trace", "{t}/adir"], "--trace"),
    (["--json", "{t}/regfile/o.json"], "--json"),
    (["--json", "/proc/x/o.json"], "/proc/x"),
    (["--json", "{t}/o.json", "--trace", "{t}/o.json"], "--trace"),
    (["--pose-errors", "bogus"], "--pose-errors"),
    (["--error-seed", "-3"], "--error-seed"),
    (["--geometry-timing", "later"], "--geometry-timing"),
    (["--approach", "zigzag"], "--approach"),
])
def test_lying_model(capsys, files, argv, expected):
    one_line_error(capsys, lying_model.main, [a.format(t=files) for a in argv], expected)


def test_lying_model_keeps_an_existing_trace_when_the_json_cannot_be_written(capsys, files):
    one_line_error(capsys, lying_model.main, ["--trace", files / "keep.txt", "--json", "/proc/x/o.json"], "--json")
    assert (files / "keep.txt").read_text() == KEEP


# --- landing_truth -------------------------------------------------------------------------------------------

@pytest.mark.parametrize("argv,expected", [
    (["--clearance", "0"], "--clearance"), (["--clearance", "-1"], "--clearance"),
    (["--clearance", "nan"], "--clearance must be a finite number"), (["--clearance", "inf"], "got inf"),
    (["--step", "0"], "--step"), (["--step", "2"], "--step"), (["--step", "nan"], "--step"),
    (["--seed", "-1"], "--seed"), (["--style", "bogus"], "--style"),
])
def test_landing_truth(capsys, tmp_path, argv, expected):
    pytest.importorskip("embreex")
    one_line_error(capsys, landing_truth.main, [tmp_path / "t.jsonl", *argv], expected)


# --- closed_loop ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("argv,expected", [
    (["--seed", "-1"], "--seed"),
    (["--runs", "1", "--seeds", "5-2"], "--seeds"),
    (["--runs", "-1"], "--runs"),
    (["--edge-args", "'unterminated"], "--edge-args"),
    (["--sitl-cmd", "/nonexistent/sitl"], "--sitl-cmd"),
    (["--sitl-cmd", "echo {bogus}"], "--sitl-cmd"),
    (["--threads", "0"], "--threads"),
    (["--vehicle-radius", "-1"], "--vehicle-radius"),
    (["--vehicle-radius", "nan"], "--vehicle-radius"),
    (["--margin", "-1"], "--margin"),
    (["--hold", "-1"], "--hold"),
    (["--start", "nan", "0", "0"], "--start NORTH"),
    (["--start", "1e9", "0", "0"], "--start NORTH"),
    (["--start", "0", "0", "inf"], "--start YAW_DEG"),
    (["--style", "bogus"], "--style"),
    (["--altitude", "nan"], "--altitude"),
    (["--gimbal", "bogus"], "--gimbal"),
])
def test_closed_loop(capsys, tmp_path, argv, expected):
    one_line_error(capsys, closed_loop.main, ["--out", tmp_path / "loop", *argv], expected)
    assert not (tmp_path / "loop").exists()            # refused before the output folder was made


@pytest.mark.parametrize("out,expected", [("{t}/regfile", "not a folder"), ("/proc/x/cl", "/proc/x/cl")])
def test_closed_loop_output_folder(capsys, files, out, expected):
    one_line_error(capsys, closed_loop.main, ["--out", out.format(t=files)], "--out", expected)


# --- bench_fusion --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("argv,expected", [
    (["--frames", "x"], "--frames"), (["--mode", "bogus"], "--mode"), (["--bogus"], "--bogus"),
    (["--altitude", "nan"], "--altitude"), (["--altitude", "-5"], "--altitude"), (["--altitude", "0"], "--altitude"),
    (["--seed", "-1"], "--seed"), (["--working", "100000", "100000"], "--working"), (["--input", "0", "5"], "--input"),
])
def test_bench_fusion(capsys, argv, expected):
    one_line_error(capsys, bench_fusion.main, argv, expected)


# --- fusion_ab ----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("argv,expected", [
    ([], "--base"), (["--base", "{t}/missing"], "--base"), (["--base", "{t}/adir"], "--base"),
    (["--base", "{t}/adir", "--opencv-threads", "0"], "--opencv-threads"), (["--base", ".", "--frames", "5"], "--frames"),
    (["--base", ".", "--mode", "bogus"], "--mode"),
])
def test_fusion_ab(capsys, files, argv, expected):
    one_line_error(capsys, fusion_ab.main, [a.format(t=files) for a in argv], expected)


# --- bench_motion --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("argv,expected", [
    (["--json", "/proc/x/o.json"], "--json"), (["--json", "{t}/adir"], "--json"),
    (["--json", "{t}/regfile/o.json"], "--json"),
    (["--sizes", "-640x480"], "--sizes -640x480"), (["--sizes", "320x240", "-640x480"], "--sizes -640x480"),
    (["--threads", "0"], "--threads"), (["--fps", "nan"], "--fps"), (["--seed", "-1"], "--seed"),
    (["--frames", "150", "--warmup", "100"], "--frames + --warmup"),
    (["--geometry-timing", "later"], "--geometry-timing"),
])
def test_bench_motion(capsys, files, argv, expected):
    one_line_error(capsys, bench_motion.main, [a.format(t=files) for a in argv], expected)


# --- bench_pipeline ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("argv,expected", [
    (["--threads", "0"], "--threads"), (["--threads", "-3"], "--threads"),
    (["--out", "/proc/x/o.json"], "--out"), (["--out", "{t}/adir"], "--out"), (["--out", "{t}/regfile/o.json"], "--out"),
    (["--frames", "x"], "--frames"), (["--size", "0x0"], "--size 0x0"), (["--rounds", "0"], "--rounds"),
    (["--runtime", "bogus"], "--runtime"), (["--camera", "{t}/nowhere.mp4"], "--camera"),
    (["--model", "{t}/keep.txt", "--out", "{t}/keep.txt"], "--out"),
])
def test_bench_pipeline(capsys, files, argv, expected):
    one_line_error(capsys, bench_pipeline.main, [a.format(t=files) for a in argv], expected)
    assert (files / "keep.txt").read_text() == KEEP


# --- nadir_depth ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("argv,expected", [
    (["--seed", "-1"], "--seed"), (["--out", "/proc/x/o.json"], "--out"), (["--out", "{t}/adir"], "--out"),
    (["--model", "{t}/nowhere.onnx"], "--model"), (["--model", "{t}/bad.onnx"], "--model"),
])
def test_nadir_depth(capsys, files, argv, expected):
    one_line_error(capsys, nadir_depth.main, [a.format(t=files) for a in argv], expected)


# --- quant_variants ------------------------------------------------------------------------------------------

def test_quant_variants_checks_calib_and_counts_before_any_variant(capsys, files):
    out = files / "qv"
    out.mkdir()
    (out / "variants.json").write_text(KEEP)
    model = tiny_onnx_model(files / "m.onnx")
    scene = tiny_scene(files / "scene")
    base = [model, "--out", out]
    one_line_error(capsys, quant_variants.main, base + ["--calib", "/nonexistent", "--frames", "1", "--eval-frames",
                                                        "1", "--iterations", "1"], "--calib", "/nonexistent")
    for flag, value in (("--frames", "0"), ("--eval-frames", "0"), ("--iterations", "0"), ("--iterations", "-1"),
                        ("--threads", "-1"), ("--threads", "0")):
        one_line_error(capsys, quant_variants.main, base + ["--calib", scene, flag, value], flag)
    one_line_error(capsys, quant_variants.main, base + ["--calib", scene, "--frames", "5"], "--calib")  # 3 frames
    one_line_error(capsys, quant_variants.main, [files / "bad.onnx", "--out", out, "--calib", scene, "--frames", "1",
                                                 "--eval-frames", "1"], "bad.onnx")
    assert (out / "variants.json").read_text() == KEEP and sorted(p.name for p in out.iterdir()) == ["variants.json"]


# --- soak ----------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("argv,expected", [
    (["--minutes", "nan"], "--minutes"), (["--minutes", "0"], "--minutes"), (["--minutes", "x"], "--minutes"),
    (["--fps", "nan"], "--fps"), (["--sample", "-1"], "--sample"),
    (["--model", "/nonexistent.onnx"], "--model"), (["--model", "{t}/bad.onnx"], "--model"),
    (["--model", "{t}/adir"], "--model"),
    (["--json", "/proc/x/s.json"], "--json"), (["--json", "{t}/adir"], "--json"),
])
def test_soak(capsys, files, argv, expected):
    one_line_error(capsys, soak.main, [a.format(t=files) for a in argv], expected)


# --- check_shipped -------------------------------------------------------------------------------------------

@pytest.mark.parametrize("argv,expected", [
    (["--seeds", "bogus"], "--seeds"), (["--models", "/nonexistent.onnx"], "--models"),
    (["--models", "{t}/bad.onnx"], "--models"), (["--models", "{t}/adir"], "--models"),
    (["--frames", "0"], "--frames"), (["--frames", "x"], "--frames"),
    (["--models", "{t}/m.onnx", "--out", "{t}/regfile"], "--out"),
    (["--models", "{t}/m.onnx", "--out", "/proc/x/cs"], "--out"),
])
def test_check_shipped(capsys, files, argv, expected):
    tiny_onnx_model(files / "m.onnx")
    one_line_error(capsys, check_shipped.main, [a.format(t=files) for a in argv], expected)


def test_check_shipped_a_failed_render_is_one_line(capsys, files, monkeypatch):
    class Failed:
        returncode, stderr = 2, "INFO something\nedge-sim: error: it went wrong\n"

    monkeypatch.setattr(check_shipped.subprocess, "run", lambda *a, **k: Failed())
    one_line_error(capsys, check_shipped.main, ["--models", tiny_onnx_model(files / "m.onnx"), "--out", files / "cs",
                                                "--seeds", "urban:3"], "it went wrong")


# --- bench_sim -----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("argv,expected", [
    (["--frames", "0"], "--frames"), (["--height", "0"], "--height"), (["--style", "bogus"], "--style"),
    (["--shadow-stride", "0"], "--shadow-stride"), (["--seed", "-1"], "--seed"), (["--warmup", "-1"], "--warmup"),
])
def test_bench_sim(capsys, argv, expected):
    pytest.importorskip("embreex")
    one_line_error(capsys, bench_sim.main, argv, expected)


# --- frame_cost ----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("argv,expected", [
    (["--json", "/proc/x/o.json"], "--json"), (["--json", "{t}/adir"], "--json"),
    (["--sizes", "-640x480"], "--sizes -640x480"), (["--threads", "0"], "--threads"),
    (["--iterations", "0"], "--iterations"),
])
def test_frame_cost(capsys, files, argv, expected):
    one_line_error(capsys, frame_cost.main, [a.format(t=files) for a in argv], expected)


# --- honest_report -------------------------------------------------------------------------------------------

@pytest.mark.parametrize("argv,expected", [
    (["--out", "{t}/regfile"], "--out"), (["--out", "/proc/x/hr"], "--out"),
    (["--max-depth", "nan"], "--max-depth"), (["--max-depth", "0"], "--max-depth"),
    (["--scene", "bogus:1"], "--scene"), (["--frames", "0"], "--frames"), (["--model", "{t}/bad.onnx"], "--model"),
])
def test_honest_report(capsys, files, argv, expected):
    one_line_error(capsys, honest_report.main, ["--out", files / "hr", "--scene", "suburban:1",
                                                *[a.format(t=files) for a in argv]], expected)
    assert not (files / "hr").exists()                 # nothing rendered into --out


# --- resolution_sweep ----------------------------------------------------------------------------------------

@pytest.mark.parametrize("argv,expected", [
    (["--seeds", "-1"], "--seeds"), (["--styles", "bogus"], "--styles"), (["--sizes", "-640x480"], "--sizes"),
    (["--json", "/proc/x/o.json"], "--json"), (["--out", "{t}/regfile"], "--out"),
])
def test_resolution_sweep(capsys, files, argv, expected):
    one_line_error(capsys, resolution_sweep.main, ["--out", files / "cache", *[a.format(t=files) for a in argv]],
                   expected)
