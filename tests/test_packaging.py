"""What `pip install .` puts into site-packages: one import name, `edge_landing`, with its typing marker, the
shipped models and the licence (the wheel is built from a copy of the checkout, offline, in a few seconds)."""
from __future__ import annotations

import configparser
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
COMMANDS = {"edge-run", "edge-eval", "edge-calibrate", "edge-export", "edge-quantize", "edge-train", "edge-sim",
            "edge-bench"}


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> zipfile.ZipFile:
    pytest.importorskip("setuptools")
    tmp = tmp_path_factory.mktemp("wheel")
    # a copy, so the build leaves no build/ or .egg-info in the checkout
    src = shutil.copytree(ROOT, tmp / "src", ignore=shutil.ignore_patterns(
        ".venv", "v", ".git", "build", "dist", "*.egg-info", "__pycache__", ".pytest_cache", "out", "runs", "scenes"))
    proc = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index",
                           "-q", "-w", str(tmp / "dist"), str(src)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    (path,) = (tmp / "dist").glob("edge_landing-*.whl")
    return zipfile.ZipFile(path)


def test_the_wheel_installs_one_top_level_name(wheel):
    names = wheel.namelist()
    (info,) = {n.split("/")[0] for n in names if n.split("/")[0].endswith(".dist-info")}
    assert wheel.read(f"{info}/top_level.txt").decode().split() == ["edge_landing"]
    record = wheel.read(f"{info}/RECORD").decode().splitlines()
    assert {line.split(",")[0].split("/")[0] for line in record} == {"edge_landing", info}
    assert {n.split("/")[0] for n in names} == {"edge_landing", info}


def test_the_wheel_ships_the_typing_marker_models_licence_and_commands(wheel):
    names = set(wheel.namelist())
    info = next(n.split("/")[0] for n in names if ".dist-info/" in n)
    assert "edge_landing/py.typed" in names
    assert {"edge_landing/runtime/models/edgenet.onnx", "edge_landing/runtime/models/edgenet.int8.onnx"} <= names
    assert any(n.startswith(f"{info}/") and n.endswith("LICENSE") for n in names)
    assert not any(n.startswith("edge_landing/tests") or n.startswith("tests/") for n in names)
    eps = configparser.ConfigParser()
    eps.read_string(wheel.read(f"{info}/entry_points.txt").decode())
    assert set(eps["console_scripts"]) == COMMANDS
    assert all(v.strip().startswith("edge_landing.") for v in eps["console_scripts"].values())
