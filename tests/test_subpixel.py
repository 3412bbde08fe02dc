import numpy as np
import onnxruntime as ort
import pytest
from onnx import TensorProto, helper, numpy_helper

from edge_landing.export.subpixel import rewrite_conv_transposes


def _conv_transpose_model(k, s, pads, out_pad, bias=True, group=1, seed=0):
    rng = np.random.default_rng(seed)
    inits = [numpy_helper.from_array(rng.standard_normal((4, 6 // group, k, k)).astype(np.float32), "w")]
    inputs = ["x", "w"]
    if bias:
        inits.append(numpy_helper.from_array(rng.standard_normal(6).astype(np.float32), "b"))
        inputs.append("b")
    node = helper.make_node("ConvTranspose", inputs, ["y"], strides=[s, s], pads=pads, output_padding=[out_pad] * 2,
                            group=group, name="up")
    graph = helper.make_graph([node], "g", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 4, 5, 7])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, None)], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    return model


def _run(model, x):
    return ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"]).run(None, {"x": x})[0]


@pytest.mark.parametrize("k,s,pads,out_pad,bias", [
    (3, 2, [1, 1, 1, 1], 0, True),    # SafeUAV-Net-Small's decoder
    (3, 2, [1, 1, 1, 1], 1, False),
    (3, 2, [0, 0, 0, 0], 0, True),    # SafeUAV-Net-Large's (output 2H+1, cropped)
    (2, 2, [0, 0, 0, 0], 0, True),
    (4, 2, [1, 1, 1, 1], 0, True),
    (3, 3, [1, 1, 1, 1], 0, True),
    (5, 2, [2, 2, 2, 2], 1, True),
    (3, 2, [0, 1, 1, 0], 0, True),    # asymmetric pads
])
def test_subpixel_rewrite_is_exact(k, s, pads, out_pad, bias):
    model = _conv_transpose_model(k, s, pads, out_pad, bias)
    x = np.random.default_rng(1).standard_normal((1, 4, 5, 7)).astype(np.float32)
    before = _run(model, x)
    assert rewrite_conv_transposes(model) == 1
    ops = [n.op_type for n in model.graph.node]
    assert "ConvTranspose" not in ops and ops[:4] == ["Conv", "Reshape", "Transpose", "Reshape"]
    assert {i.name for i in model.graph.initializer}.isdisjoint({"w", "b"})     # old weights dropped
    after = _run(model, x)
    assert after.shape == before.shape
    np.testing.assert_allclose(after, before, atol=1e-5)


def test_grouped_conv_transpose_is_left_alone():
    model = _conv_transpose_model(3, 2, [1, 1, 1, 1], 0, group=2)
    assert rewrite_conv_transposes(model) == 0
    assert [n.op_type for n in model.graph.node] == ["ConvTranspose"]


def _safeuav_small_up_block(pad_end):
    """SafeUAV-Net-Small's up block: ConvTranspose(k3, s2, p1) -> Relu -> zero Pad at the end of H and W."""
    model = _conv_transpose_model(3, 2, [1, 1, 1, 1], 0)
    model.graph.node[0].output[0] = "up_out"
    model.graph.initializer.append(numpy_helper.from_array(np.array([0, 0, 0, 0, 0, 0, pad_end, pad_end],
                                                                    np.int64), "pads"))
    model.graph.node.extend([helper.make_node("Relu", ["up_out"], ["act"]),
                             helper.make_node("Pad", ["act", "pads"], ["y"], mode="constant")])
    return model


def test_crop_then_zero_pad_is_folded_into_a_mask_exactly():
    model = _safeuav_small_up_block(pad_end=1)      # 2H-1 -> padded back to 2H: the crop is undone
    x = np.random.default_rng(5).standard_normal((1, 4, 5, 7)).astype(np.float32)
    ref = _run(model, x)
    assert rewrite_conv_transposes(model) == 1
    ops = [n.op_type for n in model.graph.node]
    assert "Slice" not in ops and "Pad" not in ops and ops.count("Mul") == 1
    got = _run(model, x)
    assert got.shape == ref.shape == (1, 6, 10, 14)
    np.testing.assert_allclose(got, ref, atol=1e-5)
    assert (got[..., -1, :] == 0).all() and (got[..., :, -1] == 0).all()


def test_a_pad_that_does_not_undo_the_crop_is_left_alone():
    model = _safeuav_small_up_block(pad_end=2)      # pads more than the crop removed: not the same function
    x = np.random.default_rng(6).standard_normal((1, 4, 5, 7)).astype(np.float32)
    ref = _run(model, x)
    assert rewrite_conv_transposes(model) == 1
    ops = [n.op_type for n in model.graph.node]
    assert "Slice" in ops and "Pad" in ops and "Mul" not in ops
    np.testing.assert_allclose(_run(model, x), ref, atol=1e-5)
