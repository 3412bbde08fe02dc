"""Tiny models and scenes built in code, shared by the tests (no torch needed)."""
from __future__ import annotations

from pathlib import Path

from edge_landing.runtime.perception.contract import (
    DepthConvention,
    DepthSpec,
    HvoSpec,
    InputSpec,
    Layout,
    ModelContract,
    Task,
)


def tiny_onnx_model(path: Path, height: int = 16, width: int = 24, task: Task = Task.DEPTH_HVO,
                    depth_gain: float = 1.0, layout: Layout = Layout.NCHW, contract: bool = True,
                    convention: DepthConvention = DepthConvention.METRIC, max_depth: float = 100.0) -> Path:
    """An ONNX model whose outputs are known exactly (NCHW input x, already scaled by 1/255):

    depth = depth_gain * (1 + x_red*255)   (metres before decoding, so depth - 1 = red channel value)
    hvo logits = 10 * x   (so the argmax class is the brightest of R, G, B)
    """
    import onnx
    from onnx import TensorProto, helper

    nodes, outputs = [], []
    in_shape = [1, 3, height, width] if layout is Layout.NCHW else [1, height, width, 3]
    x_name = "image"
    if layout is Layout.NHWC:
        nodes.append(helper.make_node("Transpose", ["image"], ["x_nchw"], perm=[0, 3, 1, 2]))
        x_name = "x_nchw"
    inits = [helper.make_tensor("c255", TensorProto.FLOAT, [], [255.0 * depth_gain]),
             helper.make_tensor("gain", TensorProto.FLOAT, [], [depth_gain]),
             helper.make_tensor("ten", TensorProto.FLOAT, [], [10.0]),
             helper.make_tensor("starts", TensorProto.INT64, [1], [0]),
             helper.make_tensor("ends", TensorProto.INT64, [1], [1]),
             helper.make_tensor("axes", TensorProto.INT64, [1], [1])]
    if task.has_depth:
        nodes += [helper.make_node("Slice", [x_name, "starts", "ends", "axes"], ["red"]),
                  helper.make_node("Mul", ["red", "c255"], ["red_scaled"]),
                  helper.make_node("Add", ["red_scaled", "gain"], ["depth"])]
        outputs.append(helper.make_tensor_value_info("depth", TensorProto.FLOAT, [1, 1, height, width]))
    if task.has_hvo:
        nodes.append(helper.make_node("Mul", [x_name, "ten"], ["hvo_logits"]))
        outputs.append(helper.make_tensor_value_info("hvo_logits", TensorProto.FLOAT, [1, 3, height, width]))
    graph = helper.make_graph(nodes, "tiny", [helper.make_tensor_value_info("image", TensorProto.FLOAT, in_shape)],
                              outputs, inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    if contract:
        c = ModelContract(
            arch="tiny-test", task=task, input=InputSpec(name="image", layout=layout, height=height, width=width),
            depth=DepthSpec("depth", convention, 0.5, max_depth) if task.has_depth else None,
            hvo=HvoSpec("hvo_logits", Layout.NCHW) if task.has_hvo else None,
            source={"note": "tiny test model built in code"})
        for k, v in c.to_metadata().items():
            model.metadata_props.add(key=k, value=v)
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


def one_line_error(capsys, main, argv, *expected: str) -> str:
    """Run a CLI ``main(argv)``: exit 2, exactly one stderr line holding every ``expected`` text, no traceback
    or usage dump (ARCHITECTURE.md §10). Returns the line."""
    assert main([str(a) for a in argv]) == 2, argv
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err and "usage:" not in err, err
    for text in expected:
        assert text in err, err
    return err
