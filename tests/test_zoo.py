"""The published networks of the zoo: exact parameter counts, key names, shapes, contracts."""
import pytest

torch = pytest.importorskip("torch")

from edge_landing.export.checkpoints import count_parameters  # noqa: E402
from edge_landing.export.zoo import get_arch  # noqa: E402
from edge_landing.export.zoo.densenet import DENSENET169, DenseNet  # noqa: E402
from edge_landing.runtime.core.errors import InputError  # noqa: E402
from edge_landing.runtime.perception.contract import DepthConvention, Layout, Task  # noqa: E402

# Keep torch to one thread in this module (tests/conftest.py).
pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_densedepth_parameter_count_matches_the_paper(densedepth):
    assert count_parameters(densedepth) == 42_657_689
    # The unused classifier is not part of the module (44,322,689 with it).
    assert not any("classifier" in name for name, _ in densedepth.named_parameters())
    assert count_parameters(densedepth) + 1664 * 1000 + 1000 == 44_322_689


def test_densenet169_matches_torchvision_layout():
    net = DenseNet(DENSENET169, with_classifier=True)
    assert count_parameters(net) == 14_149_480      # torchvision's densenet169
    assert net.out_channels == DENSENET169.out_channels == 1664
    names = set(net.state_dict())
    for key in ("features.conv0.weight", "features.norm0.running_var", "features.norm0.num_batches_tracked",
                "features.denseblock1.denselayer6.conv2.weight", "features.denseblock4.denselayer32.norm1.bias",
                "features.transition3.conv.weight", "features.norm5.weight", "classifier.bias"):
        assert key in names, key


def test_densedepth_keys_are_the_authors(densedepth):
    names = set(densedepth.state_dict())
    expected = {"encoder.original_model.features.conv0.weight",
                "encoder.original_model.features.denseblock3.denselayer32.conv2.weight",
                "encoder.original_model.features.transition2.norm.running_mean",
                "encoder.original_model.features.norm5.bias",
                "decoder.conv2.weight", "decoder.conv3.bias"}
    expected |= {f"decoder.up{i}.conv{c}.{p}" for i in range(1, 5) for c in "AB" for p in ("weight", "bias")}
    assert expected <= names
    shapes = {k: tuple(v.shape) for k, v in densedepth.state_dict().items()}
    assert shapes["decoder.conv2.weight"] == (1664, 1664, 1, 1)
    assert shapes["decoder.up1.convA.weight"] == (832, 1920, 3, 3)
    assert shapes["decoder.up4.convA.weight"] == (104, 272, 3, 3)
    assert shapes["decoder.conv3.weight"] == (1, 104, 3, 3)


def test_densedepth_output_is_half_resolution(densedepth):
    with torch.no_grad():
        (y,) = densedepth(torch.rand(1, 3, 64, 96))
    assert y.shape == (1, 1, 32, 48)
    assert torch.isfinite(y).all()


@pytest.mark.parametrize("arch,task,count", [
    ("safeuav-large", Task.HVO, 23_895_107), ("safeuav-large", Task.DEPTH, 23_894_977),
    ("safeuav-small", Task.HVO, 1_029_283), ("safeuav-small", Task.DEPTH, 1_029_249),
])
def test_safeuav_parameter_counts_match_the_paper(arch, task, count):
    assert count_parameters(get_arch(arch).build(task)) == count


@pytest.mark.parametrize("arch", ["safeuav-large", "safeuav-small"])
@pytest.mark.parametrize("task,channels", [(Task.HVO, 3), (Task.DEPTH, 1)])
def test_safeuav_is_nhwc_at_full_resolution(arch, task, channels):
    model = get_arch(arch).build(task).eval()
    with torch.no_grad():
        for h, w in ((32, 48), (24, 40)):
            (y,) = model(torch.rand(1, h, w, 3))
            assert y.shape == (1, h, w, channels)


def test_safeuav_parameter_order_is_the_checkpoint_order():
    large = [n for n, _ in get_arch("safeuav-large").build(Task.HVO).named_parameters()]
    modules = [n.rsplit(".", 1)[0] for n in large[::2]]
    assert modules == (
        [f"downBlock{i}.conv{j}" for i in (1, 2, 3) for j in (1, 2)]
        + [f"bottleneck.dilateLayers.{i}" for i in range(6)]
        + ["bottleneck.finalLayer.convt.upSampleLayer.upSample", "upBlock3.conv1", "upBlock3.conv2",
           "up2.convt.upSampleLayer.upSample", "upBlock2.conv1", "upBlock2.conv2",
           "up1.convt.upSampleLayer.upSample", "upBlock1.conv1", "upBlock1.conv2", "finalConv"])
    small = [n.rsplit(".", 1)[0] for n, _ in get_arch("safeuav-small").build(Task.HVO).named_parameters()][::2]
    assert small == ["down1", "down1pool", "down2", "down2pool", "down3", "down3pool",
                     "dilate1", "dilate2", "dilate3", "dilate4", "dilate5", "dilate6",
                     "up3_tr", "up3", "up2_tr", "up2", "up1_tr", "up1", "finalConv"]


def test_safeuav_large_bottleneck_concatenates_six_dilated_outputs():
    model = get_arch("safeuav-large").build(Task.HVO)
    dilations = [conv.dilation for conv in model.bottleneck.dilateLayers]
    assert dilations == [(d, d) for d in (1, 2, 4, 8, 16, 32)]
    assert model.bottleneck.finalLayer.convt.upSampleLayer.upSample.in_channels == 6 * 512


def test_contracts_follow_design():
    dd = get_arch("densedepth").contract(Task.DEPTH, 480, 640)
    assert dd.input.layout is Layout.NCHW and dd.input.std == (1.0, 1.0, 1.0)
    assert dd.depth.convention is DepthConvention.INVERSE and dd.depth.stride == 2
    assert (dd.depth.min_depth, dd.depth.max_depth) == (0.1, 10.0)
    kitti = get_arch("densedepth").contract(Task.DEPTH, 352, 1216, min_depth=1.0, max_depth=80.0)
    assert (kitti.depth.min_depth, kitti.depth.max_depth) == (1.0, 80.0)
    small = get_arch("safeuav-small")
    assert small.input_hw == (240, 320) and small.size_multiple == 8
    depth = small.contract(Task.DEPTH, 240, 320)
    assert depth.input.layout is Layout.NHWC and depth.depth.layout is Layout.NHWC
    assert depth.depth.convention is DepthConvention.NORMALIZED and depth.depth.max_depth == 323.485
    hvo = get_arch("safeuav-large").contract(Task.HVO, 240, 320)
    assert hvo.hvo.layout is Layout.NHWC and hvo.depth is None and hvo.arch == "safeuav-large"


def test_heads_that_do_not_exist_are_one_clear_error():
    with pytest.raises(InputError, match="densedepth has only a depth head"):
        get_arch("densedepth").build(Task.HVO)
    with pytest.raises(InputError, match="one head per network"):
        get_arch("safeuav-small").build(Task.DEPTH_HVO)
    with pytest.raises(InputError, match="unknown architecture 'unet'"):
        get_arch("unet")
