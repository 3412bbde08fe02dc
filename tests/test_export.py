"""edge-export: PyTorch -> ONNX with the model contract, verified with the real ONNX Runtime."""
import numpy as np
import pytest

torch = pytest.importorskip("torch")
onnx = pytest.importorskip("onnx")

from edge_landing.export.cli import main as export_main  # noqa: E402
from edge_landing.export.onnx_export import ExportSettings, export_onnx  # noqa: E402
from edge_landing.export.zoo import get_arch  # noqa: E402
from edge_landing.export.zoo.registry import ArchSpec  # noqa: E402
from edge_landing.runtime.core.errors import ContractError, EdgeError  # noqa: E402
from edge_landing.runtime.perception.contract import (  # noqa: E402
    DepthConvention,
    DepthSpec,
    InputSpec,
    Layout,
    ModelContract,
    Task,
)
from edge_landing.runtime.perception.inference import OnnxModel, file_sha256  # noqa: E402

QUIET = ExportSettings(progress=False, threads=1)


# Keep torch to one thread in this module (tests/conftest.py).
pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _pkl(path, model, key="weights", seed=3):
    """Give ``model`` new weights and save them in SafeUAV's container (ordered tensors under ``key``)."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in model.parameters():
            p.copy_(torch.randn(p.shape, generator=gen) * 0.05)
    torch.save({key: [p.detach().clone() for p in model.parameters()]}, path)
    return path


def _torch_prediction(model, onnx_model, rgb):
    """What the exported file should say, computed with PyTorch and decoded by the same contract."""
    x = onnx_model.prepare(rgb)
    with torch.no_grad():
        outputs = model.eval()(torch.from_numpy(x))
    names = [s.output for s in (onnx_model.contract.depth, onnx_model.contract.hvo) if s is not None]
    return onnx_model.decode(dict(zip(names, (t.numpy() for t in outputs))))


@pytest.fixture(scope="module")
def small_onnx(tmp_path_factory):
    out = tmp_path_factory.mktemp("export") / "small.onnx"
    export_onnx(get_arch("safeuav-small"), Task.HVO, out, 32, 48, settings=QUIET)
    return out


@pytest.mark.parametrize("arch,task,hw", [("safeuav-small", Task.HVO, (64, 96)),
                                          ("safeuav-small", Task.DEPTH, (64, 96)),
                                          ("safeuav-large", Task.HVO, (32, 48))])
def test_safeuav_export_round_trip_with_checkpoint(tmp_path, arch, task, hw):
    spec = get_arch(arch)
    source = spec.build(task)
    ckpt = _pkl(tmp_path / "trained.pkl", source)
    out = tmp_path / "model.onnx"
    h, w = hw
    report = export_onnx(spec, task, out, h, w, checkpoint=ckpt, settings=QUIET)
    assert report.max_rel_error <= 1e-3 and report.parameters == sum(p.numel() for p in source.parameters())
    model = OnnxModel.load(out, threads=1)
    c = model.contract
    assert (c.arch, c.task, c.input.layout, c.input.height, c.input.width) == (arch, task, Layout.NHWC, h, w)
    assert c.source["checkpoint"] == "trained.pkl" and c.source["sha256"] == file_sha256(ckpt)
    assert c.source["weights"] == "checkpoint" and c.source["torch"] == torch.__version__ and c.source["date"]
    rgb = np.random.default_rng(0).integers(0, 256, (h, w, 3), dtype=np.uint8)
    pred = model.predict(rgb)
    depth, hvo = _torch_prediction(source, model, rgb)
    if task is Task.DEPTH:
        assert c.depth.convention is DepthConvention.NORMALIZED and pred.depth_m.shape == (h, w)
        np.testing.assert_allclose(pred.depth_m, depth, rtol=1e-4, atol=1e-4)
    else:
        assert pred.hvo_prob.shape == (h, w, 3)
        np.testing.assert_allclose(pred.hvo_prob, hvo, atol=1e-5)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model.onnx", "trained.pkl"]   # no temp left


def test_densedepth_export_round_trip_kitti_range(tmp_path):
    spec = get_arch("densedepth")
    torch.manual_seed(4)
    source = spec.build(Task.DEPTH).eval()
    state = {"module." + k: v for k, v in source.state_dict().items()}
    state["module.encoder.original_model.classifier.weight"] = torch.zeros(1000, 1664)
    state["module.encoder.original_model.classifier.bias"] = torch.zeros(1000)
    torch.save(state, tmp_path / "kitti.pth")
    out = tmp_path / "dd.onnx"
    report = export_onnx(spec, Task.DEPTH, out, 64, 64, checkpoint=tmp_path / "kitti.pth",
                         options={"min_depth": 1.0, "max_depth": 80.0}, settings=QUIET)
    assert report.output_shapes == {"depth": (1, 1, 32, 32)} and report.parameters == 42_657_689
    model = OnnxModel.load(out, threads=1)
    d = model.contract.depth
    assert (d.convention, d.stride, d.min_depth, d.max_depth) == (DepthConvention.INVERSE, 2, 1.0, 80.0)
    assert model.contract.source["dropped_classifier"] is True
    rgb = np.random.default_rng(1).integers(0, 256, (64, 64, 3), dtype=np.uint8)
    want, _ = _torch_prediction(source, model, rgb)
    np.testing.assert_allclose(model.predict(rgb).depth_m, want, rtol=1e-3)


def test_single_file_at_the_requested_opset(small_onnx):
    proto = onnx.load(str(small_onnx), load_external_data=False)
    assert [o.version for o in proto.opset_import if o.domain in ("", "ai.onnx")] == [17]
    assert not any(t.data_location == onnx.TensorProto.EXTERNAL for t in proto.graph.initializer)
    assert [d.dim_value for d in proto.graph.input[0].type.tensor_type.shape.dim] == [1, 32, 48, 3]


def test_random_weights_are_loud_and_recorded(small_onnx, capsys):
    assert OnnxModel.load(small_onnx, threads=1).contract.source["weights"] == "random"
    export_onnx(get_arch("safeuav-small"), Task.HVO, small_onnx.parent / "again.onnx", 16, 16, settings=QUIET)
    assert "RANDOM weights" in capsys.readouterr().err


class _TracesDifferently(torch.nn.Module):
    """Gives other numbers while being exported than when run: the exporter must refuse to write it."""

    def forward(self, x):
        return (x[:, :1] * (3.0 if torch.onnx.is_in_onnx_export() else 1.0),)


def test_disagreeing_export_is_refused_and_leaves_nothing(tmp_path):
    contract = ModelContract(arch="tiny", task=Task.DEPTH, input=InputSpec("image", Layout.NCHW, 16, 16),
                             depth=DepthSpec("depth", DepthConvention.METRIC, 0.1, 10.0))
    spec = ArchSpec(name="tiny", paper="-", tasks=(Task.DEPTH,), default_task=Task.DEPTH, input_hw=(16, 16),
                    size_multiple=8, build=lambda task, **o: _TracesDifferently(),
                    contract=lambda task, h, w, **o: contract, output_names=lambda task: ("depth",),
                    load_checkpoint=None, min_hw=(8, 8))
    with pytest.raises(EdgeError, match="ONNX Runtime and PyTorch disagree: max rel error"):
        export_onnx(spec, Task.DEPTH, tmp_path / "tiny.onnx", 16, 16, settings=QUIET)
    assert list(tmp_path.iterdir()) == []


def test_truncated_and_contract_less_files_are_rejected(small_onnx, tmp_path):
    data = small_onnx.read_bytes()
    (tmp_path / "cut.onnx").write_bytes(data[: len(data) // 3])
    with pytest.raises(ContractError, match="not a loadable ONNX model"):
        OnnxModel.load(tmp_path / "cut.onnx")
    proto = onnx.load(str(small_onnx))
    del proto.metadata_props[:]
    onnx.save(proto, str(tmp_path / "bare.onnx"))
    with pytest.raises(ContractError, match="no model contract"):
        OnnxModel.load(tmp_path / "bare.onnx")


@pytest.mark.parametrize("args,message", [
    (["--arch", "safeuav-small", "--height", "60", "--width", "96"], "multiples of 8"),
    (["--arch", "densedepth", "--height", "32", "--width", "32"], "too small for densedepth"),
    (["--arch", "safeuav-small", "--bins", "80"], "bins do not apply to safeuav-small"),
    (["--arch", "densedepth", "--task", "hvo", "--height", "64", "--width", "64"], "no 'hvo' head"),
    (["--arch", "densedepth", "--min-depth", "20", "--height", "64", "--width", "64"], "0 < min_depth < max_depth"),
    (["--arch", "safeuav-small", "--checkpoint", "nowhere.pkl"], "checkpoint nowhere.pkl does not exist"),
    (["--arch", "safeuav-small", "--option", "filters"], "should be NAME=VALUE"),
    (["--arch", "safeuav-small", "--option", "filters=8"], "filters do not apply to safeuav-small"),
])
def test_cli_bad_input_is_one_line_and_writes_nothing(tmp_path, capsys, args, message):
    out = tmp_path / "m.onnx"
    assert export_main(args + ["--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err
    assert not out.exists()


def test_cli_wrong_checkpoint_names_parameter_and_shapes(tmp_path, capsys):
    spec = get_arch("safeuav-small")
    ckpt = _pkl(tmp_path / "hvo.pkl", spec.build(Task.HVO))
    out = tmp_path / "depth.onnx"
    rc = export_main(["--arch", "safeuav-small", "--task", "depth", "--height", "32", "--width", "32",
                      "--checkpoint", str(ckpt), "--out", str(out), "--quiet"])
    assert rc == 2 and not out.exists()
    err = capsys.readouterr().err
    assert "(parameter 'finalConv.weight') has shape [3, 16, 1, 1]" in err and "expects [1, 16, 1, 1]" in err


def test_cli_exports_with_checkpoint(tmp_path, capsys):
    spec = get_arch("safeuav-small")
    ckpt = _pkl(tmp_path / "depth.pkl", spec.build(Task.DEPTH), key="params")
    out = tmp_path / "sub" / "depth.onnx"
    assert export_main(["--arch", "safeuav-small", "--task", "depth", "--height", "32", "--width", "64",
                        "--max-depth", "300", "--checkpoint", str(ckpt), "--out", str(out), "--quiet"]) == 0
    assert "max rel error" in capsys.readouterr().out
    c = OnnxModel.load(out, threads=1).contract
    assert c.depth.max_depth == 300.0 and c.source["format"] == "safeuav-pkl[params]"


@pytest.mark.slow
@pytest.mark.parametrize("arch,task", [("safeuav-small", "hvo"), ("safeuav-large", "hvo"),
                                       ("safeuav-large", "depth"), ("densedepth", "depth")])
def test_full_size_exports_at_the_papers_input_size(tmp_path, arch, task):
    out = tmp_path / f"{arch}.onnx"
    assert export_main(["--arch", arch, "--task", task, "--out", str(out), "--quiet"]) == 0
    model = OnnxModel.load(out, threads=2)
    assert model.input_hw == get_arch(arch).input_hw
    pred = model.predict(np.zeros((*model.input_hw, 3), np.uint8))
    assert pred.valid
