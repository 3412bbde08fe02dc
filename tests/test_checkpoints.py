"""The authors' checkpoint formats, written here in their containers, then loaded strictly."""
import re

import pytest

torch = pytest.importorskip("torch")

from edge_landing.export.checkpoints import (  # noqa: E402
    load_state_dict_strict,
    strip_prefix,
    trusted_checkpoints,
)
from edge_landing.export.zoo import get_arch  # noqa: E402
from edge_landing.export.zoo.densedepth import CLASSIFIER_PREFIX  # noqa: E402
from edge_landing.runtime.core.errors import InputError  # noqa: E402
from edge_landing.runtime.perception.contract import Task  # noqa: E402

# Keep torch to one thread in this module (tests/conftest.py).
pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def authors_state(densedepth):
    """A DenseDepth state_dict as the authors' script saves it: new values, with the DenseNet classifier."""
    gen = torch.Generator().manual_seed(1)
    state = {k: (torch.randn(v.shape, generator=gen) if v.is_floating_point() else v.clone() + 7)
             for k, v in densedepth.state_dict().items()}
    state[CLASSIFIER_PREFIX + "weight"] = torch.randn(1000, 1664, generator=gen)
    state[CLASSIFIER_PREFIX + "bias"] = torch.zeros(1000)
    return state


def _assert_loaded(model, state):
    loaded = model.state_dict()
    for key in ("encoder.original_model.features.conv0.weight", "decoder.up3.convB.bias", "decoder.conv3.weight",
                "encoder.original_model.features.denseblock4.denselayer32.norm2.running_var"):
        assert torch.equal(loaded[key], state[key]), key


@pytest.mark.parametrize("classifier,prefix", [(True, "module."), (False, "")])
def test_densedepth_state_dict_variants_load(tmp_path, densedepth, authors_state, classifier, prefix):
    state = {prefix + k: v for k, v in authors_state.items() if classifier or not k.startswith(CLASSIFIER_PREFIX)}
    path = tmp_path / "nyu.pth"
    torch.save(state, path)
    info = get_arch("densedepth").load_checkpoint(densedepth, path)
    _assert_loaded(densedepth, authors_state)
    assert info["checkpoint"] == "nyu.pth" and len(info["sha256"]) == 64
    assert info["dropped_classifier"] is classifier


def test_densedepth_state_dict_nested_and_without_bn_counters_loads(tmp_path, densedepth, authors_state):
    # Training scripts nest it under "model"; files converted from Keras lack BatchNorm's step counter.
    state = {k: v for k, v in authors_state.items() if not k.endswith("num_batches_tracked")}
    torch.save({"model": state, "epoch": 3}, tmp_path / "nested.pth")
    get_arch("densedepth").load_checkpoint(densedepth, tmp_path / "nested.pth")
    _assert_loaded(densedepth, authors_state)


def test_densedepth_shape_mismatch_names_parameter_and_both_shapes(tmp_path, densedepth, authors_state):
    state = dict(authors_state)
    state["decoder.conv3.weight"] = torch.zeros(2, 104, 3, 3)
    torch.save(state, tmp_path / "bad.pth")
    with pytest.raises(InputError) as err:
        get_arch("densedepth").load_checkpoint(densedepth, tmp_path / "bad.pth")
    msg = str(err.value)
    assert "'decoder.conv3.weight'" in msg and "[2, 104, 3, 3]" in msg and "[1, 104, 3, 3]" in msg
    assert "bad.pth" in msg and "\n" not in msg


def test_missing_and_unexpected_keys_are_named(densedepth, authors_state):
    state = {k: v for k, v in authors_state.items() if k != "decoder.up2.convA.bias"}
    state["decoder.extra.weight"] = torch.zeros(1)
    with pytest.raises(InputError, match=r"missing 1 key\(s\): decoder.up2.convA.bias.*unexpected.*decoder.extra"):
        load_state_dict_strict(densedepth, strip_prefix(state), "ckpt")


def test_wrong_file_is_one_clear_error(tmp_path, densedepth):
    garbage = tmp_path / "notes.pth"
    garbage.write_bytes(b"this is not a checkpoint")
    with pytest.raises(InputError, match="could not be read as a PyTorch file"):
        get_arch("densedepth").load_checkpoint(densedepth, garbage)
    torch.save({"weights": [torch.zeros(3)]}, tmp_path / "safeuav.pkl")
    with pytest.raises(InputError, match="holds no tensors"):
        get_arch("densedepth").load_checkpoint(densedepth, tmp_path / "safeuav.pkl")
    with pytest.raises(InputError, match="does not exist"):
        get_arch("densedepth").load_checkpoint(densedepth, tmp_path / "missing.pth")


