"""Bad input to every CLI ends in ONE stderr line and exit 2, before any heavy work (found by a user-style pass)."""
import numpy as np
import pytest

from edge_landing.benchmarks.cli import main as bench_main
from edge_landing.calibration.cli import main as calibrate_main
from edge_landing.cli.eval_cli import main as eval_main
from edge_landing.export.cli import main as export_main
from edge_landing.export.quantize_cli import main as quantize_main
from edge_landing.export.train_cli import main as train_main
from edge_landing.runtime.core.errors import ContractError
from edge_landing.runtime.perception.contract import Task
from edge_landing.runtime.perception.inference import OnnxModel
from edge_landing.runtime.pipeline import JointInference, PairInference
from edge_landing.sim.cli import main as sim_main
from tests.helpers import one_line_error, tiny_onnx_model
from tests.test_train import write_tiny_scene


@pytest.mark.parametrize("main,argv,expected", [
    (eval_main, ["m.onnx", "scene", "--averaging", "bogus"], "invalid choice: 'bogus'"),
    (calibrate_main, ["scene", "--bogus"], "unrecognized arguments: --bogus"),
    (export_main, ["--arch", "resnet", "--out", "x.onnx"], "invalid choice: 'resnet'"),
    (quantize_main, ["m.onnx"], "required: --calib, --out"),
    (train_main, ["--arch", "edgenet"], "required: --train, --out"),
    (bench_main, ["--quick", "--bogus"], "unrecognized arguments"),
])
def test_argument_errors_are_one_line_not_a_usage_dump(capsys, main, argv, expected):
    err = one_line_error(capsys, main, argv, expected)
    assert "--help" in err and "usage:" not in err


def test_numbers_out_of_range_are_refused(tmp_path, capsys):
    one_line_error(capsys, sim_main, [str(tmp_path / "s"), "--frames", "1", "--seed", "-1"], "--seed")
    assert not (tmp_path / "s").exists()
    model = tiny_onnx_model(tmp_path / "m.onnx")
    one_line_error(capsys, quantize_main, [str(model), "--calib", str(tmp_path), "--out", str(tmp_path / "q.onnx"),
                                           "--threads", "0"], "--threads must be between 1 and 256")
    for flag, value in (("--iterations", "0"), ("--iterations", "-1"), ("--max-seconds", "0"), ("--height", "0")):
        one_line_error(capsys, bench_main, ["--quick", "--models", "safeuav-small", flag, value], flag)
    one_line_error(capsys, bench_main, ["--quick", "--calib", str(tmp_path / "nowhere")], "does not exist")
    from edge_landing.benchmarks.bench_motion import main as motion_main
    for flag, value in (("--fps", "0"), ("--opencv-threads", "0"), ("--frames", "0")):
        one_line_error(capsys, motion_main, ["--sizes", "640x480", flag, value], flag)   # before any render


def test_train_refuses_bad_sizes_steps_output_and_resume(tmp_path, capsys):
    base = ["--arch", "edgenet", "--train", str(tmp_path / "nowhere"), "--out", str(tmp_path / "o")]
    one_line_error(capsys, train_main, base + ["--max-steps", "0"], "--max-steps must be at least 1")
    one_line_error(capsys, train_main, base + ["--height", "-120", "--width", "160"], "too small")
    one_line_error(capsys, train_main, base[:-1] + ["/proc/x/out"], "cannot create the output folder")
    bad = tmp_path / "bad.pth"
    bad.write_bytes(b"not a checkpoint")
    scene = write_tiny_scene(tmp_path / "scene", frames=2)
    one_line_error(capsys, train_main, ["--arch", "edgenet", "--train", str(scene), "--out", str(tmp_path / "o"),
                                        "--height", "32", "--width", "32", "--resume", str(bad), "--no-progress"],
                   "not a PyTorch checkpoint")


