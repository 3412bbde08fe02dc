"""export/onnx_import.py: the shipped ONNX EdgeNet back into torch, equal in eval mode, close in train mode."""
import numpy as np
import pytest

torch = pytest.importorskip("torch")
ort = pytest.importorskip("onnxruntime")

from edge_landing.export.onnx_import import import_onnx  # noqa: E402
from edge_landing.runtime.models import MODELS_DIR  # noqa: E402


def test_shipped_onnx_comes_back_as_the_same_network():
    path = MODELS_DIR / "edgenet.onnx"
    if not path.exists():
        pytest.skip("edgenet.onnx is not shipped in this installation")
    torch.manual_seed(0)
    # Smooth random images (normalised input), 4 for the BatchNorm statistics.
    x = torch.nn.functional.interpolate(torch.randn(4, 3, 30, 40), size=(240, 320), mode="bilinear")
    model = import_onnx(path, x)
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    ref = sess.run(None, {sess.get_inputs()[0].name: x[:1].numpy()})
    with torch.no_grad():
        got = model(x[:1])
        assert np.allclose(got[0].numpy(), ref[0], rtol=1e-3, atol=1e-3)
        assert np.abs(got[1].numpy() - ref[1]).max() < 1e-2
        model.train()
        train_depth = model(x)[0]
    # Train-mode BatchNorm uses batch statistics; they were matched on these frames, so depth stays close.
    with torch.no_grad():
        model.eval()
        eval_depth = model(x)[0]
    assert float(((train_depth - eval_depth).abs() / eval_depth).median()) < 0.05
