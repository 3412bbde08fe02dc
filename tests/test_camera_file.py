"""A real camera's calibration for edge-run --intrinsics (runtime/io/camera_file.py): the formats calibration
tools write, OpenCV's pixel-centre convention, and every bad file as one line with exit 2."""
import json

import cv2
import numpy as np
import pytest

from edge_landing.cli.run import main as run_main
from edge_landing.runtime.core.camera import Intrinsics
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.io.camera_file import fit_to_frame, load_intrinsics
from tests.helpers import one_line_error

K = np.array([[612.5, 0.0, 318.2], [0.0, 611.0, 243.7], [0.0, 0.0, 1.0]])   # OpenCV convention (centres at ints)
DIST = np.array([[-0.291, 0.084, 0.0012, -0.0007, -0.011]])                  # a wide USB camera's barrel


def _opencv_file(path, matrix=K, dist=DIST, size=(640, 480)):
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)   # as OpenCV's calibration sample writes it
    if size is not None:
        fs.write("image_width", size[0])
        fs.write("image_height", size[1])
    fs.write("camera_matrix", matrix)
    fs.write("distortion_coefficients", dist)
    fs.release()
    return path


ROS = """image_width: 640
image_height: 480
camera_name: downward
camera_matrix:
  rows: 3
  cols: 3
  data: [612.5, 0.0, 318.2, 0.0, 611.0, 243.7, 0.0, 0.0, 1.0]
distortion_model: {model}
distortion_coefficients:
  rows: 1
  cols: 5
  data: [-0.291, 0.084, 0.0012, -0.0007, -0.011]
"""


@pytest.mark.parametrize("suffix", [".yaml", ".xml"])
def test_opencv_calibration_files_are_read_with_the_principal_point_moved_half_a_pixel(tmp_path, suffix):
    intr = load_intrinsics(str(_opencv_file(tmp_path / f"cam{suffix}")))
    assert (intr.width, intr.height, intr.fx, intr.fy) == (640, 480, 612.5, 611.0)
    assert (intr.cx, intr.cy) == pytest.approx((318.7, 244.2))     # pixel-edge convention, like the runtime
    assert intr.dist == pytest.approx(tuple(DIST.ravel()))


def test_ros_camera_info_and_the_projects_own_json_are_read(tmp_path):
    ros = tmp_path / "ros.yaml"
    ros.write_text(ROS.format(model="plumb_bob"))
    from_ros = load_intrinsics(str(ros))
    assert (from_ros.fx, from_ros.cx, from_ros.cy) == pytest.approx((612.5, 318.7, 244.2))
    assert from_ros.dist == pytest.approx(tuple(DIST.ravel()))
    own = tmp_path / "own.json"
    own.write_text(json.dumps(from_ros.to_json()))
    assert load_intrinsics(str(own)) == from_ros                              # round trip, no half-pixel move
    scene = tmp_path / "scene.json"
    scene.write_text(json.dumps({"frame_count": 3, "camera": from_ros.to_json()}))      # as edge-sim writes it
    assert load_intrinsics(str(scene)) == from_ros


def test_a_calibration_scales_to_the_frame_size_but_not_to_another_aspect_ratio(tmp_path):
    intr = Intrinsics(1280, 960, 1225.0, 1222.0, 637.4, 488.4, tuple(DIST.ravel()))
    half = fit_to_frame(intr, 640, 480, "cam.yaml")
    assert (half.fx, half.cx, half.cy) == pytest.approx((612.5, 318.7, 244.2)) and half.dist == intr.dist
    with pytest.raises(InputError, match="calibrated at 1280x960, but the camera gives 1280x720"):
        fit_to_frame(intr, 1280, 720, "cam.yaml")


@pytest.mark.parametrize("write, expected", [
    (lambda p: p.write_text(ROS.format(model="equidistant")), "'equidistant' is not OpenCV's pinhole model"),
    (lambda p: _opencv_file(p, size=None), "needs image_width and image_height"),
    (lambda p: _opencv_file(p, matrix=np.eye(2)), "no 3x3 camera matrix"),
    (lambda p: _opencv_file(p, matrix=K * [[1, 1, 3], [1, 1, 1], [1, 1, 1]]), "principal point"),
    (lambda p: _opencv_file(p, matrix=K * [[-1, 1, 1], [1, 1, 1], [1, 1, 1]]), "positive size and focal lengths"),
    (lambda p: _opencv_file(p, dist=np.zeros((1, 3))), "3 distortion coefficients"),
    (lambda p: p.write_text("not: [a calibration"), "not an OpenCV or ROS calibration file"),
])
def test_a_bad_calibration_file_is_one_line_naming_it(tmp_path, write, expected):
    path = tmp_path / "cam.yaml"
    write(path)
    with pytest.raises(InputError, match=expected) as info:
        load_intrinsics(str(path))
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_edge_run_refuses_a_bad_calibration_before_any_work(tmp_path, capsys):
    images = tmp_path / "frames"
    images.mkdir()
    cv2.imwrite(str(images / "0.png"), np.zeros((48, 64, 3), np.uint8))
    bad = tmp_path / "cam.yaml"
    bad.write_text(ROS.format(model="equidistant"))
    log = tmp_path / "run.jsonl"
    one_line_error(capsys, run_main, ["--camera", images, "--intrinsics", bad, "--log", log], "equidistant")
    one_line_error(capsys, run_main, ["--camera", images, "--intrinsics", tmp_path / "none.yaml"], "does not exist")
    one_line_error(capsys, run_main, ["--intrinsics", _opencv_file(tmp_path / "ok.yaml")], "synthetic camera")
    assert not log.exists()
