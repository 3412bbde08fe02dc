"""Multiply-accumulates counted from an ONNX graph (Conv, ConvTranspose, MatMul, Gemm).

Shapes come from shape inference on the FP32 model (ONNX Runtime's symbolic shape inference, which also
folds the constant chains an exporter leaves in front of Pad and Reshape; ``onnx.shape_inference`` as the
fall-back), so the count is what the exported graph really computes at its fixed input size.
One MAC = two FLOPs. Example::

    macs = count_macs("safeuav_small.onnx")
    print(macs.total / 1e9, "GMAC", macs.by_op)
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Dict, List, Optional

import numpy as np

from edge_landing.runtime.core.errors import InputError

COUNTED_OPS = ("Conv", "ConvTranspose", "MatMul", "Gemm")


@dataclass(frozen=True)
class MacCount:
    total: int
    by_op: Dict[str, int] = field(default_factory=dict)
    uncounted: List[str] = field(default_factory=list)   # counted-op nodes whose shapes were unknown

    @property
    def gflop(self) -> float:
        return 2.0 * self.total / 1e9


def _shape_table(model) -> Dict[str, List[Optional[int]]]:
    table: Dict[str, List[Optional[int]]] = {}
    for vi in list(model.graph.input) + list(model.graph.output) + list(model.graph.value_info):
        dims = vi.type.tensor_type.shape.dim
        table[vi.name] = [d.dim_value if d.HasField("dim_value") else None for d in dims]
    for init in model.graph.initializer:
        table[init.name] = list(init.dims)
    return table


def _known(shape: Optional[List[Optional[int]]]) -> bool:
    return shape is not None and all(isinstance(d, int) and d > 0 for d in shape)


def _node_macs(node, shapes) -> Optional[int]:
    """MACs of one node, or None when a needed shape is unknown."""
    get = shapes.get
    if node.op_type == "Conv":
        out, w = get(node.output[0]), get(node.input[1])
        if not (_known(out) and _known(w)):
            return None
        # each output element: Cin/group × kernel MACs; w = [Cout, Cin/group, k...]
        return int(np.prod(out, dtype=np.int64) * np.prod(w[1:], dtype=np.int64))
    if node.op_type == "ConvTranspose":
        x, w = get(node.input[0]), get(node.input[1])
        if not (_known(x) and _known(w)):
            return None
        # each input element is scattered to Cout/group × kernel outputs; w = [Cin, Cout/group, k...]
        return int(np.prod(x, dtype=np.int64) * np.prod(w[1:], dtype=np.int64))
    if node.op_type == "MatMul":
        a, out = get(node.input[0]), get(node.output[0])
        if not (_known(a) and _known(out)):
            return None
        return int(np.prod(out, dtype=np.int64) * a[-1])
    if node.op_type == "Gemm":
        a, out = get(node.input[0]), get(node.output[0])
        if not (_known(a) and _known(out)):
            return None
        trans_a = next((attr.i for attr in node.attribute if attr.name == "transA"), 0)
        return int(np.prod(out, dtype=np.int64) * (a[0] if trans_a else a[1]))
    return 0


def _infer(model):
    import onnx

    try:
        from onnxruntime.tools.symbolic_shape_infer import SymbolicShapeInference

        return SymbolicShapeInference.infer_shapes(model, auto_merge=True)
    except Exception:  # it raises assorted errors on graphs it does not know; ONNX's own pass still works
        return onnx.shape_inference.infer_shapes(model)


def _shapes_by_running(model, names: List[str]) -> Dict[str, List[Optional[int]]]:
    """Last resort for graphs shape inference cannot follow (AdaBins' mViT): run the model once on zeros with
    the tensors in ``names`` added as outputs and read their real shapes."""
    import onnx
    import onnxruntime as ort

    probe = onnx.ModelProto()
    probe.CopyFrom(model)
    existing = {o.name for o in probe.graph.output}
    for name in names:
        if name not in existing:
            probe.graph.output.append(onnx.helper.make_tensor_value_info(name, onnx.TensorProto.FLOAT, None))
    sess = ort.InferenceSession(probe.SerializeToString(), providers=["CPUExecutionProvider"])
    feed = {}
    for inp in sess.get_inputs():
        if not all(isinstance(d, int) for d in inp.shape):
            raise InputError(f"input '{inp.name}' has a dynamic shape {inp.shape}; MACs need a fixed input size")
        feed[inp.name] = np.zeros(inp.shape, dtype=np.float32)
    values = sess.run(list(names), feed)
    return {name: list(v.shape) for name, v in zip(names, values)}


def count_macs(model_or_path) -> MacCount:
    """MACs of one inference of an ONNX model (path or ModelProto) at its fixed input size."""
    import onnx

    if isinstance(model_or_path, (str, os.PathLike)):
        try:
            model = onnx.load(str(model_or_path))
        except Exception as exc:  # onnx raises DecodeError and friends for unreadable files
            raise InputError(f"{model_or_path} is not a readable ONNX file ({str(exc)[:120]})") from None
    else:
        model = model_or_path
    inferred = _infer(model)
    shapes = _shape_table(inferred)
    nodes = [n for n in inferred.graph.node if n.op_type in COUNTED_OPS]
    unknown = [n for n in nodes if _node_macs(n, shapes) is None]
    if unknown:
        wanted = sorted({t for n in unknown for t in (n.input[0], n.output[0]) if t not in shapes or
                         not _known(shapes[t])})
        try:
            shapes.update(_shapes_by_running(model, wanted))
        except InputError:
            raise
        except Exception:  # a graph ONNX Runtime cannot run with extra outputs: those nodes stay uncounted
            pass
    by_op: Dict[str, int] = {}
    uncounted: List[str] = []
    for node in nodes:
        macs = _node_macs(node, shapes)
        if macs is None:
            uncounted.append(node.name or node.op_type)
            continue
        by_op[node.op_type] = by_op.get(node.op_type, 0) + macs
    return MacCount(total=sum(by_op.values()), by_op=by_op, uncounted=uncounted)
