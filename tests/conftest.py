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
