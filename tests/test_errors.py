"""The finiteness test behind NonFiniteError: one sum first, the elementwise test where the sum cannot decide."""
import pidg  # noqa: F401  (sets OMP_WAIT_POLICY before torch is imported)

import torch

from pidg.errors import all_finite


def test_all_finite_agrees_with_the_elementwise_test():
    x = torch.randn(1000, 3)
    assert all_finite(x) and all_finite(torch.zeros(0, 3)) and all_finite(torch.arange(5))
    for bad in (float("nan"), float("inf"), float("-inf")):
        y = x.clone()
        y[517, 2] = bad
        assert not all_finite(y)
    both = x.clone()
    both[3, 0], both[9, 1] = float("inf"), float("-inf")  # their sum is NaN, not a cancellation to a finite value
    assert not all_finite(both)
    huge = torch.full((4,), 3e38)  # finite values whose float32 sum overflows: the elementwise test decides
    assert torch.isinf(huge.sum()) and all_finite(huge)
    assert not all_finite(torch.cat([huge, torch.tensor([float("nan")])]))
