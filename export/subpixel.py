"""Rewrite strided ConvTranspose as Conv + depth-to-space + Slice ("sub-pixel" convolution), exactly.

ONNX Runtime's CPU provider runs ConvTranspose through a slow col2im path and has no int8 kernel for it, so
in a quantized graph it stays float and is often the largest single cost (SafeUAV-Net's decoders). A
ConvTranspose with stride s is the same as s×s small convolutions over the input, one per output phase,
whose outputs interleave: one Conv with s²·Cout channels, a depth-to-space (Reshape, Transpose, Reshape) and
a crop. That Conv is an
ordinary one, so it quantizes to QLinearConv. Only group=1, dilation 1, equal strides, explicit pads and
constant weights are rewritten; anything else is left as it is. Example::

    model = onnx.load("m.onnx")
    count = rewrite_conv_transposes(model)     # in place; returns how many nodes were rewritten
"""
from __future__ import annotations

from typing import Dict, List, Optional, Tuple

import numpy as np


def _attrs(node) -> dict:
    from onnx import helper

    return {a.name: helper.get_attribute_value(a) for a in node.attribute}


def _phase_taps(s: int, k: int, pad_begin: int) -> Tuple[int, int]:
    """Input-row offsets d (output row s·m + a reads input row m + d) used by any phase: (lowest, highest)."""
    ds = [(a + pad_begin - t) // s for a in range(s) for t in range(k) if (a + pad_begin - t) % s == 0]
    return min(0, min(ds)), max(0, max(ds))


def subpixel_weights(w: np.ndarray, b: Optional[np.ndarray], s: int, pads: Tuple[int, int]
                     ) -> Tuple[np.ndarray, np.ndarray, Tuple[int, int], Tuple[int, int]]:
    """ConvTranspose weights [Cin, Cout, kH, kW] -> Conv weights [Cout·s², Cin, KH, KW], bias, and the
    lowest/highest tap offsets per axis. Channel o·s² + a·s + c holds output phase (a, c) of channel o."""
    cin, cout, kh, kw = w.shape
    (lo_h, hi_h), (lo_w, hi_w) = _phase_taps(s, kh, pads[0]), _phase_taps(s, kw, pads[1])
    w2 = np.zeros((cout * s * s, cin, hi_h - lo_h + 1, hi_w - lo_w + 1), dtype=w.dtype)
    for a in range(s):
        for c in range(s):
            for th in range(hi_h - lo_h + 1):
                ky = a + pads[0] - s * (lo_h + th)
                if not 0 <= ky < kh:
                    continue
                for tw in range(hi_w - lo_w + 1):
                    kx = c + pads[1] - s * (lo_w + tw)
                    if 0 <= kx < kw:
                        w2[a * s + c::s * s, :, th, tw] = w[:, :, ky, kx].T
    b2 = np.repeat(b if b is not None else np.zeros(cout, w.dtype), s * s).astype(w.dtype)
    return w2, b2, (lo_h, hi_h), (lo_w, hi_w)


def _rewritable(node, attrs: dict, inits: Dict[str, np.ndarray], shapes: Dict[str, list]) -> Optional[str]:
    """None when the node can be rewritten, else why not."""
    if attrs.get("group", 1) != 1:
        return "grouped"
    if any(d != 1 for d in attrs.get("dilations", [1, 1])):
        return "dilated"
    if attrs.get("auto_pad", b"NOTSET") not in (b"NOTSET", "NOTSET") or "output_shape" in attrs:
        return "auto_pad/output_shape"
    strides = attrs.get("strides", [1, 1])
    if len(strides) != 2 or strides[0] != strides[1] or strides[0] < 2:
        return f"strides {strides}"
    if node.input[1] not in inits or (len(node.input) > 2 and node.input[2] and node.input[2] not in inits):
        return "weights are not constant"
    x = shapes.get(node.input[0])
    if not x or len(x) != 4 or not all(isinstance(d, int) and d > 0 for d in x[2:]):
        return "input size unknown"
    return None


def rewrite_conv_transposes(model) -> int:
    """Rewrite every eligible ConvTranspose of ``model`` in place; returns the number rewritten."""
    import onnx
    from onnx import helper, numpy_helper

    inferred = onnx.shape_inference.infer_shapes(model)
    shapes = {vi.name: [d.dim_value if d.HasField("dim_value") else None for d in vi.type.tensor_type.shape.dim]
              for vi in list(inferred.graph.value_info) + list(inferred.graph.input)}
    inits = {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}
    new_nodes: List = []
    count = 0
    for node in model.graph.node:
        attrs = _attrs(node) if node.op_type == "ConvTranspose" else {}
        if node.op_type != "ConvTranspose" or _rewritable(node, attrs, inits, shapes) is not None:
            new_nodes.append(node)
            continue
        s = attrs["strides"][0]
        pads = attrs.get("pads", [0, 0, 0, 0])
        out_pad = attrs.get("output_padding", [0, 0])
        w = inits[node.input[1]]
        b = inits[node.input[2]] if len(node.input) > 2 and node.input[2] else None
        h_in, w_in = shapes[node.input[0]][2:]
        kh, kw = w.shape[2:]
        out_h = (h_in - 1) * s - pads[0] - pads[2] + kh + out_pad[0]
        out_w = (w_in - 1) * s - pads[1] - pads[3] + kw + out_pad[1]
        w2, b2, (lo_h, hi_h), (lo_w, hi_w) = subpixel_weights(w, b, s, (pads[0], pads[1]))
        rows, cols = -(-out_h // s), -(-out_w // s)          # conv output size so that s·size covers the output
        conv_pads = [-lo_h, -lo_w, hi_h + rows - h_in, hi_w + cols - w_in]
        base = node.name or f"ConvTranspose_{count}"
        names = {k: f"{base}_subpixel_{k}" for k in ("w", "b", "conv", "d2s", "starts", "ends", "axes", "shape6",
                                                     "shape4", "r6", "t6")}
        cout = w2.shape[0] // (s * s)
        model.graph.initializer.extend([numpy_helper.from_array(w2, names["w"]), numpy_helper.from_array(b2, names["b"])])
        crop = (rows * s, cols * s) != (out_h, out_w)
        d2s_out = names["d2s"] if crop else node.output[0]
        new_nodes.append(helper.make_node("Conv", [node.input[0], names["w"], names["b"]], [names["conv"]],
                                          name=f"{base}_subpixel_conv", kernel_shape=list(w2.shape[2:]),
                                          pads=conv_pads))
        # DepthToSpace(CRD) spelt as Reshape -> Transpose -> Reshape: ONNX Runtime's quantizer keeps those in
        # uint8, while a DepthToSpace would be dequantized to float and back around it.
        model.graph.initializer.extend([
            numpy_helper.from_array(np.array([0, cout, s, s, rows, cols], np.int64), names["shape6"]),
            numpy_helper.from_array(np.array([0, cout, rows * s, cols * s], np.int64), names["shape4"])])
        new_nodes += [helper.make_node("Reshape", [names["conv"], names["shape6"]], [names["r6"]],
                                       name=f"{base}_subpixel_split"),
                      helper.make_node("Transpose", [names["r6"]], [names["t6"]], perm=[0, 1, 4, 2, 5, 3],
                                       name=f"{base}_subpixel_interleave"),
                      helper.make_node("Reshape", [names["t6"], names["shape4"]], [d2s_out],
                                       name=f"{base}_subpixel_merge")]
        if crop:
            model.graph.initializer.extend([numpy_helper.from_array(np.array(v, np.int64), names[k]) for k, v in
                                            (("starts", [0, 0]), ("ends", [out_h, out_w]), ("axes", [2, 3]))])
            new_nodes.append(helper.make_node("Slice", [d2s_out, names["starts"], names["ends"], names["axes"]],
                                              [node.output[0]], name=f"{base}_subpixel_crop"))
        count += 1
    del model.graph.node[:]
    model.graph.node.extend(new_nodes)
    used = {i for n in model.graph.node for i in n.input}
    keep = [i for i in model.graph.initializer if i.name in used]   # the ConvTranspose weights are gone now
    del model.graph.initializer[:]
    model.graph.initializer.extend(keep)
    return count