def _safeuav_pkl(path, model, key, seed=2):
    """The authors' container: torch.save of a dict holding an ordered list of parameter tensors."""
    gen = torch.Generator().manual_seed(seed)
    tensors = [torch.randn(p.shape, generator=gen) * 0.05 for p in model.parameters()]
    torch.save({key: tensors, "optimizer": {"state": {}}, "history_dict": {}}, path)
    return tensors


@pytest.mark.parametrize("arch,key", [("safeuav-large", "weights"), ("safeuav-small", "weights"),
                                      ("safeuav-small", "params")])
def test_safeuav_pkl_loads_by_position(tmp_path, arch, key):
    spec = get_arch(arch)
    source, target = spec.build(Task.HVO), spec.build(Task.HVO)
    tensors = _safeuav_pkl(tmp_path / "model.pkl", source, key)
    info = spec.load_checkpoint(target, tmp_path / "model.pkl")
    assert info["format"] == f"safeuav-pkl[{key}]" and info["checkpoint"] == "model.pkl"
    for param, tensor in zip(target.parameters(), tensors):
        assert torch.equal(param.detach(), tensor)
    # Same weights, same function.
    x = torch.rand(1, 16, 24, 3)
    source.load_state_dict(target.state_dict())
    with torch.no_grad():
        assert torch.equal(source(x)[0], target(x)[0])


def test_safeuav_wrong_head_names_parameter_and_both_shapes(tmp_path):
    spec = get_arch("safeuav-small")
    _safeuav_pkl(tmp_path / "hvo.pkl", spec.build(Task.HVO), "weights")
    with pytest.raises(InputError) as err:
        spec.load_checkpoint(spec.build(Task.DEPTH), tmp_path / "hvo.pkl")
    msg = str(err.value)
    assert re.search(r"tensor #36 \(parameter 'finalConv.weight'\) has shape \[3, 16, 1, 1\].*expects \[1, 16, 1, 1\]",
                     msg), msg


def test_safeuav_wrong_count_and_wrong_container(tmp_path):
    small, large = get_arch("safeuav-small"), get_arch("safeuav-large")
    _safeuav_pkl(tmp_path / "small.pkl", small.build(Task.HVO), "weights")
    with pytest.raises(InputError, match="holds 38 tensors but the model has 44 parameters"):
        large.load_checkpoint(large.build(Task.HVO), tmp_path / "small.pkl")
    torch.save({"state_dict": {"a": torch.zeros(1)}}, tmp_path / "other.pkl")
    with pytest.raises(InputError, match="no key 'weights' or 'params'"):
        small.load_checkpoint(small.build(Task.HVO), tmp_path / "other.pkl")
    torch.save({"weights": {"a": torch.zeros(1)}}, tmp_path / "dict.pkl")
    with pytest.raises(InputError, match="'weights' should be a list of tensors"):
        small.load_checkpoint(small.build(Task.HVO), tmp_path / "dict.pkl")


def test_old_containers_legacy_format_and_trusted_objects(tmp_path):
    spec = get_arch("safeuav-small")
    model = spec.build(Task.HVO)
    tensors = [torch.full(p.shape, 0.5) for p in model.parameters()]
    # Pre-1.6 PyTorch wrote the legacy (non-zip) format: still readable without unpickling code.
    torch.save({"params": tensors}, tmp_path / "legacy.pkl", _use_new_zipfile_serialization=False)
    spec.load_checkpoint(model, tmp_path / "legacy.pkl")
    assert all(torch.equal(p.detach(), t) for p, t in zip(model.parameters(), tensors))
    # Files that also pickle other objects (numpy values in the training history) need explicit trust.
    np = pytest.importorskip("numpy")
    torch.save({"weights": tensors, "history_dict": {"loss": np.float64(0.25)}}, tmp_path / "history.pkl")
    with pytest.raises(InputError, match=r"holds Python objects besides tensors .*--trust-checkpoint"):
        spec.load_checkpoint(model, tmp_path / "history.pkl")
    with trusted_checkpoints():
        info = spec.load_checkpoint(spec.build(Task.HVO), tmp_path / "history.pkl")
    assert info["format"] == "safeuav-pkl[weights]"
