import numpy as np
import pytest
import torch

from pidg.kernel_math import float32_array, select_distinct_rows


@pytest.mark.parametrize("requires_grad", [False, True])
def test_float32_array_views_contiguous_float32_and_copies_the_rest(requires_grad):
    t = torch.arange(12, dtype=torch.float32).reshape(4, 3).requires_grad_(requires_grad)
    view = float32_array(t)
    assert view.dtype == np.float32 and view.flags.c_contiguous and np.array_equal(view, t.detach().numpy())
    assert np.shares_memory(view, t.detach().numpy())  # no copy of a tensor that already is what the kernels take
    for other in (t.detach().T, t.detach().double(), t.detach()[:, 1]):  # strided, float64, a column view
        copy = float32_array(other)
        assert copy.dtype == np.float32 and copy.flags.c_contiguous
        assert np.array_equal(copy, other.to(torch.float32).numpy())
    rows = float32_array(t.detach()[1:3])  # a contiguous slice at an offset is viewed, not copied
    assert np.array_equal(rows, t.detach().numpy()[1:3]) and np.shares_memory(rows, t.detach().numpy())


def test_zeroed_buffer_pool_reuses_a_buffer_only_once_released():
    from pidg.kernel_math import ZeroedBufferPool

    pool = ZeroedBufferPool(per_shape=2)
    first = pool.zeros(5, 3)
    assert first.shape == (5, 3) and first.dtype == np.float32 and not first.any()
    first[:] = 7.0
    held = torch.from_numpy(first)  # a tensor over it (a gradient handed to autograd) keeps it in use
    del first
    second = pool.zeros(5, 3)
    assert not second.any() and (held == 7.0).all()  # a new buffer; the held one is untouched
    second_id = id(second)
    second[1, 1] = 4.0
    del second
    again = pool.zeros(5, 3)
    assert id(again) == second_id and not again.any()  # released: reused, and zeroed again
    assert pool.zeros(2, 2, 2).shape == (2, 2, 2)  # any number of dimensions


def test_zeroed_buffer_pool_re_zeroes_only_the_rows_its_holder_announced():
    """A holder that writes some rows only says which; the next holder gets those rows zeroed (int rows, or a bool mask
    over the first axis), and a holder that announced none gets the whole buffer zeroed."""
    from pidg.kernel_math import ZeroedBufferPool

    pool = ZeroedBufferPool(per_shape=1)
    buf = pool.zeros(6, 4, rows=np.array([1, 4]))
    buf[[1, 4]] = 3.0
    buf_id = id(buf)
    del buf
    again = pool.zeros(6, 4, rows=np.array([True, False, False, False, False, True]))
    assert id(again) == buf_id and not again.any()
    again[[0, 5]] = 2.0
    del again
    whole = pool.zeros(6, 4)  # the previous holder wrote rows 0 and 5: zeroed; this one announces nothing
    assert not whole.any()
    whole[:] = 1.0
    del whole
    assert not pool.zeros(6, 4).any()  # all of it zeroed again
    marked = pool.zeros(6, 4, rows=np.array([2]))
    marked[2] = 5.0
    marked[3] = 9.0  # outside the announced rows: the pool does not clean it (the caller's contract)
    del marked
    assert pool.zeros(6, 4)[3].tolist() == [9.0] * 4


def test_quotient_where_at_least_matches_its_definition():
    from pidg.kernel_math import quotient_where_at_least

    num = torch.tensor([[1.0, 2.0, 3.0], [4.0, -5.0, 6.0]])
    den = torch.tensor([[0.5, 0.25, 0.0], [2.0, 1.0, 0.2499]])
    out = quotient_where_at_least(num, den, 0.25)
    assert out.dtype == torch.float32 and out.shape == (2, 3)
    assert out.tolist() == [[2.0, 8.0, 0.0], [2.0, -5.0, 0.0]]
    strided = quotient_where_at_least(num.T, den.T, 0.25)  # any layout: the kernel reads a contiguous copy
    assert strided.tolist() == out.T.tolist()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_select_distinct_rows_is_index_select_with_its_gradient(dtype):
    """select_distinct_rows (the flow loss's gather of supervised pixels) against index_select: values and gradients
    equal, and a gradient still held is not overwritten by the next backward (on float32 CPU the gradient is a pooled
    buffer)."""
    g = torch.Generator().manual_seed(5)
    image = torch.randn(400, 3, generator=g, dtype=dtype, requires_grad=True)
    index = torch.randperm(400, generator=g)[: 400 // 3]
    weights = [torch.randn(index.numel(), 3, generator=g, dtype=dtype) for _ in range(2)]
    rows = select_distinct_rows(image, index)
    assert torch.equal(rows, image.index_select(0, index))
    (first,) = torch.autograd.grad((rows * weights[0]).sum(), image)
    kept = first.clone()
    (second,) = torch.autograd.grad((select_distinct_rows(image, index) * weights[1]).sum(), image)
    (reference,) = torch.autograd.grad((image.index_select(0, index) * weights[1]).sum(), image)
    assert torch.equal(second, reference) and torch.equal(first, kept)  # the held gradient is intact
    assert not torch.equal(first, second)
    del first, second
    (third,) = torch.autograd.grad((select_distinct_rows(image, index[:5]) * weights[0][:5]).sum(), image)
    (reference,) = torch.autograd.grad((image.index_select(0, index[:5]) * weights[0][:5]).sum(), image)
    assert torch.equal(third, reference)  # a reused buffer is zero outside the new rows


@pytest.mark.parametrize("gather_last", [True, False])
@pytest.mark.parametrize("leaf", [True, False])
def test_select_distinct_rows_keeps_other_gradients_out_of_its_pooled_buffer(gather_last, leaf):
    """Autograd adds two gradients of one tensor in place into either when only it refers to that one: had the pooled
    buffer been that one, the other gradient would fill rows the pool does not re-zero, and the buffer's next user
    would start from them. Both orders of the two uses, on a leaf and on an intermediate tensor."""
    from pidg.kernel_math import ZEROED_BUFFERS

    n = 997  # a shape of its own in the process's pool
    source = torch.randn(n, 4, requires_grad=True)
    x = source if leaf else source * 1.0
    index = torch.arange(0, n, 10)
    if gather_last:
        loss = (x * 3.0).sum() + select_distinct_rows(x, index).sum()
    else:
        loss = select_distinct_rows(x, index).sum() + (x * 3.0).sum()
    loss.backward()
    assert torch.equal(source.grad, torch.full((n, 4), 3.0).index_fill(0, index, 4.0))
    source.grad = None
    del loss, x
    assert not ZEROED_BUFFERS.zeros(n, 4).any()  # the same buffer, released and re-zeroed at its rows
