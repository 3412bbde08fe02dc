"""A real ONNX graph that sees flat ground below a level camera, whatever the image.

Shared by the soak and autopilot-probe benchmarks and by the streaming-runtime tests: with it the CPU cost
of a run is fusion and plumbing, not the network, and every pixel's true depth is known.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from edge_landing.runtime import DepthConvention, DepthSpec, HvoSpec, InputSpec, Intrinsics, Layout, ModelContract, Mount, Task

__all__ = ["flat_ground_model", "ground_plane_depth"]


def ground_plane_depth(height: int, width: int, agl_m: float, mount: Mount = Mount(),
                       hfov_rad: float = math.radians(90.0)) -> np.ndarray:
    """Planar z-depth (H×W, metres, camera frame) of flat ground ``agl_m`` below a level camera with this
    mount; NaN above the horizon."""
    k = Intrinsics.from_hfov(width, height, hfov_rad)
    rays = k.pixel_rays().reshape(-1, 3).astype(np.float64)
    down = (mount.body_from_camera() @ rays.T)[2]  # body z = down when level
    with np.errstate(divide="ignore"):
        z = np.where(down > 1e-6, agl_m / down, np.nan)
    return z.reshape(height, width).astype(np.float32)


def flat_ground_model(path: Path, height: int = 48, width: int = 64, agl_m: float = 10.0,
                      arch: str = "flat-ground-test", note: str = "flat ground test model") -> Path:
    """Write to ``path`` an ONNX graph whose depth is a flat ground plane ``agl_m`` below the camera (90° hfov,
    default mount) and whose HVO logits say 'horizontal' everywhere, whatever the image (0 × input keeps the
    input in the graph). ``arch`` and ``note`` name it in its contract metadata."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    plane = ground_plane_depth(height, width, agl_m)[None, None]
    logits = np.zeros((1, 3, height, width), np.float32)
    logits[:, 0] = 8.0
    inits = [numpy_helper.from_array(plane, "plane"), numpy_helper.from_array(logits, "logits"),
             numpy_helper.from_array(np.zeros((), np.float32), "zero")]
    nodes = [helper.make_node("ReduceMean", ["image"], ["mean"], axes=[1], keepdims=1),
             helper.make_node("Mul", ["mean", "zero"], ["nothing"]),
             helper.make_node("Add", ["plane", "nothing"], ["depth"]),
             helper.make_node("Add", ["logits", "nothing"], ["hvo_logits"])]
    graph = helper.make_graph(
        nodes, "flat_ground", [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 3, height, width])],
        [helper.make_tensor_value_info("depth", TensorProto.FLOAT, [1, 1, height, width]),
         helper.make_tensor_value_info("hvo_logits", TensorProto.FLOAT, [1, 3, height, width])], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    contract = ModelContract(arch=arch, task=Task.DEPTH_HVO,
                             input=InputSpec(name="image", layout=Layout.NCHW, height=height, width=width),
                             depth=DepthSpec("depth", DepthConvention.METRIC, 0.5, 200.0),
                             hvo=HvoSpec("hvo_logits", Layout.NCHW), source={"note": note})
    for key, value in contract.to_metadata().items():
        model.metadata_props.add(key=key, value=value)
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path
