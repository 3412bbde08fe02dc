"""Tiny conv nets and scenes built in code for the quantization and benchmark tests (no torch)."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from edge_landing.evaluation.scene import SceneMeta, SceneWriter
from edge_landing.runtime.core.camera import Intrinsics
from edge_landing.runtime.perception.contract import (
    DepthConvention,
    DepthSpec,
    HvoSpec,
    InputSpec,
    Layout,
    ModelContract,
    Task,
)


def tiny_conv_net(path: Path, task: Task = Task.DEPTH_HVO, height: int = 32, width: int = 48, seed: int = 0,
                  upsample: bool = False) -> Path:
    """conv3×3(3→8)+ReLU, conv3×3(8→8)+ReLU, then 1×1 heads: HVO logits (3) and depth = Softplus(conv)+1 m.

    ``upsample``: the second conv has stride 2 and a ConvTranspose (k3, s2, pads 1, output padding 1) + ReLU
    brings the map back to full size, as in SafeUAV-Net's decoder.
    """
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    rng = np.random.default_rng(seed)

    def weight(name, shape):
        fan_in = int(np.prod(shape[1:]))
        return numpy_helper.from_array((rng.standard_normal(shape) * np.sqrt(2.0 / fan_in)).astype(np.float32), name)

    inits = [weight("w1", (8, 3, 3, 3)), numpy_helper.from_array(np.zeros(8, np.float32), "b1"),
             weight("w2", (8, 8, 3, 3)), numpy_helper.from_array(np.full(8, 0.1, np.float32), "b2"),
             weight("wh", (3, 8, 1, 1)), weight("wd", (1, 8, 1, 1)),
             numpy_helper.from_array(np.array(1.0, np.float32), "one")]
    nodes = [helper.make_node("Conv", ["image", "w1", "b1"], ["c1"], pads=[1, 1, 1, 1], name="conv1"),
             helper.make_node("Relu", ["c1"], ["r1"], name="relu1"),
             helper.make_node("Conv", ["r1", "w2", "b2"], ["c2"], pads=[1, 1, 1, 1], name="conv2",
                              strides=[2, 2] if upsample else [1, 1]),
             helper.make_node("Relu", ["c2"], ["r2"], name="relu2")]
    if upsample:
        inits.append(weight("wt", (8, 8, 3, 3)))
        nodes[-1].output[0] = "r2_low"
        nodes += [helper.make_node("ConvTranspose", ["r2_low", "wt"], ["u"], strides=[2, 2], pads=[1, 1, 1, 1],
                                   output_padding=[1, 1], name="up"),
                  helper.make_node("Relu", ["u"], ["r2"], name="relu_up")]
    outputs = []
    if task.has_hvo:
        nodes.append(helper.make_node("Conv", ["r2", "wh"], ["hvo_logits"], name="hvo_head"))
        outputs.append(helper.make_tensor_value_info("hvo_logits", TensorProto.FLOAT, [1, 3, height, width]))
    if task.has_depth:
        nodes += [helper.make_node("Conv", ["r2", "wd"], ["d0"], name="depth_head"),
                  helper.make_node("Softplus", ["d0"], ["d1"], name="depth_softplus"),
                  helper.make_node("Add", ["d1", "one"], ["depth"], name="depth_offset")]
        outputs.append(helper.make_tensor_value_info("depth", TensorProto.FLOAT, [1, 1, height, width]))
    graph = helper.make_graph(nodes, "tiny-conv", [helper.make_tensor_value_info(
        "image", TensorProto.FLOAT, [1, 3, height, width])], outputs, inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    contract = ModelContract(arch="tiny-conv", task=task,
                             input=InputSpec(name="image", layout=Layout.NCHW, height=height, width=width),
                             depth=DepthSpec("depth", DepthConvention.METRIC, 0.5, 100.0) if task.has_depth else None,
                             hvo=HvoSpec("hvo_logits", Layout.NCHW) if task.has_hvo else None,
                             source={"note": "tiny conv net built in code"})
    for k, v in contract.to_metadata().items():
        model.metadata_props.add(key=k, value=v)
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


def textured_scene(path: Path, frames: int, height: int = 32, width: int = 48, seed: int = 0,
                   black_first: int = 0, ground_truth: bool = True, depth_offset_m: float = 5.0) -> Path:
    """Smooth random colour fields (so convs see structure), optional depth/HVO ground truth.

    ``black_first``: that many all-black frames first, a deliberately bad calibration set.
    """
    rng = np.random.default_rng(seed)
    writer = SceneWriter(path, SceneMeta(intrinsics=Intrinsics.from_hfov(width, height)))
    for i in range(frames):
        if i < black_first:
            rgb = np.zeros((height, width, 3), np.uint8)
        else:
            coarse = rng.uniform(0, 255, (height // 4, width // 4, 3)).astype(np.float32)
            rgb = np.clip(cv2.resize(coarse, (width, height), interpolation=cv2.INTER_CUBIC), 0, 255).astype(np.uint8)
        depth = hvo = None
        if ground_truth:
            depth = (depth_offset_m + rgb[..., 0].astype(np.float32) / 10.0).astype(np.float32)
            hvo = np.argmax(rgb, axis=2).astype(np.uint8)
        writer.write(i, rgb, depth, hvo)
    writer.close()
    return path


def quantized_pair(folder: Path, calib_frames: int = 5, eval_frames: int = 3) -> dict:
    """A tiny depth+HVO FP32 net at 64×96 and its gate-passing INT8 twin (``net.int8.onnx``) in ``folder``."""
    from edge_landing.export.quantize import QuantizeConfig, quantize

    fp32 = tiny_conv_net(folder / "net.onnx", Task.DEPTH_HVO, height=64, width=96)
    scene = textured_scene(folder / "scene", calib_frames + eval_frames, height=64, width=96)
    report = quantize(fp32, folder / "net.int8.onnx", QuantizeConfig(calib_scene=scene, calib_frames=calib_frames,
                                                                     eval_frames=eval_frames, progress=False,
                                                                     speed_gate=False))
    assert report.passed and report.written
    return {"fp32": fp32, "int8": folder / "net.int8.onnx"}
