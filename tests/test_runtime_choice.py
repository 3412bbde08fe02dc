"""edge-run's choice of runtime: ONNX Runtime, or OpenVINO on the same file when it agrees and is faster here."""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("onnx")
pytest.importorskip("openvino")

from edge_landing.cli.common import EXIT_BAD_INPUT
from edge_landing.cli.run import main
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.perception import runtime_choice as rc
from edge_landing.runtime.perception.backend import Runtime, RuntimeRequest
from edge_landing.runtime.perception.inference import OnnxModel, SessionConfig
from edge_landing.runtime.perception.precision import Precision, ProbeConfig, pick_model
from tests.quant_models import quantized_pair


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    return quantized_pair(tmp_path_factory.mktemp("runtime"))


def _probe(tmp_path):
    return ProbeConfig(threads=1, warmup=1, iterations=5, cache_dir=tmp_path / "cache")


def test_openvino_runs_the_same_file_to_the_same_outputs(pair):
    rgb = rc.probe_image(64, 96)
    ort = OnnxModel.load(pair["fp32"], threads=1)
    ov = OnnxModel.load(pair["fp32"], config=SessionConfig(threads=1, runtime=Runtime.OPENVINO))
    assert ov.contract == ort.contract
    a, b = ort.predict(rgb), ov.predict(rgb)
    assert a.valid and b.valid
    np.testing.assert_allclose(b.depth_m, a.depth_m, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(b.hvo_prob, a.hvo_prob, atol=1e-4)
    first = ov.run(ov.prepare(rgb))
    ov.run(ov.prepare(rc.probe_image(64, 96, seed=5)))
    np.testing.assert_allclose(first[ov.contract.depth.output], ov.run(ov.prepare(rgb))[ov.contract.depth.output])


def test_auto_times_every_candidate_picks_the_fastest_and_caches(pair, tmp_path, monkeypatch):
    config = _probe(tmp_path)
    choice = rc.pick_runtime(pick_model(pair["fp32"], Precision.AUTO, config), pair["fp32"], Precision.AUTO,
                             RuntimeRequest.AUTO, config)
    for label in ("onnxruntime fp32", "onnxruntime int8", "openvino fp32", "openvino int8"):
        assert label in choice.reason
    (entry,) = (tmp_path / "cache").glob("runtime-*.json")
    import json

    record = json.loads(entry.read_text())
    fastest = min((v, k) for k, v in record["p50_s"].items() if not k.startswith("openvino")
                  or record["agrees"][k][0])[1]
    assert f"{choice.runtime.value} {choice.precision.value}" == fastest
    assert choice.path == (pair["int8"] if choice.precision is Precision.INT8 else pair["fp32"])
    monkeypatch.setattr(rc, "interleaved_p50_s", lambda *_: pytest.fail("probed although cached"))
    again = rc.pick_runtime(pick_model(pair["fp32"], Precision.AUTO, config), pair["fp32"], Precision.AUTO,
                            RuntimeRequest.AUTO, config)
    assert (again.path, again.runtime) == (choice.path, choice.runtime) and "cached" in again.reason


def test_an_openvino_candidate_that_disagrees_is_refused(pair, tmp_path, monkeypatch):
    config = _probe(tmp_path)
    monkeypatch.setattr(rc, "agreement", lambda *_: (False, "HVO labels agree on 80.0%"))
    base = pick_model(pair["fp32"], Precision.FP32, config)
    choice = rc.pick_runtime(base, pair["fp32"], Precision.FP32, RuntimeRequest.AUTO, config)
    assert choice.runtime is Runtime.ONNXRUNTIME and "openvino fp32 refused: HVO labels agree on 80.0%" in choice.reason
    with pytest.raises(InputError, match="OpenVINO's outputs differ"):
        rc.pick_runtime(base, pair["fp32"], Precision.FP32, RuntimeRequest.OPENVINO, _probe(tmp_path / "other"))


def test_onnxruntime_asked_or_openvino_missing_changes_nothing(pair, tmp_path, monkeypatch):
    config = _probe(tmp_path)
    base = pick_model(pair["fp32"], Precision.INT8, config)
    assert rc.pick_runtime(base, pair["fp32"], Precision.INT8, RuntimeRequest.ONNXRUNTIME, config) is base
    monkeypatch.setattr(rc, "openvino_available", lambda: False)
    assert rc.pick_runtime(base, pair["fp32"], Precision.INT8, RuntimeRequest.AUTO, config) is base
    with pytest.raises(InputError, match="openvino is not installed"):
        rc.pick_runtime(base, pair["fp32"], Precision.INT8, RuntimeRequest.OPENVINO, config)
    assert not config.cache_dir.exists()


def test_explicit_precision_keeps_its_file_on_either_runtime(pair, tmp_path):
    config = _probe(tmp_path)
    base = pick_model(pair["fp32"], Precision.INT8, config)
    choice = rc.pick_runtime(base, pair["fp32"], Precision.INT8, RuntimeRequest.OPENVINO, config)
    assert choice.path == pair["int8"] and choice.runtime is Runtime.OPENVINO
    assert choice.line().startswith("model net.int8.onnx (int8) on openvino: fastest here")


def test_edge_run_names_a_bad_runtime_in_one_line(pair, capsys):
    assert main(["--model", str(pair["fp32"]), "--runtime", "tensorrt"]) == EXIT_BAD_INPUT
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--runtime 'tensorrt'" in err[0] and "auto, onnxruntime, openvino" in err[0]
