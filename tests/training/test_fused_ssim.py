import pidg  # noqa: F401
import pytest
import torch
import torch.nn.functional as F

from pidg.metrics import ssim
from pidg.training.fused_ssim import blur, fused_ssim, gaussian_window_1d


def test_blur_matches_zero_padded_conv2d():
    maps = torch.rand(4, 23, 37, generator=torch.Generator().manual_seed(0))
    k = torch.from_numpy(gaussian_window_1d())
    win = (k[:, None] * k[None, :]).expand(4, 1, 11, 11)
    expected = F.conv2d(maps.unsqueeze(0), win, padding=5, groups=4)[0]
    assert torch.allclose(blur(maps), expected, atol=1e-6)


def test_fused_ssim_value_and_gradient_match_the_autograd_reference():
    g = torch.Generator().manual_seed(1)
    gt = torch.rand(29, 41, 3, generator=g, dtype=torch.float64)
    pred = (gt + 0.2 * torch.randn(29, 41, 3, generator=g, dtype=torch.float64)).clamp(0, 1)
    ref_in = pred.clone().requires_grad_(True)
    ref = ssim(ref_in, gt, padding="zeros")
    ref.backward()
    fused_in = pred.to(torch.float32).requires_grad_(True)
    value = fused_ssim(fused_in, gt.to(torch.float32))
    (3.0 * value).backward()
    assert abs(float(value.detach()) - float(ref.detach())) < 1e-6
    rel = (fused_in.grad.double() - 3.0 * ref_in.grad).abs().max() / ref_in.grad.abs().max()
    assert rel < 1e-4


def test_fused_ssim_rejects_mismatched_shapes():
    with pytest.raises(ValueError, match="shapes differ"):
        fused_ssim(torch.rand(20, 20, 3), torch.rand(20, 21, 3))
