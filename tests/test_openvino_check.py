"""A file is compiled and run by OpenVINO in a child process before this process touches it
(runtime/perception/openvino_check.py): OpenVINO 2026.4.1 died of SIGSEGV compiling DenseDepth's INT8 file on an
AVX2-only CPU, which took edge-bench (and would take edge-run's runtime probe) down with it."""
from __future__ import annotations

import json
import os
import stat
import sys
from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("onnx")
pytest.importorskip("openvino")

from edge_landing.benchmarks.cli import openvino_usable
from edge_landing.runtime.perception import runtime_choice as rc
from edge_landing.runtime.perception.backend import Runtime, RuntimeRequest
from edge_landing.runtime.perception.openvino_check import main as check_main
from edge_landing.runtime.perception.openvino_check import runs_in_child
from edge_landing.runtime.perception.precision import Precision, ProbeConfig, pick_model
from tests.quant_models import quantized_pair

CRASH = "OpenVINO crashed (SIGSEGV) compiling or running it on this CPU"


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    return quantized_pair(tmp_path_factory.mktemp("ovcheck"))


def test_a_file_openvino_runs_passes_the_check(pair):
    assert runs_in_child(pair["fp32"], 1) == (True, "")
    assert runs_in_child(pair["int8"], 1) == (True, "")
    assert runs_in_child(pair["fp32"], 1, precision=None) == (True, "")     # OpenVINO's own default: its own compile


def test_the_bench_compiles_openvino_as_edge_run_does(pair):
    """f32 float layers unless asked otherwise: on a bf16 CPU OpenVINO's default is bf16, which edge-run never runs,
    so a bench column timed at the default would not be edge-run's figure."""
    from edge_landing.runtime.perception.backend import OpenVinoSession, openvino_default_precision
    from edge_landing.runtime.perception.inference import read_contract

    def hint(session):
        return str(session._compiled.get_property("INFERENCE_PRECISION_HINT"))

    assert hint(OpenVinoSession(pair["fp32"], 1)) == "<Type: 'float32'>"
    default = hint(OpenVinoSession(pair["fp32"], 1, precision=None))
    assert default == ("<Type: 'bfloat16'>" if openvino_default_precision() == "bf16" else "<Type: 'float32'>")
    from edge_landing.benchmarks.speed import openvino_backend

    backend = openvino_backend(pair["fp32"], read_contract(pair["fp32"]), 1)
    outputs = backend.run()
    assert outputs and all(isinstance(o, np.ndarray) and np.isfinite(o).all() for o in outputs)


def test_a_child_that_dies_of_a_signal_is_reported_by_the_signal_not_raised(pair, tmp_path, monkeypatch):
    crasher = tmp_path / "python"
    crasher.write_text("#!/bin/sh\nkill -SEGV $$\n")
    crasher.chmod(crasher.stat().st_mode | stat.S_IEXEC)
    monkeypatch.setattr(sys, "executable", str(crasher))
    assert runs_in_child(pair["fp32"], 1) == (False, CRASH)


def test_a_file_openvino_cannot_read_gives_its_one_line(tmp_path, capsys):
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"not a model" * 10)
    ok, why = runs_in_child(bad, 1)
    assert not ok and why.startswith("OpenVINO cannot run it: ") and "\n" not in why
    assert check_main([str(tmp_path / "missing.onnx"), "1"]) == 2 and "usage" in capsys.readouterr().err
    assert check_main([str(bad), "1", "fp16"]) == 2 and "[f32|default]" in capsys.readouterr().err


def test_edge_run_never_picks_a_file_openvino_crashed_on_and_says_so(pair, tmp_path, monkeypatch):
    calls = []

    def fake_check(path, threads, precision="f32"):
        calls.append(path)
        return (False, CRASH) if str(path).endswith(".int8.onnx") else (True, "")

    monkeypatch.setattr(rc, "runs_in_child", fake_check)
    config = ProbeConfig(threads=1, warmup=1, iterations=5, cache_dir=tmp_path / "cache")
    choice = rc.pick_runtime(pick_model(pair["fp32"], Precision.AUTO, config), pair["fp32"], Precision.AUTO,
                             RuntimeRequest.AUTO, config)
    assert not (choice.runtime is Runtime.OPENVINO and choice.precision is Precision.INT8)
    assert f"openvino int8 refused: {CRASH}" in choice.reason and "openvino int8 not run" in choice.reason
    assert sorted(os.path.basename(p) for p in calls) == ["net.int8.onnx", "net.onnx"]
    (entry,) = (tmp_path / "cache").glob("runtime-*.json")
    record = json.loads(entry.read_text())
    assert record["p50_s"]["openvino int8"] is None and record["agrees"]["openvino int8"] == [False, CRASH]
    again = rc.pick_runtime(pick_model(pair["fp32"], Precision.AUTO, config), pair["fp32"], Precision.AUTO,
                            RuntimeRequest.AUTO, config)
    assert (again.path, again.runtime) == (choice.path, choice.runtime) and "cached" in again.reason
    assert len(calls) == 2                                       # the cache remembers the crash: no second child


def test_edge_bench_leaves_out_only_the_file_openvino_crashed_on(pair, monkeypatch):
    import edge_landing.runtime.perception.backend as backend
    import edge_landing.runtime.perception.openvino_check as check

    monkeypatch.setattr(check, "runs_in_child", lambda path, threads, precision="f32":
                        (False, CRASH) if str(path).endswith(".int8.onnx") else (True, ""))
    monkeypatch.setattr(backend, "openvino_default_precision", lambda: "f32")
    files, notes = openvino_usable(SimpleNamespace(fp32_path=pair["fp32"], int8_path=pair["int8"]), 2)
    assert files == {"openvino": (pair["fp32"], "f32")} and notes == [f"OpenVINO INT8 not timed: {CRASH}"]


def test_on_a_bf16_cpu_edge_bench_times_openvino_default_as_a_peer_and_says_edge_run_does_not_run_it(pair, monkeypatch):
    import edge_landing.runtime.perception.backend as backend
    import edge_landing.runtime.perception.openvino_check as check

    asked = []
    monkeypatch.setattr(check, "runs_in_child", lambda path, threads, precision="f32": asked.append(precision)
                        or (True, ""))
    monkeypatch.setattr(backend, "openvino_default_precision", lambda: "bf16")
    files, notes = openvino_usable(SimpleNamespace(fp32_path=pair["fp32"], int8_path=pair["int8"]), 2)
    assert files == {"openvino": (pair["fp32"], "f32"), "openvino-int8": (pair["int8"], "f32"),
                     "openvino-default": (pair["fp32"], None)}
    assert asked == ["f32", "f32", None]                     # the default precision is its own compile, checked too
    assert len(notes) == 1 and "bf16" in notes[0] and "edge-run compiles in f32" in notes[0]
