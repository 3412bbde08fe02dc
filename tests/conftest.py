"""Fixtures shared by the torch-side tests (export, zoo, checkpoints)."""
import pytest


@pytest.fixture(scope="module")
def one_torch_thread():
    """The test machine's cores are shared: keep torch to one thread in a module, as the project asks."""
    torch = pytest.importorskip("torch")
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="module")
def densedepth(one_torch_thread):
    """DenseNet-169 is big: build DenseDepth once per module (seeded, eval mode)."""
    torch = pytest.importorskip("torch")
    from edge_landing.export.zoo import get_arch
    from edge_landing.runtime.perception.contract import Task

    torch.manual_seed(0)
    return get_arch("densedepth").build(Task.DEPTH).eval()


@pytest.fixture(autouse=True)
def _probe_cache_in_tmp(tmp_path_factory, monkeypatch):
    """edge-run caches its FP32/INT8 speed probe under ~/.cache; tests keep it in a temporary folder."""
    monkeypatch.setenv("EDGE_LANDING_CACHE", str(tmp_path_factory.getbasetemp() / "edge-landing-cache"))
