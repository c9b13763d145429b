"""Linear layers whose products run on more torch threads inside ``matmul_threads``: the same values and gradients
as ``F.linear``, the products on the asked count, the caller's count back afterwards."""
import pidg  # noqa: F401  (sets OMP_WAIT_POLICY before torch is imported)

import pytest
import torch
import torch.nn.functional as F

from pidg.models import parallel_linear
from pidg.models.parallel_linear import Linear, linear, matmul_threads


def _inputs(leading: tuple[int, ...], bias: bool, dtype=torch.float32):
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(*leading, 24, generator=gen, dtype=dtype)
    weight = torch.randn(7, 24, generator=gen, dtype=dtype)
    b = torch.randn(7, generator=gen, dtype=dtype) if bias else None
    grad = torch.randn(*leading, 7, generator=gen, dtype=dtype)
    return x, weight, b, grad


def _values_and_grads(fn, x, weight, bias, grad):
    leaves = [t.clone().requires_grad_(True) if t is not None else None for t in (x, weight, bias)]
    out = fn(*leaves)
    out.backward(grad)
    return [out.detach()] + [t.grad if t is not None else None for t in leaves]


@pytest.fixture
def one_torch_thread():
    caller = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(caller)


@pytest.mark.parametrize("leading", [(37,), (4, 37)])  # a layer's rows, and the jet's [4, M, W] tangents
@pytest.mark.parametrize("bias", [True, False])
def test_linear_on_more_threads_matches_f_linear_and_restores_the_count(one_torch_thread, leading, bias):
    x, weight, b, grad = _inputs(leading, bias)
    expected = _values_and_grads(F.linear, x, weight, b, grad)
    with matmul_threads(2):
        got = _values_and_grads(linear, x, weight, b, grad)
        assert torch.get_num_threads() == 1
    for name, e, g in zip(["out", "d x", "d weight", "d bias"], expected, got):
        if e is None:
            assert g is None, name
            continue
        torch.testing.assert_close(g, e, rtol=1e-6, atol=1e-5, msg=name)  # sums of 148 products in another order


def test_products_run_on_the_asked_threads_forward_and_backward(one_torch_thread, monkeypatch):
    """Every thread count set while the layer runs: 2 for its products, then the caller's 1 again."""
    calls: list[int] = []
    set_threads = torch.set_num_threads
    monkeypatch.setattr(torch, "set_num_threads", lambda n: (calls.append(n), set_threads(n))[1])
    x, weight, b, grad = _inputs((37,), True)
    with matmul_threads(2):
        forward = _values_and_grads(lambda *a: linear(*a), x, weight, b, grad)
    assert calls == [2, 1, 2, 1]  # forward, then backward
    assert forward[0].shape == (37, 7)


def test_outside_the_context_and_off_cpu_float32_nothing_switches(one_torch_thread, monkeypatch):
    calls: list[int] = []
    monkeypatch.setattr(torch, "set_num_threads", lambda n: calls.append(n))
    x, weight, b, grad = _inputs((5,), True)
    out = linear(x, weight, b)
    assert torch.equal(out, F.linear(x, weight, b))
    with matmul_threads(2):
        linear(x.double(), weight.double(), b.double())  # float64 (checks and references) is left alone
    with matmul_threads(0):  # 0: no switch
        linear(x, weight, b)
    assert calls == [] and parallel_linear._threads is None


def test_no_grad_switches_around_the_product_only(one_torch_thread):
    x, weight, b, _ = _inputs((5,), True)
    with matmul_threads(2), torch.no_grad():
        out = linear(x, weight, b)
        assert torch.get_num_threads() == 1 and out.grad_fn is None
    torch.testing.assert_close(out, F.linear(x, weight, b))


def test_linear_module_keeps_nn_linear_parameters_and_state_dict():
    torch.manual_seed(0)
    layer = Linear(3, 2)
    reference = torch.nn.Linear(3, 2)
    reference.load_state_dict(layer.state_dict())
    x = torch.randn(4, 3)
    assert set(layer.state_dict()) == {"weight", "bias"}
    with matmul_threads(2):
        torch.testing.assert_close(layer(x), reference(x))
