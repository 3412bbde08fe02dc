import math

import numpy as np
import onnx
import pytest

from edge_landing.cli.common import EXIT_BAD_INPUT
from edge_landing.evaluation.scene import Scene
from edge_landing.export.quant_check import compare
from edge_landing.export.quantize import Tolerance, check_tolerance, depth_head_nodes
from edge_landing.export.quantize_cli import main
from edge_landing.runtime.perception.contract import Task
from edge_landing.runtime.perception.inference import OnnxModel, file_sha256
from tests.quant_models import textured_scene, tiny_conv_net


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    d = tmp_path_factory.mktemp("quant")
    return {"dir": d, "both": tiny_conv_net(d / "both.onnx", Task.DEPTH_HVO),
            "hvo": tiny_conv_net(d / "hvo.onnx", Task.HVO),
            "good": textured_scene(d / "good", 10), "bad": textured_scene(d / "bad", 12, black_first=6)}


def _argv(model, scene, out, *extra):
    return [str(model), "--calib", str(scene), "--frames", "6", "--out", str(out), "--no-progress", *extra]


def test_quantized_model_runs_keeps_contract_and_records_settings(models, tmp_path, capsys):
    src = models["both"]
    sha = file_sha256(src)
    out = tmp_path / "both.int8.onnx"
    assert main(_argv(src, models["good"], out)) == 0
    assert "INT8 vs FP32 on 4 held-out frame(s)" in capsys.readouterr().out
    assert file_sha256(src) == sha                                    # the FP32 file is untouched
    fp32, int8 = OnnxModel.load(src), OnnxModel.load(out)
    q = int8.contract.quantization
    assert int8.contract.with_quantization({}) == fp32.contract.with_quantization({})  # contract carried over
    assert (q["format"], q["activations"], q["weights"]) == ("QDQ", "QUInt8", "QInt8")
    assert q["per_channel"] and q["reduce_range"] and q["passed"] and not q["forced"]
    assert q["float_depth_head"] and "depth_head" in q["excluded_nodes"]   # depth models keep the head float
    assert q["calibration"]["frames"] == 6 and q["comparison"]["frames"] == 4
    assert q["comparison"]["hvo"]["agreement"] >= 0.9 and q["comparison"]["depth"]["agreement"] >= 0.9
    ops = {n.op_type for n in onnx.load(str(out)).graph.node}
    assert {"QuantizeLinear", "DequantizeLinear"} <= ops
    frame = Scene(textured_scene(tmp_path / "one", 1, seed=5)).read_rgb("000000")
    p32, p8 = fp32.predict(frame), int8.predict(frame)
    assert p8.valid and p8.depth_m.shape == p32.depth_m.shape
    np.testing.assert_allclose(p8.depth_m, p32.depth_m, rtol=0.05)
    assert np.mean(p8.hvo_prob.argmax(2) == p32.hvo_prob.argmax(2)) > 0.9


def test_gate_trips_on_black_calibration_and_leaves_nothing(models, tmp_path, capsys):
    src, out = models["both"], tmp_path / "bad.int8.onnx"
    sha = file_sha256(src)
    assert main(_argv(src, models["bad"], out)) == EXIT_BAD_INPUT
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "INT8 model rejected" in err[0] and "--force" in err[0]
    assert not out.exists() and file_sha256(src) == sha
    assert not list(tmp_path.glob(".edge-quantize-*"))               # no temporary left behind


def test_force_keeps_a_failing_model_and_says_so(models, tmp_path, capsys):
    out = tmp_path / "forced.int8.onnx"
    assert main(_argv(models["both"], models["bad"], out, "--force")) == 0
    assert "written anyway" in capsys.readouterr().out
    q = OnnxModel.load(out).contract.quantization
    assert q["passed"] is False and q["forced"] is True


def test_hvo_model_quantizes_fully_and_rejects_depth_head_flag(models, tmp_path, capsys):
    out = tmp_path / "hvo.int8.onnx"
    assert main(_argv(models["hvo"], models["good"], out)) == 0
    q = OnnxModel.load(out).contract.quantization
    assert not q["float_depth_head"] and "depth" not in q["comparison"]
    code = main(_argv(models["hvo"], models["good"], tmp_path / "x.onnx", "--keep-depth-head-float"))
    assert code == EXIT_BAD_INPUT and "no depth head" in capsys.readouterr().err


