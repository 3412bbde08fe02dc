import csv
import json
from pathlib import Path

import numpy as np
import pytest
from onnx import TensorProto, helper, numpy_helper

from edge_landing.benchmarks import report as rep
from edge_landing.benchmarks.cli import main
from edge_landing.benchmarks.flops import count_macs
from edge_landing.benchmarks.speed import Backend, SpeedConfig, interleaved
from tests.quant_models import tiny_conv_net


def _graph(nodes, inputs, outputs, inits):
    model = helper.make_model(helper.make_graph(nodes, "g", inputs, outputs, inits),
                              opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    return model


def test_macs_of_a_conv_net_match_the_hand_count(tmp_path):
    macs = count_macs(tiny_conv_net(tmp_path / "m.onnx", height=32, width=48))
    assert macs.by_op == {"Conv": 32 * 48 * (8 * 3 * 9 + 8 * 8 * 9 + 3 * 8 + 1 * 8)} and not macs.uncounted
    assert macs.gflop == pytest.approx(2 * macs.total / 1e9)


def test_macs_of_conv_transpose_matmul_gemm_and_grouped_conv():
    f = TensorProto.FLOAT
    inits = [numpy_helper.from_array(np.zeros(s, np.float32), n) for n, s in
             (("wt", (4, 2, 3, 3)), ("wg", (4, 1, 3, 3)), ("b", (10, 6)), ("g", (6, 5)))]
    inits.append(numpy_helper.from_array(np.array([6, 6], np.int64), "shape"))
    nodes = [helper.make_node("ConvTranspose", ["x", "wt"], ["y"], strides=[2, 2]),          # 4->2 ch
             helper.make_node("Conv", ["x", "wg"], ["z"], group=4, pads=[1, 1, 1, 1]),        # depthwise
             helper.make_node("MatMul", ["a", "b"], ["c"]),                                   # batched 2x3x10 @ 10x6
             helper.make_node("Reshape", ["c", "shape"], ["c2"]),
             helper.make_node("Gemm", ["c2", "g"], ["d"])]
    model = _graph(nodes, [helper.make_tensor_value_info("x", f, [1, 4, 5, 7]),
                           helper.make_tensor_value_info("a", f, [2, 3, 10])],
                   [helper.make_tensor_value_info(n, f, None) for n in ("y", "z", "d")], inits)
    macs = count_macs(model)
    assert macs.by_op["ConvTranspose"] == 4 * 5 * 7 * 2 * 9
    assert macs.by_op["Conv"] == 4 * 5 * 7 * 9
    assert macs.by_op["MatMul"] == 2 * 3 * 6 * 10
    assert macs.by_op["Gemm"] == 6 * 5 * 6


def test_interleaved_rotates_backends_and_reports_percentiles():
    order = []
    backends = [Backend("a", "ort-fp32", 2, lambda: order.append("a")),
                Backend("b", "ort-int8", 2, lambda: order.append("b"), before=lambda: order.append("b-before"))]
    timings = interleaved(backends, SpeedConfig(warmup=1, iterations=4, progress=False))
    runs = [o for o in order if o != "b-before"]
    assert runs[:2] == ["a", "b"] and runs[2:4] == ["a", "b"] and runs[4:6] == ["b", "a"]   # rotation after warm-up
    assert order.count("b-before") == 5
    t = timings["b"].to_json()
    assert t["iterations"] == 4 and t["images_per_s"] > 0 and t["p50_ms"] <= t["p90_ms"] <= t["p99_ms"]


def test_quick_bench_writes_a_report_with_the_schema(tmp_path, capsys):
    out = tmp_path / "bench"
    code = main(["--quick", "--models", "safeuav-small", "--height", "48", "--width", "64", "--out", str(out),
                 "--iterations", "2", "--no-progress"])
    assert code == 0
    stdout = capsys.readouterr().out
    assert "| safeuav-small | 48×64 |" in stdout and "paper V100 img/s" in stdout
    report = json.loads((out / "report.json").read_text())
    assert report["schema"] == rep.SCHEMA_VERSION and report["settings"]["threads"] == 2
    assert report["peak"]["gflops"] > 0
    from edge_landing.runtime.core.cpu_features import cpu_features

    isa = cpu_features()      # the report names the CPU's ISA features, in the JSON and above the table
    assert report["machine"]["isa"]["features"] == list(isa.features) and f"CPU: {isa.summary()}" in stdout
    (row,) = report["rows"]
    assert set(rep.ROW_KEYS) <= set(row)
    assert {"ort-fp32", "ort-int8", "torch"} <= set(row["timings"])
    import importlib.util

    if importlib.util.find_spec("openvino") is not None:     # the peer runtime on the same two files
        assert {"openvino", "openvino-int8"} <= set(row["timings"]) and "OpenVINO INT8 img/s" in stdout
    for t in row["timings"].values():
        assert {"images_per_s", "p50_ms", "p90_ms", "p99_ms", "iterations", "threads"} <= set(t)
        assert t["iterations"] == 2 and t["threads"] == 2
    assert row["params_m"] == pytest.approx(1.029283, abs=1e-6)          # SafeUAV-Net-Small HVO, models.md
    assert row["paper_v100_images_per_s"] == 101.366
    assert row["onnx_int8_mb"] < row["onnx_fp32_mb"] and row["gmac"] > 0
    assert row["int8_vs_fp32"] > 0 and 0 < row["fp32_share_of_peak"] and row["peak_gflops_same_run"] > 0
    with open(out / "report.csv") as fh:
        lines = list(csv.DictReader(fh))
    assert {line["backend"] for line in lines} == set(row["timings"])
    assert (out / "report.png").read_bytes()[:4] == b"\x89PNG"


def test_unknown_model_and_bad_checkpoint_are_one_clear_error(tmp_path, capsys):
    assert main(["--models", "resnet", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "unknown model 'resnet'" in err and "safeuav-small" in err
    assert main(["--models", "safeuav-small", "--checkpoint", "safeuav-small=/nope.pth", "--out", str(tmp_path)]) == 2
    assert "/nope.pth does not exist" in capsys.readouterr().err


def test_markdown_includes_scaling_table():
    row = rep.BenchRow(model="m", arch="m", task="hvo", input_hw=[8, 8], threads=2, params_m=1.0, onnx_fp32_mb=4.0,
                       onnx_int8_mb=1.0, gmac=1.0, paper_v100_images_per_s=None,
                       timings={"ort-fp32": {"images_per_s": 10.0, "p50_ms": 100, "p90_ms": 110, "p99_ms": 120}},
                       scaling={"ort-fp32": {"1": 6.0, "2": 10.0, "speedup": 10 / 6}}).finish(100.0)
    assert row.fp32_gflops == pytest.approx(20.0) and row.fp32_share_of_peak == pytest.approx(0.2)
    md = rep.to_markdown({"rows": [rep.row_to_json(row)], "peak": {"gflops": 100.0}, "settings": {"threads": 2}})
    assert "| m | ORT FP32 | 6.00 | 10.00 | 1.67× |" in md and "20.0 (20 %)" in md


def test_profile_sums_kernel_time_per_op_type(tmp_path):
    from edge_landing.benchmarks.profile import profile_ops, summarise
    from edge_landing.runtime.perception.inference import read_contract

    path = tiny_conv_net(tmp_path / "m.onnx")
    ops = profile_ops(path, read_contract(path), threads=1, runs=3, warmup=1)
    assert "Conv" in {o.op_type for o in ops} and sum(o.share for o in ops) == pytest.approx(1.0)
    events = [{"cat": "Node", "name": "a_kernel_time", "dur": 1000, "args": {"op_name": "Conv"}},      # warm-up
              {"cat": "Session", "name": "model_run"},
              {"cat": "Node", "name": "a_kernel_time", "dur": 3000, "args": {"op_name": "Conv"}},
              {"cat": "Node", "name": "b_kernel_time", "dur": 1000, "args": {"op_name": "Add"}},
              {"cat": "Session", "name": "model_run"}]
    conv, add = summarise(events, runs_after_warmup=1, warmup=1)
    assert (conv.op_type, conv.total_ms, conv.share, conv.nodes) == ("Conv", 3.0, 0.75, 1) and add.total_ms == 1.0


def test_goal_checks_say_met_or_missed_by_how_much():
    from edge_landing.benchmarks.goals import check_goals

    def row(model, fp32, int8, torch, share, agree=1.0):
        t = {k: {"images_per_s": v} for k, v in (("ort-fp32", fp32), ("ort-int8", int8), ("torch", torch))}
        return {"model": model, "timings": t, "int8_vs_fp32": int8 / fp32, "int8_vs_torch": int8 / torch,
                "fp32_share_of_peak": share, "int8_agreement": agree,
                "profile": {"ort-int8": [{"op_type": "Transpose", "share": 0.35}]}}

    report = {"rows": [row("safeuav-small", 35.0, 47.6, 16.0, 0.73), row("edgenet", 113.0, 207.0, 42.0, 0.63)]}
    checks = {(c.model, c.goal): c for c in check_goals(report)}
    ratio = checks[("safeuav-small", "ORT INT8 / ORT FP32")]
    assert not ratio.met and "MISSED by 3 %" in ratio.line() and "Transpose 35 %" in ratio.line()
    assert checks[("safeuav-small", "ORT INT8 / PyTorch eager")].met
    assert checks[("edgenet", "ORT INT8 images/s / SafeUAV-Net-Small INT8")].value == pytest.approx(207 / 47.6)
    assert ("edgenet", "ORT FP32 share of the matmul peak") not in checks   # not a conv-heavy published model


def test_per_cpu_goals_judge_the_fastest_configuration_edge_run_may_run_not_openvinos_bf16():
    """Issue 16's goals are about what edge-run runs: ORT or OpenVINO (f32), FP32 or INT8. OpenVINO's own default
    precision is a peer it is compared with, never a pick."""
    from edge_landing.benchmarks.goals import check_goals

    def row(model, **ips):
        return {"model": model, "timings": {k.replace("_", "-"): {"images_per_s": v} for k, v in ips.items()}}

    report = {"rows": [
        row("edgenet", ort_fp32=74.0, ort_int8=82.0, torch=39.0, openvino=57.0, openvino_int8=107.0),
        row("safeuav-small", ort_fp32=51.0, ort_int8=67.0, torch=32.0, openvino=55.0, openvino_int8=119.0,
            openvino_default=136.0),
        row("densedepth", ort_fp32=0.42, ort_int8=0.40)]}
    checks = {(c.model, c.goal): c for c in check_goals(report)}
    pick = "fastest of what edge-run may run"
    edge = checks[("edgenet", f"{pick} / ORT FP32")]
    assert edge.met and edge.value == pytest.approx(107 / 74) and edge.target == 1.3 and "openvino-int8" in edge.detail
    assert checks[("safeuav-small", f"{pick} / PyTorch eager")].value == pytest.approx(119 / 32)
    beaten = checks[("safeuav-small", f"{pick} / fastest OpenVINO (openvino-default)")]
    assert not beaten.met and beaten.value == pytest.approx(119 / 136) and "does not run" in beaten.line()
    assert checks[("edgenet", f"{pick} / fastest OpenVINO (openvino-int8)")].met
    # A slower INT8 is never the pick: FP32 is, so "never slower than FP32" holds at exactly 1.
    assert checks[("densedepth", f"{pick} / ORT FP32")].value == pytest.approx(1.0)
    assert ("densedepth", f"{pick} / PyTorch eager") not in checks


def test_depth_anything_v2_small_peer_has_the_published_size(one_torch_thread):
    """The speed peer: Depth Anything V2 Small's architecture (24.8 M parameters), random weights."""
    pytest.importorskip("transformers")
    import torch

    from edge_landing.benchmarks.catalog import CATALOG, PEERS, PrepareConfig, input_hw
    from edge_landing.export.zoo import get_arch
    from edge_landing.runtime.perception.contract import Task

    spec = get_arch("depth-anything-v2-small")
    net = spec.build(Task.DEPTH)
    assert sum(p.numel() for p in net.parameters()) == 24_785_089
    with torch.inference_mode():
        (depth,) = net(torch.zeros(1, 3, 60, 80))
    assert depth.shape == (1, 1, 60, 80)              # resized back from 4x5 patches of 14 pixels
    cfg = PrepareConfig(cache_dir=Path("unused"))
    assert [input_hw(CATALOG[n], cfg) for n in PEERS] == [(518, 518), (240, 320)]
    assert all("random weights" in CATALOG[n].peer_note for n in PEERS)
