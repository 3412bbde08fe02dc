"""AdaBins and its EfficientNet-B5 encoder: sizes, names, bins, checkpoints and ONNX export.

The full network (78 M parameters) is built once per module at 80 bins and run at the smallest legal input
(320×448); the 480×640 export through edge-export is marked slow.
"""
import warnings

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from edge_landing.export.checkpoints import count_parameters  # noqa: E402
from edge_landing.export.zoo import get_arch  # noqa: E402
from edge_landing.export.zoo.adabins import (  # noqa: E402
    OLD_KEY_PREFIXES,
    AdaBins,
    check_input_size,
    patch_count,
)
from edge_landing.export.zoo.efficientnet import (  # noqa: E402
    EFFICIENTNET_B5_TF,
    Conv2dSame,
    EfficientNet,
    _same_pad,
    round_filters,
    round_repeats,
)
from edge_landing.runtime.core.errors import InputError  # noqa: E402
from edge_landing.runtime.perception.contract import (  # noqa: E402
    DepthConvention,
    Layout,
    ModelContract,
    Task,
)

SMALLEST_HW = (320, 448)


@pytest.fixture(scope="module", autouse=True)
def _one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def model80():
    torch.manual_seed(0)
    return get_arch("adabins").build(Task.DEPTH, bins=80).eval()