def test_bad_inputs_are_one_line_errors(models, tmp_path, capsys):
    small = textured_scene(tmp_path / "small", 3)
    assert main(_argv(models["both"], small, tmp_path / "o.onnx")) == EXIT_BAD_INPUT
    assert "held out" in capsys.readouterr().err
    assert main(_argv(models["both"], models["good"], models["both"])) == EXIT_BAD_INPUT
    assert "FP32 input itself" in capsys.readouterr().err
    assert main(_argv(models["both"], tmp_path / "nope", tmp_path / "o.onnx")) == EXIT_BAD_INPUT
    assert "does not exist" in capsys.readouterr().err
    assert main(_argv(models["both"], models["good"], tmp_path / "o.onnx", "--method", "magic")) == EXIT_BAD_INPUT
    assert "magic" in capsys.readouterr().err


def test_depth_head_walk_stops_at_the_last_conv(models):
    names = depth_head_nodes(onnx.load(str(models["both"])), "depth")
    assert names == ["depth_offset", "depth_softplus", "depth_head"]


def test_tolerance_names_each_failure_and_ignores_nan_metrics():
    comparison = {"depth": {"delta1_drop": 0.05, "abs_rel_increase": 0.0, "agreement": 0.95},
                  "hvo": {"miou_drop": 0.0, "hprec_drop": math.nan, "agreement": 0.5}}
    reasons = check_tolerance(comparison, Tolerance())
    assert len(reasons) == 2
    assert "δ1 drop +0.0500" in reasons[0] and "label agreement" in reasons[1]
    comparison["hvo"]["agreement"] = math.nan           # no agreement figure is a failure, not a pass
    assert any("label agreement" in r for r in check_tolerance(comparison, Tolerance(max_delta1_drop=0.1)))


def test_conv_transpose_is_rewritten_so_it_quantizes(models, tmp_path):
    src = tiny_conv_net(tmp_path / "up.onnx", Task.HVO, upsample=True)
    proto = onnx.load(str(src))
    proto.metadata_props.add(key="training.run", value="tiny")        # not a contract key: kept all the same
    onnx.save(proto, str(src))
    out = tmp_path / "up.int8.onnx"
    assert main(_argv(src, models["good"], out)) == 0
    assert {p.key: p.value for p in onnx.load(str(out)).metadata_props}["training.run"] == "tiny"
    q = OnnxModel.load(out).contract.quantization
    assert q["subpixel_conv_transposes"] == 1 and q["comparison"]["hvo"]["agreement"] >= 0.9
    ops = [n.op_type for n in onnx.load(str(out)).graph.node]
    assert "ConvTranspose" not in ops and "QLinearConv" not in ops and ops.count("Conv") == 4
    assert main(_argv(src, models["good"], tmp_path / "kept.onnx", "--no-subpixel")) == 0
    assert "ConvTranspose" in [n.op_type for n in onnx.load(str(tmp_path / "kept.onnx")).graph.node]


def test_depth_is_compared_with_fp32_when_ground_truth_is_out_of_the_models_range(models, tmp_path):
    far = textured_scene(tmp_path / "far", 3, depth_offset_m=500.0)   # the tiny model's range ends at 100 m
    fp32 = OnnxModel.load(models["both"])
    result = compare(fp32, fp32, [(Scene(far), "000000"), (Scene(far), "000001")], progress=False)["depth"]
    assert result["reference"].startswith("fp32 (no ground-truth pixel")
    assert result["delta1_drop"] == 0.0 and result["abs_rel_increase"] == 0.0 and result["agreement"] == 1.0
    near = compare(fp32, fp32, [(Scene(models["good"]), "000006")], progress=False)["depth"]
    assert near["reference"] == "ground truth" and np.isfinite(near["fp32"]["abs_rel"])


