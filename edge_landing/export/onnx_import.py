"""Back from a shipped EdgeNet ONNX file to a trainable checkpoint (for fine-tuning with ``edge-train --init``).

The export folds every BatchNorm into its convolution, so the ONNX file holds 17 convolutions with bias and
no BatchNorm. The torch EdgeNet's convolutions, taken in forward order, match the ONNX Conv nodes in graph
order (shapes are checked one by one). Each fused (W, b) goes back as conv weight W, and the BatchNorm after it
is set from data so that it is the identity-plus-bias both in eval mode (exactly) and in train mode
(approximately): running mean μ and variance σ² of the conv's output over a few frames, γ = √(σ² + ε),
β = b + μ, so γ(x − μ)/√(σ² + ε) + β = x + b. Without that step, train-mode BatchNorm would renormalise every
channel and fine-tuning would start from a different network.

    python -m edge_landing.export.onnx_import edge_landing/runtime/models/edgenet.onnx --scene scenes/val_sub20 \\
        --out runs/shipped.pth
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Optional, Sequence, cast

import numpy as np
import torch
from torch import nn

from edge_landing.cli.common import CliParser, run_cli
from edge_landing.runtime.core.errors import InputError


def _onnx_convs(path: Path) -> list[tuple[np.ndarray, Optional[np.ndarray]]]:
    import onnx
    from onnx import numpy_helper

    graph = onnx.load(str(path)).graph
    inits = {i.name: numpy_helper.to_array(i) for i in graph.initializer}
    out = []
    for node in graph.node:
        if node.op_type == "Conv":
            w = inits[node.input[1]]
            b = inits[node.input[2]] if len(node.input) > 2 and node.input[2] in inits else None
            out.append((w, b))
    return out


def _forward_convs(model: nn.Module, x: torch.Tensor) -> list[nn.Conv2d]:
    order: list[nn.Conv2d] = []
    hooks = [m.register_forward_hook(lambda mod, _i, _o: order.append(mod)) for m in model.modules()
             if isinstance(m, nn.Conv2d)]
    with torch.no_grad():
        model(x)
    for h in hooks:
        h.remove()
    return order


def import_onnx(path: Path, frames: torch.Tensor) -> nn.Module:
    """An EdgeNet (torch) equal to the ONNX file; ``frames`` N×3×H×W normalised input for the BN statistics."""
    from edge_landing.export.zoo import edgenet
    from edge_landing.runtime.perception.contract import Task

    meta = json.loads((path.with_suffix(".json")).read_text()) if path.with_suffix(".json").exists() else {}
    model = edgenet.build(Task.DEPTH_HVO, **meta.get("options", {})).eval()
    convs = _forward_convs(model, frames[:1])
    fused = _onnx_convs(path)
    if len(convs) != len(fused):
        raise InputError(f"{path}: {len(fused)} Conv nodes but EdgeNet has {len(convs)} convolutions")
    bn_after: dict[int, nn.BatchNorm2d] = {id(m[0]): cast(nn.BatchNorm2d, m[1]) for m in model.modules()
                                           if isinstance(m, edgenet.ConvBNReLU)}
    biases: dict[int, torch.Tensor] = {}
    with torch.no_grad():
        for conv, (w, b) in zip(convs, fused):
            if tuple(conv.weight.shape) != w.shape:
                raise InputError(f"{path}: conv shape {w.shape} where EdgeNet has {tuple(conv.weight.shape)}")
            conv.weight.copy_(torch.from_numpy(np.array(w)))       # a writable copy
            bias = torch.from_numpy(np.array(b)) if b is not None else torch.zeros(w.shape[0])
            bn = bn_after.get(id(conv))
            if bn is None:
                assert conv.bias is not None
                conv.bias.copy_(bias)
                continue
            bn.weight.fill_(1.0)
            bn.bias.copy_(bias)
            assert bn.running_mean is not None and bn.running_var is not None   # EdgeNet tracks statistics
            bn.running_mean.zero_()
            bn.running_var.fill_(1.0 - bn.eps)
            biases[id(bn)] = bias
        # Conv-output statistics with the exact (eval) network, then the data-matched BatchNorm.
        stats: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}
        hooks = [bn.register_forward_hook(lambda mod, inp, _o: stats.__setitem__(
            id(mod), (inp[0].mean(dim=(0, 2, 3)), inp[0].var(dim=(0, 2, 3), unbiased=False))))
            for bn in bn_after.values()]
        model(frames)
        for h in hooks:
            h.remove()
        for bn in bn_after.values():
            mu, var = stats[id(bn)]
            assert bn.running_mean is not None and bn.running_var is not None
            bn.running_mean.copy_(mu)
            bn.running_var.copy_(var)
            bn.weight.copy_(torch.sqrt(var + bn.eps))
            bn.bias.copy_(biases[id(bn)] + mu)
    return model


def _frames(scene: str, n: int, hw: tuple[int, int]) -> torch.Tensor:
    import cv2

    from edge_landing.evaluation.scene import Scene

    s = Scene(scene)
    mean, std = np.array([0.485, 0.456, 0.406], np.float32), np.array([0.229, 0.224, 0.225], np.float32)
    imgs = [(cv2.resize(s.read_rgb(f), (hw[1], hw[0]), interpolation=cv2.INTER_AREA) / 255.0 - mean) / std
            for f in s.frame_ids[:n]]
    return torch.from_numpy(np.stack(imgs).transpose(0, 3, 1, 2).astype(np.float32))


def _main(argv: Optional[Sequence[str]] = None) -> int:
    p = CliParser(prog="onnx_import", description=__doc__.split("\n\n")[0])
    p.add_argument("model", type=Path)
    p.add_argument("--scene", required=True, help="scene whose first frames set the BatchNorm statistics")
    p.add_argument("--frames", type=int, default=16)
    p.add_argument("--out", required=True, type=Path)
    args = p.parse_args(argv)
    x = _frames(args.scene, args.frames, (240, 320))
    model = import_onnx(args.model, x)
    import onnxruntime as ort

    sess = ort.InferenceSession(str(args.model), providers=["CPUExecutionProvider"])
    ref = sess.run(None, {sess.get_inputs()[0].name: x[:1].numpy()})      # the export has batch 1
    with torch.no_grad():
        got = model(x[:1])
    diffs = [float(np.max(np.abs(r - g.numpy()) / (np.abs(r) + 1e-3))) for r, g in zip(ref, got)]
    print(f"max relative difference to the ONNX outputs (eval mode): {', '.join(f'{d:.2e}' for d in diffs)}")
    torch.save({"model": model.state_dict(), "source": str(args.model)}, args.out)
    print(f"wrote {args.out}")
    return 0


def main(argv: Optional[Sequence[str]] = None) -> int:
    return run_cli(_main, argv)


if __name__ == "__main__":
    raise SystemExit(main())