@pytest.fixture(scope="module")
def run80(model80):
    """One forward pass at the smallest legal size, shared by the tests that look at outputs."""
    x = torch.randn(1, 3, *SMALLEST_HW, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        edges, depth = model80(x)
    return x, edges, depth


def _meta_model(bins):
    # Counting parameters needs shapes only: the meta device allocates no memory.
    with torch.device("meta"):
        return AdaBins(bins=bins)


def test_parameter_counts_match_the_reference():
    m = _meta_model(256)
    assert count_parameters(m) == 78_257_328
    assert count_parameters(m, "encoder.") == 28_340_784            # 28.34 M
    assert count_parameters(m, "decoder.") == 43_993_472            # 43.99 M
    assert count_parameters(m, "adaptive_bins_layer.") == 5_890_048  # 5.89 M
    assert count_parameters(m, "conv_out.") == 33_024
    assert count_parameters(_meta_model(80)) == 78_189_392


def test_efficientnet_b5_scaling_facts():
    assert [round_filters(c, 1.6) for c in (32, 16, 24, 40, 80, 112, 192, 320, 1280)] == \
        [48, 24, 40, 64, 128, 176, 304, 512, 2048]
    assert [round_repeats(r, 2.2) for r in (1, 2, 2, 3, 3, 4, 1)] == [3, 5, 5, 7, 7, 9, 3]
    with torch.device("meta"):
        net = EfficientNet(EFFICIENTNET_B5_TF)
    assert [len(stage) for stage in net.blocks] == [3, 5, 5, 7, 7, 9, 3]
    # plus the 2048→1000 classifier this gives the 30.39 M of tf_efficientnet_b5
    assert count_parameters(net) + 2048 * 1000 + 1000 == 30_389_784
    # squeeze-excitation is sized from the block's input channels, not the expanded ones
    assert net.blocks[0][0].se.conv_reduce.out_channels == 12
    assert net.blocks[1][0].se.conv_reduce.out_channels == 6
    assert net.blocks[1][0].conv_pw.out_channels == 144          # 24 × expand ratio 6
    assert net.blocks[1][1].se.conv_reduce.out_channels == 10
    assert net.blocks[6][2].se.conv_reduce.out_channels == 128
    assert all(m.eps == 1e-3 for m in net.modules() if isinstance(m, torch.nn.BatchNorm2d))


def test_tf_same_padding_puts_the_odd_pixel_after():
    assert _same_pad(8, 5, 2) == (1, 2)
    assert _same_pad(8, 3, 2) == (0, 1)
    assert _same_pad(7, 3, 2) == (1, 1)
    assert _same_pad(9, 3, 1) == (1, 1)
    conv = Conv2dSame(1, 1, 3, stride=2)
    with torch.no_grad():
        conv.weight.zero_()
        conv.weight[0, 0, 0, 0] = 1.0      # picks the top-left tap: output[i, j] = padded[2i, 2j]
        x = torch.arange(1.0, 37.0).reshape(1, 1, 6, 6)
        y = conv(x)
    assert y.shape[-2:] == (3, 3)            # ceil(6 / 2)
    assert torch.equal(y[0, 0], x[0, 0, ::2, ::2])   # no padding before: the first tap is pixel (0, 0)


def test_checkpoint_key_names_are_the_authors():
    keys = set(_meta_model(80).state_dict())
    for key in ("encoder.original_model.conv_stem.weight", "encoder.original_model.bn1.running_var",
                "encoder.original_model.blocks.0.0.conv_dw.weight", "encoder.original_model.blocks.0.1.conv_pw.weight",
                "encoder.original_model.blocks.1.0.conv_pwl.weight", "encoder.original_model.blocks.6.2.bn3.bias",
                "encoder.original_model.blocks.3.6.se.conv_reduce.bias",
                "encoder.original_model.blocks.5.8.se.conv_expand.weight",
                "encoder.original_model.conv_head.weight", "encoder.original_model.bn2.weight",
                "decoder.conv2.weight", "decoder.up4._net.4.running_mean", "decoder.up1._net.3.bias",
                "decoder.conv3.weight", "adaptive_bins_layer.patch_transformer.positional_encodings",
                "adaptive_bins_layer.patch_transformer.embedding_convPxP.weight",
                "adaptive_bins_layer.patch_transformer.transformer_encoder.layers.3.self_attn.in_proj_weight",
                "adaptive_bins_layer.conv3x3.weight", "adaptive_bins_layer.regressor.4.bias", "conv_out.0.weight"):
        assert key in keys, key
    assert not any("classifier" in k for k in keys)


def test_forward_gives_ordered_bins_and_depth_inside_them(run80):
    _, edges, depth = run80
    assert edges.shape == (1, 81) and depth.shape == (1, 1, 160, 224)
    assert edges[0, 0].item() == pytest.approx(1e-3)
    assert edges[0, -1].item() == pytest.approx(10.0, rel=1e-5)
    widths = edges[0, 1:] - edges[0, :-1]
    assert (widths > 0).all()
    # depth is a convex combination of the bin centres
    centres = 0.5 * (edges[0, 1:] + edges[0, :-1])
    assert centres.min() <= depth.min() and depth.max() <= centres.max()


def test_input_size_rules():
    assert patch_count(480, 640) == 300 and patch_count(*SMALLEST_HW) == 140
    check_input_size(*SMALLEST_HW)
    check_input_size(320, 416)                       # 130 patches: still legal
    with pytest.raises(InputError, match="at least 129"):
        check_input_size(288, 416)                   # 117 patches
    with pytest.raises(InputError, match="at most 500"):
        check_input_size(704, 1024)
    with pytest.raises(InputError, match="multiples of 32"):
        check_input_size(330, 448)


def test_contract_describes_the_metric_depth_output():
    spec = get_arch("adabins")
    c = spec.contract(Task.DEPTH, 480, 640, bins=80, max_depth=80.0)
    assert c.input.layout is Layout.NCHW and c.input.scale == pytest.approx(1 / 255)
    assert c.input.mean == (0.485, 0.456, 0.406) and c.input.std == (0.229, 0.224, 0.225)
    assert c.depth.convention is DepthConvention.METRIC and c.depth.stride == 2
    assert (c.depth.output, c.depth.min_depth, c.depth.max_depth) == ("depth", 1e-3, 80.0)
    assert spec.output_names(Task.DEPTH) == ("bin_edges", "depth")
    assert ModelContract.from_metadata(c.to_metadata()) == c
    with pytest.raises(InputError, match="only a depth head"):
        spec.contract(Task.HVO, 480, 640)


def _old_name(key):
    for old, new in OLD_KEY_PREFIXES:
        if key.startswith(new):
            return old + key[len(new):]
    return key


def test_checkpoint_formats_load(tmp_path, model80):
    spec = get_arch("adabins")
    torch.manual_seed(5)
    target = spec.build(Task.DEPTH, bins=80)
    source = model80.state_dict()
    # the authors' training checkpoint: nested under 'model', DataParallel prefixes, older mViT names
    authors = {"module." + _old_name(k): v for k, v in source.items()}
    assert sum(k.startswith("module.adaptive_bins_layer.embedding_conv.") for k in authors) == 2
    torch.save({"model": authors, "optimizer": {"state": {}, "param_groups": []}, "epoch": 24}, tmp_path / "ab.pt")
    info = spec.load_checkpoint(target, tmp_path / "ab.pt")
    assert info["epoch"] == 24 and info["renamed_old_keys"] == 4 and len(info["sha256"]) == 64
    loaded = target.state_dict()
    assert all(torch.equal(loaded[k], v) for k, v in source.items())
    # a bare state_dict with current names; two tensors changed so that the second load is visible
    plain = dict(source)
    plain["conv_out.0.bias"] = source["conv_out.0.bias"] + 1.0
    plain["encoder.original_model.bn1.running_mean"] = source["encoder.original_model.bn1.running_mean"] - 2.0
    torch.save(plain, tmp_path / "plain.pth")
    info = spec.load_checkpoint(target, tmp_path / "plain.pth")
    assert info["renamed_old_keys"] == 0
    loaded = target.state_dict()
    assert all(torch.equal(loaded[k], v) for k, v in plain.items())


def test_checkpoint_mismatch_names_parameter_and_both_shapes(tmp_path, model80):
    # a 256-bin checkpoint given to the 80-bin network
    torch.save({"model": {"module.conv_out.0.weight": torch.zeros(256, 128, 1, 1)}}, tmp_path / "ab256.pt")
    with pytest.raises(InputError, match=r"'conv_out\.0\.weight' has shape \[256, 128, 1, 1\].*\[80, 128, 1, 1\]"):
        get_arch("adabins").load_checkpoint(model80, tmp_path / "ab256.pt")
    torch.save({"model": {"decoder.conv3.weight": torch.zeros(128, 128, 3, 3)}}, tmp_path / "partial.pt")
    with pytest.raises(InputError, match="missing"):
        get_arch("adabins").load_checkpoint(model80, tmp_path / "partial.pt")


def test_legacy_onnx_export_matches_pytorch_at_the_smallest_size(tmp_path, model80, run80):
    ort = pytest.importorskip("onnxruntime")
    x, edges, depth = run80
    path = tmp_path / "adabins80.onnx"
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")   # the legacy exporter's deprecation and constant-folding notes
        torch.onnx.export(model80, (x,), str(path), dynamo=False, opset_version=17, input_names=["image"],
                          output_names=["bin_edges", "depth"])
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    got_edges, got_depth = session.run(["bin_edges", "depth"], {"image": x.numpy()})
    for got, want in ((got_edges, edges.numpy()), (got_depth, depth.numpy())):
        assert got.shape == want.shape
        assert np.max(np.abs(got - want)) / np.max(np.abs(want)) < 1e-3
    # random weights give a nearly flat depth map: compare with its spread as well, not just its size
    assert np.max(np.abs(got_depth - depth.numpy())) < 1e-2 * float(depth.max() - depth.min())


@pytest.mark.slow
@pytest.mark.parametrize("bins,hw", [(80, SMALLEST_HW), (256, (480, 640))])
def test_edge_export_writes_a_verified_contract_model(tmp_path, bins, hw):
    from edge_landing.export.onnx_export import ExportSettings, export_onnx
    from edge_landing.runtime.perception.inference import OnnxModel

    out = tmp_path / f"adabins{bins}.onnx"
    report = export_onnx(get_arch("adabins"), Task.DEPTH, out, *hw, options={"bins": bins},
                         settings=ExportSettings(progress=False))
    assert report.max_rel_error < 1e-3
    assert report.output_shapes == {"bin_edges": (1, bins + 1), "depth": (1, 1, hw[0] // 2, hw[1] // 2)}
    contract = OnnxModel.load(out).contract
    assert contract.arch == "adabins" and contract.depth.convention is DepthConvention.METRIC