def test_calibration_from_two_scenes_shares_and_interleaves_frames(models, tmp_path):
    from edge_landing.export.calib_frames import split_frames

    a, b = Scene(models["good"]), Scene(textured_scene(tmp_path / "other", 8, seed=9))
    calib, held = split_frames([a, b], 5, 4)
    assert [s.path for s, _ in calib] == [a.path, b.path, a.path, b.path, a.path]     # 3 + 2, interleaved
    assert [f for s, f in calib if s is a] == ["000000", "000001", "000002"]
    assert [(s.path, f) for s, f in held] == [(a.path, "000003"), (b.path, "000002"), (a.path, "000004"),
                                               (b.path, "000003")]
    out = tmp_path / "two.int8.onnx"
    assert main([str(models["both"]), "--calib", str(a.path), str(b.path), "--frames", "6", "--eval-frames", "4",
                 "--out", str(out), "--no-progress"]) == 0
    q = OnnxModel.load(out).contract.quantization
    assert q["calibration"]["scenes"] == [str(a.path), str(b.path)] and q["calibration"]["frames"] == 6
    assert q["comparison"]["frames"] == 4 and q["comparison"]["last"] == "other/000004"   # 3 + 3 calibrate, 2 + 2 held out


def test_joint_net_keeps_its_whole_depth_branch_float_and_nothing_shared():
    from onnx import TensorProto, helper

    def conv(i, o, name):
        return helper.make_node("Conv", [i, "w"], [o], name=name)
    nodes = [conv("image", "t1", "trunk"), helper.make_node("Relu", ["t1"], ["t"], name="trunk_relu"),
             conv("t", "d1", "depth_conv3x3"), helper.make_node("Relu", ["d1"], ["d2"], name="depth_relu"),
             conv("d2", "d3", "depth_out_conv"), helper.make_node("Exp", ["d3"], ["depth"], name="exp"),
             conv("t", "hvo_logits", "hvo_conv")]
    vi = helper.make_tensor_value_info
    graph = helper.make_graph(nodes, "g", [vi("image", TensorProto.FLOAT, [1, 1, 4, 4])],
                              [vi("depth", TensorProto.FLOAT, None), vi("hvo_logits", TensorProto.FLOAT, None)],
                              [helper.make_tensor("w", TensorProto.FLOAT, [1, 1, 1, 1], [1.0])])
    model = helper.make_model(graph)
    assert sorted(depth_head_nodes(model, "depth")) == ["depth_conv3x3", "depth_out_conv", "depth_relu", "exp"]


def test_speed_gate_records_the_cpu_and_the_search_times_each_branch(models, tmp_path):
    """Speed gate: INT8 timed against FP32 here, with the CPU's features; the branch search (forced on with
    ``always``) re-quantizes with each top-level branch in float, and what it keeps float is in the record."""
    from edge_landing.export.quant_speed import SpeedSearch, branch_groups
    from edge_landing.export.quantize import QuantizeConfig, quantize
    from edge_landing.runtime.core.cpu_features import cpu_features

    model = onnx.load(str(models["both"]))
    for node in model.graph.node:    # exporter-style names: /branch/.../op
        if node.name in ("conv1", "relu1", "conv2", "relu2"):
            node.name = f"/{'a' if node.name.endswith('1') else 'b'}/{node.name}"
    src = tmp_path / "named.onnx"
    onnx.save(model, str(src))
    assert branch_groups(model, ["/b/relu2"]) == {"a": ["/a/conv1", "/a/relu1"], "b": ["/b/conv2"]}
    report = quantize(src, tmp_path / "named.int8.onnx", QuantizeConfig(
        calib_scene=models["good"], calib_frames=6, eval_frames=4, progress=False, speed_search=SpeedSearch.ALWAYS))
    assert report.passed and report.written
    q = OnnxModel.load(tmp_path / "named.int8.onnx").contract.quantization
    assert q["tuned_on_cpu"]["features"] == list(cpu_features().features)
    speed = q["speed"]
    assert speed["fp32_p50_ms"] > 0 and speed["int8_p50_ms"] > 0 and speed["threads"] == 2
    assert speed["faster_here"] == (speed["int8_p50_ms"] < speed["fp32_p50_ms"])
    search = q["speed_search"]
    assert search["ran"] and [s["branch"] for s in search["steps"]] == ["a", "b"]
    for step in search["steps"]:
        assert step["int8_p50_ms"] > 0 and step["with_branch_float_p50_ms"] > 0
        assert step["kept_float"] == (step["branch"] in search["kept_float"])
    for branch in search["kept_float"]:
        assert any(n.startswith(f"/{branch}/") for n in q["excluded_nodes"])