def test_export_to_an_impossible_folder_is_one_line(capsys):
    one_line_error(capsys, export_main, ["--arch", "safeuav-small", "--out", "/proc/x/m.onnx", "--quiet"],
                   "cannot create the output folder /proc/x")


def test_a_folder_given_as_model_says_so(tmp_path):
    with pytest.raises(ContractError, match="is a folder, not a file"):
        OnnxModel.load(tmp_path)


def test_edge_run_refuses_models_without_the_heads_it_needs(tmp_path):
    hvo = OnnxModel.load(tiny_onnx_model(tmp_path / "h.onnx", task=Task.HVO), threads=1)
    depth = OnnxModel.load(tiny_onnx_model(tmp_path / "d.onnx", task=Task.DEPTH), threads=1)
    with pytest.raises(ContractError, match="no depth head"):
        JointInference(hvo)
    with pytest.raises(ContractError, match="no depth head"):
        PairInference(hvo, hvo)
    with pytest.raises(ContractError, match="no hvo head"):
        PairInference(depth, depth)
    assert PairInference(depth, hvo).name == "d.onnx + h.onnx"
    assert JointInference(depth).model is depth
    assert np.isfinite(depth.contract.depth.max_depth)


def test_train_does_not_overwrite_an_earlier_run_unless_asked(tmp_path, capsys):
    out = tmp_path / "run"
    out.mkdir()
    (out / "last.pth").write_bytes(b"an earlier run")
    scene = write_tiny_scene(tmp_path / "scene", frames=2)
    one_line_error(capsys, train_main, ["--arch", "edgenet", "--train", str(scene), "--out", str(out),
                                        "--height", "32", "--width", "32", "--no-progress"], "already holds a training run")
    assert (out / "last.pth").read_bytes() == b"an earlier run"


@pytest.mark.parametrize("module,argv", [
    ("edge_landing.export.train_cli", ["--arch", "edgenet", "--train", "scenes/a", "--out", "runs/a"]),
    ("edge_landing.export.cli", ["--arch", "edgenet", "--out", "m.onnx"]),
])
def test_missing_export_extra_is_one_line(module, argv):
    """Without torch (the [export] extra) the command names the extra to install instead of a traceback."""
    import subprocess
    import sys

    code = ("import sys; sys.modules['torch'] = None; import importlib; "
            f"sys.exit(importlib.import_module('{module}').main({argv!r}))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    err = done.stderr.strip().splitlines()
    assert done.returncode == 2 and len(err) == 1, done.stderr
    assert "pip install 'edge-landing[export]'" in err[0]


def test_a_nan_tolerance_cannot_switch_the_int8_gate_off(tmp_path, capsys):
    model = tiny_onnx_model(tmp_path / "m.onnx")
    base = [str(model), "--calib", str(tmp_path), "--out", str(tmp_path / "q.onnx")]
    for flag, value in (("--max-delta1-drop", "nan"), ("--max-miou-drop", "inf"), ("--min-label-agreement", "2")):
        one_line_error(capsys, quantize_main, base + [flag, value], f"{flag} must be between 0 and 1")
    assert not (tmp_path / "q.onnx").exists()


def test_eval_and_calibrate_never_write_over_the_model(tmp_path, capsys):
    model = tiny_onnx_model(tmp_path / "m.onnx")
    before = model.read_bytes()
    scene = write_tiny_scene(tmp_path / "scene", frames=2)
    one_line_error(capsys, eval_main, [str(model), str(scene), "--json", str(model)], "is the same file as model")
    one_line_error(capsys, calibrate_main, [str(scene), "--model", str(model), "--out", str(model)],
                   "is the same file as --model")
    assert model.read_bytes() == before
    for main, argv in ((eval_main, [str(model), str(scene), "--max-depth", "inf"]),
                       (calibrate_main, [str(scene), "--model", str(model), "--max-depth", "inf"])):
        one_line_error(capsys, main, argv, "--max-depth must be a finite number")
    one_line_error(capsys, eval_main, [str(model), str(scene), "--figure-frames", "0"], "--figure-frames")
