import numpy as np
import pytest
import torch

from pidg.kernel_math import float32_array


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
