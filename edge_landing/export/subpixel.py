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
    # Dimensions are int or None (unknown); _rewritable only passes nodes whose input sizes are known ints.
    shapes: Dict[str, list] = {vi.name: [d.dim_value if d.HasField("dim_value") else None for d in vi.type.tensor_type.shape.dim]
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
    fold_crop_pad(model)
    used = {i for n in model.graph.node for i in n.input}
    keep = [i for i in model.graph.initializer if i.name in used]   # the ConvTranspose weights are gone now
    del model.graph.initializer[:]
    model.graph.initializer.extend(keep)
    return count


def fold_crop_pad(model) -> int:
    """Fold ``crop -> [Relu] -> zero Pad back to the uncropped size`` into ``[Relu] -> Mul(0/1 mask)``.

    SafeUAV-Net pads each transposed convolution's output by one zero row and column. After the rewrite
    above that becomes a crop of the depth-to-space output immediately padded back: two copies of the whole
    map, each of which also forces ONNX Runtime to change layout around it in the int8 graph. Multiplying by a
    mask whose cropped rows and columns are 0 is the same function in one element-wise op (mask 0/1 quantizes
    exactly). Only exact matches are folded (constant pads, zero value, restoring exactly what was cropped).
    Returns the number folded.
    """
    from onnx import numpy_helper

    inits = {i.name: i for i in model.graph.initializer}
    consumers: Dict[str, List] = {}
    for n in model.graph.node:
        for i in n.input:
            consumers.setdefault(i, []).append(n)
    graph_outputs = {o.name for o in model.graph.output}
    removed, stale, count = set(), set(), 0
    for crop in list(model.graph.node):
        if crop.op_type != "Slice" or not crop.name.endswith("_subpixel_crop"):
            continue
        chain = _single_consumer_chain(crop.output[0], consumers, graph_outputs)
        if chain is None:
            continue
        relu, pad = chain
        folded = _crop_pad_mask(crop, pad, inits)
        if folded is None:
            continue
        mask_name = f"{crop.name}_mask"
        model.graph.initializer.append(numpy_helper.from_array(folded, mask_name))
        if relu is not None:
            relu.input[0] = crop.input[0]
            source = relu.output[0]
            stale.add(source)   # its recorded shape was the cropped one
        else:
            source = crop.input[0]
        pad.op_type, pad.name = "Mul", f"{crop.name}_as_mask"
        del pad.input[:]
        pad.input.extend([source, mask_name])
        del pad.attribute[:]
        removed.add(id(crop))
        count += 1
    if count:
        infos = [vi for vi in model.graph.value_info if vi.name not in stale]
        del model.graph.value_info[:]
        model.graph.value_info.extend(infos)
        kept = [n for n in model.graph.node if id(n) not in removed]
        del model.graph.node[:]
        model.graph.node.extend(kept)
        used = {i for n in model.graph.node for i in n.input}
        keep = [i for i in model.graph.initializer if i.name in used]
        del model.graph.initializer[:]
        model.graph.initializer.extend(keep)
    return count


def _single_consumer_chain(name: str, consumers: Dict[str, List], graph_outputs: set):
    """(relu or None, pad) when ``name`` feeds exactly one Pad, optionally through exactly one Relu."""
    if name in graph_outputs or len(consumers.get(name, [])) != 1:
        return None
    node = consumers[name][0]
    relu = None
    if node.op_type == "Relu":
        relu = node
        if relu.output[0] in graph_outputs or len(consumers.get(relu.output[0], [])) != 1:
            return None
        node = consumers[relu.output[0]][0]
    return (relu, node) if node.op_type == "Pad" else None


def _crop_pad_mask(crop, pad, inits) -> Optional[np.ndarray]:
    """The 0/1 mask [1, 1, H, W] equivalent to ``crop`` then ``pad``, or None when they are not inverse."""
    from onnx import helper, numpy_helper

    attrs = {a.name: helper.get_attribute_value(a) for a in pad.attribute}
    if attrs.get("mode", b"constant") not in (b"constant", "constant") or len(pad.input) < 2:
        return None
    if len(pad.input) > 2 and pad.input[2]:
        value = inits.get(pad.input[2])
        if value is None or float(numpy_helper.to_array(value).ravel()[0]) != 0.0:
            return None
    if len(pad.input) > 3 and pad.input[3]:
        return None   # explicit axes: not the plain 4-D form
    pads_init, ends_init = inits.get(pad.input[1]), inits.get(crop.input[2])
    starts_init, axes_init = inits.get(crop.input[1]), inits.get(crop.input[3]) if len(crop.input) > 3 else None
    if pads_init is None or ends_init is None or starts_init is None or axes_init is None:
        return None
    pads = numpy_helper.to_array(pads_init).astype(np.int64).ravel()
    starts, ends = numpy_helper.to_array(starts_init).ravel(), numpy_helper.to_array(ends_init).ravel()
    if len(pads) != 8 or list(numpy_helper.to_array(axes_init).ravel()) != [2, 3] or any(starts != 0):
        return None
    if any(pads[:6] != 0):
        return None   # padding anywhere but the end of H and W
    out_h, out_w = int(ends[0]), int(ends[1])
    full_h, full_w = out_h + int(pads[6]), out_w + int(pads[7])
    shape4 = inits.get(crop.name[: -len("_crop")] + "_shape4")   # the depth-to-space output [0, C, H, W]
    if shape4 is None or list(numpy_helper.to_array(shape4).ravel()[2:]) != [full_h, full_w]:
        return None   # the pad does not restore exactly what the crop removed
    mask = np.ones((1, 1, full_h, full_w), np.float32)
    mask[..., out_h:, :] = 0.0
    mask[..., :, out_w:] = 0.0
    return mask
