"""edge-train, edge-export and edge-bench refuse bad numbers and paths in ONE stderr line (exit 2) before any
training, export or benchmark starts, and a refused run leaves an earlier run's files alone."""
from __future__ import annotations

import pytest

pytest.importorskip("torch")

from edge_landing.benchmarks.cli import main as bench_main  # noqa: E402
from edge_landing.export.cli import main as export_main  # noqa: E402
from edge_landing.export.train_cli import main as train_main  # noqa: E402
from tests.helpers import one_line_error  # noqa: E402
from tests.test_train import write_tiny_scene  # noqa: E402


@pytest.mark.parametrize("extra,expected", [
    (["--weight-decay", "-1"], "--weight-decay must be a finite number >= 0, got -1.0"),
    (["--weight-decay", "nan"], "--weight-decay must be a finite number >= 0, got nan"),
    (["--seed", "-1"], "--seed must be an integer between 0 and"),
    (["--net-width", "-4"], "--net-width must be between 1 and"),
    (["--net-width", "0"], "--net-width must be between 1 and"),
    (["--lr", "inf"], "--lr must be a finite number > 0, got inf"),
    (["--lr", "0"], "--lr must be a finite number > 0"),
    (["--hvo-weight", "-1"], "--hvo-weight must be a finite number >= 0"),
    (["--hvo-weight", "nan"], "--hvo-weight must be a finite number >= 0, got nan"),
    (["--depth-l1-weight", "-1"], "--depth-l1-weight must be a finite number >= 0"),
    (["--threads", "0"], "--threads must be between 1 and 256, got 0"),
    (["--threads", "1000"], "--threads must be between 1 and 256"),
    (["--export-height", "0"], "--export-height must be a finite number >= 1"),
    (["--export-width", "-8"], "--export-width must be a finite number >= 1"),
    (["--export-height", "100000", "--export-width", "100000"], "--export-height must be a finite number >= 1 and <= 4096"),
    (["--export-height", "100"], "--export-height/--export-width"),
    (["--height", "100000", "--width", "100000"], "too large"),
    (["--epochs", "0"], "--epochs must be at least 1"),
])
def test_train_refuses_bad_numbers_before_training(tmp_path, capsys, extra, expected):
    out = tmp_path / "run"
    one_line_error(capsys, train_main, ["--arch", "edgenet", "--train", str(tmp_path / "scene"), "--out", str(out),
                                        "--height", "32", "--width", "32", "--no-progress", *extra], expected)
    assert not (out / "last.pth").exists()


def test_train_refused_for_a_missing_scene_leaves_no_empty_out_folder(tmp_path, capsys):
    write_tiny_scene(tmp_path / "scene")
    for out in (tmp_path / "new" / "run", tmp_path / "kept"):
        if out.name == "kept":
            out.mkdir()   # a folder the user made stays
        one_line_error(capsys, train_main, ["--arch", "edgenet", "--train", str(tmp_path / "scene"), "--val",
                                            str(tmp_path / "nowhere"), "--out", str(out), "--height", "32",
                                            "--width", "32", "--no-progress"], "does not exist or is not a folder")
        assert out.exists() == (out.name == "kept")
    assert not (tmp_path / "new").exists()


def test_train_checkpoint_folder_says_it_is_a_folder(tmp_path, capsys):
    one_line_error(capsys, train_main, ["--arch", "edgenet", "--train", str(tmp_path), "--out", str(tmp_path / "o"),
                                        "--init", str(tmp_path)], "is a folder")


@pytest.mark.parametrize("export_size,expected", [
    (["--export-width", "-8"], "--export-width"),
    (["--export-height", "100000", "--export-width", "100000"], "--export-height"),
    (["--export-height", "40", "--export-width", "36"], "--export-height/--export-width"),
])
def test_refused_overwrite_with_a_bad_export_size_keeps_the_earlier_run(tmp_path, capsys, export_size, expected):
    out = tmp_path / "run"
    out.mkdir()
    (out / "last.pth").write_bytes(b"an earlier run")
    scene = write_tiny_scene(tmp_path / "scene", frames=2)
    one_line_error(capsys, train_main, ["--arch", "edgenet", "--train", str(scene), "--out", str(out), "--overwrite",
                                        "--height", "32", "--width", "32", "--epochs", "1", "--batch", "2",
                                        "--no-progress", *export_size], expected)
    assert (out / "last.pth").read_bytes() == b"an earlier run"
    assert sorted(p.name for p in out.iterdir()) == ["last.pth"]


@pytest.mark.parametrize("args,expected", [
    (["--arch", "edgenet", "--option", "channels=-4"], "--option channels must be a finite number > 0, got -4"),
    (["--arch", "edgenet", "--option", "channels=nan"], "--option channels must be a finite number > 0, got nan"),
    (["--arch", "edgenet", "--option", "channels=0"], "--option channels must be a finite number > 0, got 0"),
    (["--arch", "edgenet", "--option", "channels=2.5"], "--option channels must be a whole number"),
    (["--arch", "edgenet", "--option", "channels=100000"], "channels must be a whole number between 1 and 256"),
    (["--arch", "edgenet", "--height", "100000", "--width", "100000"], "--height must be a finite number >= 1 and <= 4096"),
    (["--arch", "edgenet", "--width", "0"], "--width must be a finite number >= 1"),
    (["--arch", "densedepth", "--max-depth", "inf"], "--max-depth must be a finite number > 0, got inf"),
    (["--arch", "densedepth", "--min-depth", "-1"], "--min-depth must be a finite number > 0"),
    (["--arch", "adabins", "--bins", "0"], "--bins must be a finite number > 0, got 0"),
    (["--arch", "adabins", "--bins", "1"], "bins must be a whole number between 2 and"),
])
def test_export_refuses_bad_options_and_sizes_before_the_export(tmp_path, capsys, args, expected):
    out = tmp_path / "m.onnx"
    err = one_line_error(capsys, export_main, args + ["--out", str(out)], expected)   # progress on: still one line
    assert "RANDOM" not in err and not out.exists()


def test_export_checkpoint_folder_says_it_is_a_folder(tmp_path, capsys):
    one_line_error(capsys, export_main, ["--arch", "edgenet", "--checkpoint", str(tmp_path), "--out",
                                         str(tmp_path / "m.onnx")], "is a folder")


@pytest.mark.parametrize("extra,expected", [
    (["--models", ",,"], "--models ',,' names no model"),
    (["--models", ""], "--models '' names no model"),
    (["--warmup", "-1"], "--warmup must be a finite number >= 0, got -1"),
    (["--threads", "0"], "--threads must be between 1 and 256"),
    (["--max-seconds", "inf"], "--max-seconds must be a finite number > 0"),
    (["--height", "100000"], "--height must be a finite number >= 16 and <= 4096"),
    (["--height", "60"], "--height/--width"),
])
def test_bench_refuses_bad_settings_and_keeps_the_old_report(tmp_path, capsys, extra, expected):
    (tmp_path / "report.json").write_text("earlier")
    one_line_error(capsys, bench_main, ["--quick", "--no-progress", "--out", str(tmp_path), *extra], expected)
    assert (tmp_path / "report.json").read_text() == "earlier"
    assert not (tmp_path / "cache").exists()


def test_bench_checks_the_calibration_scene_length_before_exporting(tmp_path, capsys):
    scene = write_tiny_scene(tmp_path / "scene", frames=3)
    one_line_error(capsys, bench_main, ["--models", "edgenet", "--calib", str(scene), "--out", str(tmp_path / "b"),
                                        "--no-progress"], "--calib-frames 4 needs at least 5")
    assert not (tmp_path / "b").exists()
