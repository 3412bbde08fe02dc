import numpy as np
import pytest

from edge_landing.runtime.core.errors import ContractError, InputError
from edge_landing.runtime.perception.contract import Layout, ModelContract, Task
from edge_landing.runtime.perception.inference import OnnxModel
from tests.helpers import tiny_onnx_model


@pytest.mark.parametrize("layout", [Layout.NCHW, Layout.NHWC])
def test_predict_decodes_depth_and_hvo_from_metadata(tmp_path, layout):
    path = tiny_onnx_model(tmp_path / "m.onnx", layout=layout)
    model = OnnxModel.load(path)
    rgb = np.zeros((16, 24, 3), np.uint8)
    rgb[..., 0] = 7
    rgb[:, 12:, 1] = 200
    pred = model.predict(rgb, frame_id=3, capture_time_s=1.5)
    assert pred.valid and pred.frame_id == 3
    np.testing.assert_allclose(pred.depth_m, 8.0, rtol=1e-5)
    labels = pred.hvo_prob.argmax(axis=2)
    assert (labels[:, :12] == 0).all() and (labels[:, 12:] == 1).all()
    np.testing.assert_allclose(pred.hvo_prob.sum(axis=2), 1.0, rtol=1e-5)


def test_predict_resizes_any_frame_and_scales(tmp_path):
    model = OnnxModel.load(tiny_onnx_model(tmp_path / "m.onnx"))
    rgb = np.full((48, 72, 3), 3, np.uint8)
    pred = model.predict(rgb, out_hw=(48, 72), scale=2.0)
    assert pred.depth_m.shape == (48, 72) and pred.hvo_prob.shape == (48, 72, 3)
    np.testing.assert_allclose(pred.depth_m, 8.0, rtol=1e-5)


def test_contract_round_trip(tmp_path):
    model = OnnxModel.load(tiny_onnx_model(tmp_path / "m.onnx"))
    assert ModelContract.from_metadata(model.contract.to_metadata()) == model.contract
    assert model.contract.task is Task.DEPTH_HVO


def test_missing_contract_is_one_clear_error(tmp_path):
    path = tiny_onnx_model(tmp_path / "m.onnx", contract=False)
    with pytest.raises(ContractError, match="no model contract.*edge.arch"):
        OnnxModel.load(path)


def test_truncated_file_is_one_clear_error(tmp_path):
    path = tiny_onnx_model(tmp_path / "m.onnx")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(ContractError, match="not a loadable ONNX model"):
        OnnxModel.load(path)


def test_bad_image_is_rejected(tmp_path):
    model = OnnxModel.load(tiny_onnx_model(tmp_path / "m.onnx"))
    with pytest.raises(InputError, match="H×W×3"):
        model.predict(np.zeros((16, 24), np.uint8))


@pytest.mark.parametrize("layout", [Layout.NCHW, Layout.NHWC])
@pytest.mark.parametrize("color", ["RGB", "BGR"])
def test_preprocess_matches_the_contract_formula(layout, color):
    from edge_landing.runtime.perception.contract import HvoSpec, InputSpec
    from edge_landing.runtime.perception.inference import preprocess

    mean, std = (0.485, 0.456, 0.406), (0.229, 0.224, 0.225)
    contract = ModelContract("t", Task.HVO, InputSpec("image", layout, 12, 20, color=color, mean=mean, std=std),
                             hvo=HvoSpec("h"))
    rgb = np.random.default_rng(1).integers(0, 256, (12, 20, 3), dtype=np.uint8)
    x = preprocess(rgb, contract)
    src = rgb[..., ::-1] if color == "BGR" else rgb
    expected = (src / 255.0 - np.array(mean)) / np.array(std)
    expected = expected.transpose(2, 0, 1)[None] if layout is Layout.NCHW else expected[None]
    assert x.dtype == np.float32 and x.flags["C_CONTIGUOUS"]
    np.testing.assert_allclose(x, expected, atol=1e-5)
